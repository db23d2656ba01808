// The stage-1 anchor representation (train/anchors/anchor_model.h) and the expansion
// kernels (train/anchors/expander.h, kernels/expander.cl): voxel grid math,
// initialisation, growing and pruning bookkeeping, the archive, and the
// device expansion forward and backward against double-precision references
// and central finite differences, alone and chained through the renderer.
#include <gtest/gtest.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <functional>
#include <numeric>
#include <random>
#include <set>
#include <string>
#include <tuple>
#include <vector>

#include "host/io/model_io.h"
#include "tests/io_test_util.h"
#include "tests/reference/expander_reference.h"
#include "tests/reference/reference_renderer.h"
#include "tests/test_util.h"
#include "train/anchors/anchor_model.h"
#include "train/anchors/expander.h"

namespace ag2gs {
namespace {

constexpr double kC0 = 0.28209479177387814;

double sigmoid(double x) {
  return 1.0 / (1.0 + std::exp(-x));
}

Eigen::Vector3i cell_at(const AnchorModel& m, size_t a) {
  return Eigen::Vector3i(m.cell()[3 * a], m.cell()[3 * a + 1], m.cell()[3 * a + 2]);
}

// A grid with origin 0 and unit top voxels (exact cell arithmetic).
VoxelGrid unit_grid(const AnchorConfig& c) {
  VoxelGrid g;
  g.origin = Eigen::Vector3d::Zero();
  g.top_voxel = 1.0;
  g.layer_ratio = c.layer_ratio;
  g.layers = c.layers;
  return g;
}

std::vector<Eigen::Vector3d> random_points(size_t n, double extent, uint32_t seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(-extent, extent);
  std::vector<Eigen::Vector3d> p(n);
  for (auto& x : p) x = Eigen::Vector3d(u(rng), u(rng), u(rng));
  return p;
}

std::vector<Eigen::Vector3<uint8_t>> random_colors(size_t n, uint32_t seed) {
  std::mt19937 rng(seed);
  std::vector<Eigen::Vector3<uint8_t>> c(n);
  for (auto& x : c) x = Eigen::Vector3<uint8_t>(rng() & 255, rng() & 255, rng() & 255);
  return c;
}

// Randomises every trained parameter of `m` (positions stay at voxel centres).
// wild: logits up to +-30 and offsets beyond the voxel, the range training can reach.
void randomise(AnchorModel& m, uint32_t seed, bool wild) {
  std::mt19937 rng(seed);
  auto u = [&](double lo, double hi) {
    return static_cast<float>(std::uniform_real_distribution<double>(lo, hi)(rng));
  };
  std::normal_distribution<double> nrm(0, 1);
  const double lw = wild ? 30 : 3;
  for (float& x : m.feature()) x = u(-1, 1);
  for (float& x : m.offset()) x = u(wild ? -2 : -0.4, wild ? 2 : 0.4);
  for (float& x : m.scale_logit()) x = u(-lw, wild ? lw : 0.5);
  for (float& x : m.quat()) x = static_cast<float>(nrm(rng));
  for (float& x : m.opacity_logit()) x = u(-lw, lw);
  for (size_t i = 0; i < m.sh().size(); ++i) m.sh()[i] = u(-1, 1) * (i % 48 < 3 ? 1.f : 0.3f);
}

// A model of about `target` anchors (random points, init layer 0) with random parameters.
AnchorModel random_model(size_t points, uint32_t seed, bool wild, float scale_cap = 1.f) {
  AnchorConfig c;
  c.scale_cap = scale_cap;
  VoxelGrid g = unit_grid(c);
  g.top_voxel = 0.25;
  g.origin = Eigen::Vector3d(-1.05, -0.95, -1.01);
  AnchorModel m;
  m.initialise_from_points(random_points(points, 1.0, seed), random_colors(points, seed + 1), g, c, seed);
  randomise(m, seed + 2, wild);
  return m;
}

template <typename T>
bool same_bytes(const std::vector<T>& a, const std::vector<T>& b) {
  return a.size() == b.size() && (a.empty() || std::memcmp(a.data(), b.data(), a.size() * sizeof(T)) == 0);
}

bool same_arrays(const ModelArchive& a, const ModelArchive& b) {
  if (a.arrays().size() != b.arrays().size()) return false;
  for (const auto& [name, t] : a.arrays()) {
    if (!b.has(name)) return false;
    const Tensor& u = b.tensor(name);
    if (u.dtype != t.dtype || u.shape != t.shape || u.bytes != t.bytes) return false;
  }
  return true;
}

// ---------------------------------------------------------------------------
// Voxel grid

TEST(VoxelGrid, SizesCellsCentresAndNesting) {
  SceneBounds b;
  b.lo = Eigen::Vector3d(-1, -2, 0.5);
  b.hi = Eigen::Vector3d(3, 0, 1.5);  // longest extent 4
  AnchorConfig c;
  c.top_cells = 200;
  const VoxelGrid g = VoxelGrid::from_bounds(b, c);
  EXPECT_EQ(g.origin, b.lo);
  EXPECT_DOUBLE_EQ(g.top_voxel, 4.0 / 200);
  EXPECT_EQ(g.layers, 3);
  EXPECT_DOUBLE_EQ(g.voxel(1), g.top_voxel / 4);
  EXPECT_DOUBLE_EQ(g.voxel(2), g.top_voxel / 16);

  EXPECT_EQ(g.cell_of(0, b.lo + Eigen::Vector3d::Constant(1e-9)), Eigen::Vector3i(0, 0, 0));
  EXPECT_EQ(g.cell_of(0, b.lo - Eigen::Vector3d::Constant(1e-9)), Eigen::Vector3i(-1, -1, -1));
  EXPECT_EQ(g.cell_of(0, b.lo + Eigen::Vector3d(0.031, 0.5, -0.05)), Eigen::Vector3i(1, 25, -3));
  EXPECT_EQ(g.cell_of(0, Eigen::Vector3d(NAN, 0, 0)).x(), -(1 << 30));  // clamped, never UB
  EXPECT_EQ(g.cell_of(0, Eigen::Vector3d(1e300, 0, 0)).x(), 1 << 30);

  std::mt19937 rng(3);
  std::uniform_int_distribution<int> ci(-500, 500);
  for (int layer = 0; layer < 3; ++layer)
    for (int i = 0; i < 200; ++i) {
      const Eigen::Vector3i cell(ci(rng), ci(rng), ci(rng));
      const Eigen::Vector3d p = g.centre(layer, cell);
      EXPECT_EQ(g.cell_of(layer, p), cell);
      EXPECT_NEAR((p - b.lo).x(), (cell.x() + 0.5) * g.voxel(layer), 1e-12);
    }
  // Layers nest: the parent of a point's fine cell is its coarse cell.
  for (const Eigen::Vector3d& p : random_points(5000, 5.0, 4))
    for (int fine = 1; fine < 3; ++fine)
      for (int coarse = 0; coarse <= fine; ++coarse)
        ASSERT_EQ(g.parent_cell(fine, g.cell_of(fine, p), coarse), g.cell_of(coarse, p));
  EXPECT_EQ(g.parent_cell(1, Eigen::Vector3i(-1, -4, -5), 0), Eigen::Vector3i(-1, -1, -2));
  EXPECT_EQ(g.parent_cell(2, Eigen::Vector3i(15, 16, -17), 0), Eigen::Vector3i(0, 1, -2));
  EXPECT_THROW(g.parent_cell(0, Eigen::Vector3i(0, 0, 0), 1), std::invalid_argument);

  // Degenerate boxes fall back to the camera rig, then fail clearly.
  SceneBounds flat;
  flat.lo = flat.hi = Eigen::Vector3d(1, 1, 1);
  flat.camera_radius = 2;
  EXPECT_DOUBLE_EQ(VoxelGrid::from_bounds(flat, c).top_voxel, 4.0 / 200);
  flat.camera_radius = 0;
  test::expect_error_with<std::invalid_argument>([&] { VoxelGrid::from_bounds(flat, c); }, {"bounds are empty"});
  c.init_layer = 3;
  test::expect_error_with<std::invalid_argument>([&] { VoxelGrid::from_bounds(b, c); }, {"init_layer"});
}

TEST(VoxelGrid, KeysAreInjectiveAndOrdered) {
  std::vector<std::tuple<int, int, int, int>> tuples;
  for (int l : {0, 1, 15})
    for (int x : {-kMaxAnchorCell, -1, 0, 1, kMaxAnchorCell - 1})
      for (int y : {-kMaxAnchorCell, -7, 0, kMaxAnchorCell - 1})
        for (int z : {-kMaxAnchorCell, 0, 3, kMaxAnchorCell - 1}) tuples.emplace_back(l, x, y, z);
  std::vector<std::pair<uint64_t, size_t>> keys;
  for (size_t i = 0; i < tuples.size(); ++i) {
    auto [l, x, y, z] = tuples[i];
    keys.emplace_back(anchor_voxel_key(l, Eigen::Vector3i(x, y, z)), i);
  }
  std::sort(keys.begin(), keys.end());
  for (size_t i = 1; i < keys.size(); ++i) {
    EXPECT_LT(keys[i - 1].first, keys[i].first);                    // injective
    EXPECT_LT(tuples[keys[i - 1].second], tuples[keys[i].second]);  // same order as the tuples
  }
  EXPECT_THROW(anchor_voxel_key(0, Eigen::Vector3i(kMaxAnchorCell, 0, 0)), std::out_of_range);
  EXPECT_THROW(anchor_voxel_key(16, Eigen::Vector3i(0, 0, 0)), std::out_of_range);
}

// ---------------------------------------------------------------------------
// Initialisation

TEST(AnchorInit, OneAnchorPerOccupiedVoxelWithMeanColour) {
  AnchorConfig c;
  const VoxelGrid g = unit_grid(c);
  // Voxels (1,0,0): 2 points, (0,0,0): 3 points, (2,-1,0): 1 point; one NaN point.
  const std::vector<Eigen::Vector3d> pts = {{1.5, 0.2, 0.9}, {0.1, 0.1, 0.1},  {2.2, -0.5, 0.3}, {0.9, 0.9, 0.9},
                                            {NAN, 0, 0},     {1.01, 0.7, 0.2}, {0.5, 0.2, 0.7}};
  const std::vector<Eigen::Vector3<uint8_t>> col = {{10, 20, 30}, {255, 0, 0},  {7, 7, 7},  {0, 255, 0},
                                                    {1, 1, 1},    {30, 40, 50}, {0, 0, 255}};
  AnchorModel m;
  const AnchorInitStats st = m.initialise_from_points(pts, col, g, c, 42);
  EXPECT_EQ(st.points_used, 6u);
  EXPECT_EQ(st.points_skipped, 1u);
  EXPECT_EQ(st.anchors_per_layer, (std::vector<size_t>{3, 0, 0}));
  ASSERT_EQ(m.size(), 3u);
  EXPECT_EQ(m.gaussians(), 15u);
  m.check();
  // (layer, cell) order.
  const Eigen::Vector3i cells[3] = {{0, 0, 0}, {1, 0, 0}, {2, -1, 0}};
  const Eigen::Vector3d mean_col[3] = {Eigen::Vector3d(255, 255, 255) / 3.0 / 255.0,
                                       Eigen::Vector3d(40, 60, 80) / 2.0 / 255.0, Eigen::Vector3d(7, 7, 7) / 255.0};
  for (int a = 0; a < 3; ++a) {
    EXPECT_EQ(cell_at(m, a), cells[a]);
    EXPECT_EQ(m.layer()[a], 0);
    EXPECT_EQ(m.find(0, cells[a]), a);
    EXPECT_EQ(m.voxel()[a], 1.f);
    for (int k = 0; k < 3; ++k) {
      EXPECT_EQ(m.pos()[3 * a + k], static_cast<float>(cells[a][k] + 0.5));
      EXPECT_LE(std::abs(m.feature()[3 * a + k]), c.init_feature);
    }
    for (int i = 0; i < 5; ++i) {
      const size_t gi = a * 5 + i;
      for (int k = 0; k < 3; ++k) {
        EXPECT_NEAR(m.sh()[gi * 48 + k], (mean_col[a][k] - 0.5) / kC0, 1e-6);
        EXPECT_GE(m.offset()[gi * 3 + k], -0.5f);
        EXPECT_LE(m.offset()[gi * 3 + k], 0.5f);
        EXPECT_NEAR(sigmoid(m.scale_logit()[gi * 3 + k]), c.init_scale, 1e-7);
      }
      for (int k = 3; k < 48; ++k) EXPECT_EQ(m.sh()[gi * 48 + k], 0.f);
      EXPECT_NEAR(sigmoid(m.opacity_logit()[gi]), c.init_opacity, 1e-7);
      Eigen::Vector4d q;
      for (int k = 0; k < 4; ++k) q[k] = m.quat()[gi * 4 + k];
      EXPECT_NEAR(q.norm(), 1.0, 1e-6);
      EXPECT_NEAR(q[0], 1.0, 1e-3);
      EXPECT_GT((q - Eigen::Vector4d(1, 0, 0, 0)).norm(), 0.0);  // perturbed
    }
  }
  // Empty voxels have no anchor, on any layer.
  EXPECT_EQ(m.find(0, Eigen::Vector3i(0, 1, 0)), -1);
  EXPECT_EQ(m.find(0, Eigen::Vector3i(2, 0, 0)), -1);
  EXPECT_EQ(m.find(1, Eigen::Vector3i(0, 0, 0)), -1);
  EXPECT_EQ(m.find(7, Eigen::Vector3i(0, 0, 0)), -1);

  // Children spread over the voxel: offsets are not all alike.
  std::set<float> xs(m.offset().begin(), m.offset().end());
  EXPECT_GT(xs.size(), 40u);
  // No colours: grey DC = 0.
  m.initialise_from_points(pts, {}, g, c, 42);
  for (size_t gi = 0; gi < m.gaussians(); ++gi) EXPECT_EQ(m.sh()[gi * 48], 0.f);
  EXPECT_THROW(m.initialise_from_points(pts, {col[0]}, g, c, 42), std::invalid_argument);
}

// --init-children-at-points: children sit on their voxel's points with the
// points' colours; children beyond the points keep the random offset and the
// mean colour of the default.
TEST(AnchorInit, ChildrenAtPointsTakeThePointsPlacesAndColours) {
  AnchorConfig c;
  const VoxelGrid g = unit_grid(c);
  // Voxel (0,0,0): 7 points (more than K = 5); voxel (1,0,0): 2 points.
  std::vector<Eigen::Vector3d> pts;
  std::vector<Eigen::Vector3<uint8_t>> col;
  for (int i = 0; i < 7; ++i) {
    pts.emplace_back(0.1 + 0.11 * i, 0.9 - 0.1 * i, 0.05 + 0.13 * i);
    col.emplace_back(static_cast<uint8_t>(30 * i), 100, static_cast<uint8_t>(255 - 30 * i));
  }
  pts.emplace_back(1.2, 0.3, 0.4);
  col.emplace_back(200, 10, 10);
  pts.emplace_back(1.8, 0.6, 0.5);
  col.emplace_back(10, 200, 10);
  AnchorModel plain, at;
  plain.initialise_from_points(pts, col, g, c, 5);
  c.init_children_at_points = true;
  at.initialise_from_points(pts, col, g, c, 5);
  ASSERT_EQ(at.size(), 2u);
  at.check();
  auto child_on_point = [&](size_t gi) {
    const size_t a = gi / 5;
    for (size_t p = 0; p < pts.size(); ++p) {
      bool same = true;
      for (int k = 0; k < 3; ++k)
        same = same && std::abs(at.pos()[3 * a + k] + at.offset()[3 * gi + k] * at.voxel()[a] - pts[p][k]) < 1e-6;
      if (same) return static_cast<int>(p);
    }
    return -1;
  };
  std::set<int> used;
  for (size_t gi = 0; gi < 5; ++gi) {  // anchor 0: five distinct points of its seven
    const int p = child_on_point(gi);
    ASSERT_GE(p, 0) << gi;
    ASSERT_LT(p, 7) << gi;
    used.insert(p);
    for (int k = 0; k < 3; ++k) EXPECT_NEAR(at.sh()[gi * 48 + k], (col[p][k] / 255.0 - 0.5) / kC0, 1e-6);
  }
  EXPECT_EQ(used.size(), 5u);
  for (size_t gi = 5; gi < 7; ++gi) EXPECT_EQ(child_on_point(gi), static_cast<int>(gi + 2));  // anchor 1: its two
  for (size_t gi = 7; gi < 10; ++gi) {  // ... and three children as without the option
    for (int k = 0; k < 3; ++k) {
      EXPECT_EQ(at.offset()[gi * 3 + k], plain.offset()[gi * 3 + k]);
      EXPECT_EQ(at.sh()[gi * 48 + k], plain.sh()[gi * 48 + k]);
    }
  }
  // Everything else as without the option.
  EXPECT_EQ(at.scale_logit(), plain.scale_logit());
  EXPECT_EQ(at.opacity_logit(), plain.opacity_logit());
  EXPECT_EQ(at.quat(), plain.quat());
}

TEST(AnchorInit, EveryLayerWhenInitLayerIsMinusOne) {
  AnchorConfig c;
  c.init_layer = -1;
  VoxelGrid g = unit_grid(c);
  const auto pts = random_points(3000, 2.0, 11);
  AnchorModel m;
  const AnchorInitStats st = m.initialise_from_points(pts, random_colors(pts.size(), 1), g, c, 5);
  std::set<std::tuple<int, int, int, int>> occupied;
  for (int l = 0; l < 3; ++l)
    for (const auto& p : pts) {
      const Eigen::Vector3i cl = g.cell_of(l, p);
      occupied.emplace(l, cl.x(), cl.y(), cl.z());
    }
  ASSERT_EQ(m.size(), occupied.size());
  size_t a = 0;
  for (const auto& [l, x, y, z] : occupied) {  // std::set order = (layer, x, y, z)
    EXPECT_EQ(m.layer()[a], l);
    EXPECT_EQ(cell_at(m, a), Eigen::Vector3i(x, y, z));
    EXPECT_FLOAT_EQ(m.voxel()[a], static_cast<float>(g.voxel(l)));
    ++a;
  }
  size_t total = 0;
  for (size_t n : st.anchors_per_layer) total += n;
  EXPECT_EQ(total, m.size());
  EXPECT_LT(st.anchors_per_layer[0], st.anchors_per_layer[1]);
  std::printf("  3000 points -> anchors per layer %zu %zu %zu\n", st.anchors_per_layer[0], st.anchors_per_layer[1],
              st.anchors_per_layer[2]);
}

// init_layers N seeds the N layers from init_layer down, each exactly as
// a run seeding that layer alone would; past the finest layer it is clipped,
// and 0 is refused.
TEST(AnchorInit, InitLayersSeedsTheCoarsestLayersAsEachAlone) {
  const auto pts = random_points(3000, 2.0, 12);
  const auto cols = random_colors(pts.size(), 2);
  AnchorConfig two;
  two.init_layers = 2;
  const VoxelGrid g = unit_grid(two);
  AnchorModel m;
  const AnchorInitStats st = m.initialise_from_points(pts, cols, g, two, 5);
  EXPECT_GT(st.anchors_per_layer[0], 0u);
  EXPECT_GT(st.anchors_per_layer[1], st.anchors_per_layer[0]);
  EXPECT_EQ(st.anchors_per_layer[2], 0u);
  ASSERT_EQ(m.size(), st.anchors_per_layer[0] + st.anchors_per_layer[1]);
  // Layer by layer, the anchors (cells, children, colours) of a run seeding that layer alone.
  size_t a = 0;
  for (int l = 0; l < 2; ++l) {
    AnchorConfig one = two;
    one.init_layers = 1;
    one.init_layer = l;
    AnchorModel alone;
    alone.initialise_from_points(pts, cols, g, one, 5);
    const size_t K = static_cast<size_t>(one.children);
    for (size_t b = 0; b < alone.size(); ++b, ++a) {
      ASSERT_EQ(m.layer()[a], l);
      ASSERT_EQ(cell_at(m, a), cell_at(alone, b));
      for (size_t k = 0; k < K * 3; ++k) ASSERT_EQ(m.offset()[a * K * 3 + k], alone.offset()[b * K * 3 + k]);
      for (size_t k = 0; k < K * kAnchorShCoeffs * 3; ++k)
        ASSERT_EQ(m.sh()[a * K * kAnchorShCoeffs * 3 + k], alone.sh()[b * K * kAnchorShCoeffs * 3 + k]);
    }
  }
  // Clipped at the finest layer: from layer 1, 5 layers are layers 1 and 2.
  AnchorConfig deep = two;
  deep.init_layer = 1;
  deep.init_layers = 5;
  AnchorModel d;
  const AnchorInitStats sd = d.initialise_from_points(pts, cols, g, deep, 5);
  EXPECT_EQ(sd.anchors_per_layer[0], 0u);
  EXPECT_EQ(sd.anchors_per_layer[1], st.anchors_per_layer[1]);
  EXPECT_GT(sd.anchors_per_layer[2], sd.anchors_per_layer[1]);
  AnchorConfig none = two;
  none.init_layers = 0;
  test::expect_error_with<std::invalid_argument>([&] { none.validate(); }, {"init_layers is 0"});
}

TEST(AnchorInit, DeterministicAndIndependentOfPointOrder) {
  AnchorConfig c;
  c.init_layer = -1;
  VoxelGrid g = unit_grid(c);
  g.top_voxel = 0.3;
  auto pts = random_points(2000, 1.0, 21);
  auto col = random_colors(pts.size(), 22);
  auto archive_of = [&](uint64_t seed) {
    AnchorModel m;
    m.initialise_from_points(pts, col, g, c, seed);
    ModelArchive a;
    m.to_archive(a);
    return a;
  };
  const ModelArchive a1 = archive_of(7), a2 = archive_of(7);
  EXPECT_TRUE(same_arrays(a1, a2));
  // Reversed point order: same bytes (colour sums of uint8 values are exact).
  std::reverse(pts.begin(), pts.end());
  std::reverse(col.begin(), col.end());
  EXPECT_TRUE(same_arrays(a1, archive_of(7)));
  // Another seed moves the random parts only.
  const ModelArchive b = archive_of(8);
  for (const char* name : {"anchors/offset", "anchors/quat", "anchors/feature"})
    EXPECT_NE(a1.tensor(name).bytes, b.tensor(name).bytes) << name;
  for (const char* name : {"anchors/pos", "anchors/cell", "anchors/sh", "anchors/opacity_logit", "anchors/scale_logit"})
    EXPECT_EQ(a1.tensor(name).bytes, b.tensor(name).bytes) << name;
  // Offsets of different children and anchors are different numbers.
  const auto off = a1.get<float>("anchors/offset");
  std::set<float> distinct(off.begin(), off.end());
  EXPECT_GT(distinct.size(), off.size() * 99 / 100);
}

// ---------------------------------------------------------------------------
// Growing and pruning bookkeeping

TEST(AnchorModel, AddFindRemoveCompact) {
  AnchorConfig c;
  const VoxelGrid g = unit_grid(c);
  AnchorModel m;
  m.initialise_from_points(random_points(400, 3.0, 31), random_colors(400, 32), g, c, 1);
  randomise(m, 33, false);
  const size_t A = m.size(), K = 5;
  ASSERT_GT(A, 20u);

  // A finer anchor grown from child 7 (anchor 1).
  const Eigen::Vector3i fine(4, -3, 9);
  const int id = m.add_anchor(1, fine, 7, 99);
  ASSERT_EQ(id, static_cast<int>(A));
  EXPECT_EQ(m.find(1, fine), id);
  EXPECT_EQ(m.add_anchor(1, fine, 7, 100), -1);  // taken
  EXPECT_EQ(m.add_anchor(0, cell_at(m, 0), -1, 1), -1);
  EXPECT_EQ(m.add_anchor(2, Eigen::Vector3i(kMaxAnchorCell, 0, 0), -1, 1), -1);  // not representable
  EXPECT_THROW(m.add_anchor(3, fine, -1, 1), std::out_of_range);
  EXPECT_THROW(m.add_anchor(2, fine, static_cast<int64_t>(m.gaussians()), 1), std::out_of_range);
  m.check();
  EXPECT_EQ(m.layer()[id], 1);
  EXPECT_EQ(m.voxel()[id], 0.25f);
  for (int k = 0; k < 3; ++k) {
    EXPECT_EQ(m.pos()[3 * id + k], static_cast<float>(g.centre(1, fine)[k]));
    EXPECT_EQ(m.feature()[3 * id + k], m.feature()[3 * 1 + k]);
  }
  for (size_t i = 0; i < K; ++i) {
    const size_t row = id * K + i;
    const double o0 = c.init_opacity;
    EXPECT_EQ(m.opacity_logit()[row], std::min(m.opacity_logit()[7], static_cast<float>(std::log(o0 / (1 - o0)))));
    for (int k = 0; k < 4; ++k) EXPECT_EQ(m.quat()[row * 4 + k], m.quat()[7 * 4 + k]);
    for (int k = 0; k < 48; ++k) EXPECT_EQ(m.sh()[row * 48 + k], m.sh()[7 * 48 + k]);
    for (int k = 0; k < 3; ++k) {
      EXPECT_NEAR(sigmoid(m.scale_logit()[row * 3 + k]), c.init_scale, 1e-7);
      EXPECT_LE(std::abs(m.offset()[row * 3 + k]), 0.5f);
    }
  }
  // A fresh anchor without a parent: grey, init opacity.
  const int fresh = m.add_anchor(2, Eigen::Vector3i(-1, -2, -3), -1, 5);
  ASSERT_EQ(fresh, static_cast<int>(A) + 1);
  EXPECT_EQ(m.sh()[fresh * K * 48], 0.f);
  EXPECT_NEAR(sigmoid(m.opacity_logit()[fresh * K]), c.init_opacity, 1e-7);

  // Remove every third anchor and the grown one.
  const AnchorModel before = m;
  std::vector<uint8_t> keep(m.size());
  for (size_t a = 0; a < keep.size(); ++a) keep[a] = (a % 3 != 0) && a != static_cast<size_t>(id);
  const std::vector<int> kept = m.remove_anchors(keep);
  m.check();
  ASSERT_EQ(kept.size(), m.size());
  EXPECT_TRUE(std::is_sorted(kept.begin(), kept.end()));
  for (size_t r = 0; r < kept.size(); ++r) {
    const size_t o = kept[r];
    EXPECT_TRUE(keep[o]);
    EXPECT_EQ(cell_at(m, r), cell_at(before, o));
    EXPECT_EQ(m.layer()[r], before.layer()[o]);
    EXPECT_EQ(m.find(m.layer()[r], cell_at(m, r)), static_cast<int>(r));
    for (int k = 0; k < 3; ++k) EXPECT_EQ(m.feature()[3 * r + k], before.feature()[3 * o + k]);
    for (size_t j = 0; j < K * 48; ++j) ASSERT_EQ(m.sh()[r * K * 48 + j], before.sh()[o * K * 48 + j]);
    for (size_t j = 0; j < K * 4; ++j) ASSERT_EQ(m.quat()[r * K * 4 + j], before.quat()[o * K * 4 + j]);
    for (size_t j = 0; j < K * 3; ++j) ASSERT_EQ(m.offset()[r * K * 3 + j], before.offset()[o * K * 3 + j]);
    for (size_t j = 0; j < K; ++j) ASSERT_EQ(m.opacity_logit()[r * K + j], before.opacity_logit()[o * K + j]);
  }
  for (size_t a = 0; a < keep.size(); ++a)
    if (!keep[a]) EXPECT_EQ(m.find(before.layer()[a], cell_at(before, a)), -1);
  // The voxel is free again.
  const size_t kept_count = m.size();
  EXPECT_EQ(m.add_anchor(1, fine, -1, 1), static_cast<int>(kept_count));
  EXPECT_THROW(m.remove_anchors(std::vector<uint8_t>(3, 1)), std::invalid_argument);
  EXPECT_EQ(AnchorModel::child_rows({2, -1, 0}, 2), (std::vector<int>{4, 5, -1, -1, 0, 1}));
  // Remove everything.
  m.remove_anchors(std::vector<uint8_t>(m.size(), 0));
  EXPECT_EQ(m.size(), 0u);
  m.check();
  EXPECT_EQ(m.add_anchor(0, Eigen::Vector3i(0, 0, 0), -1, 1), 0);
}

// ---------------------------------------------------------------------------
// Archive

TEST(AnchorModel, ArchiveRoundTripIsBitExact) {
  AnchorModel m = random_model(800, 41, true);
  m.add_anchor(2, Eigen::Vector3i(-30, 5, 17), 3, 1);
  ModelArchive a;
  a.meta["other"] = "kept";
  m.to_archive(a);
  test::ScratchDir dir("anchors");
  write_model_archive(dir.file("model.ag2gs"), a);
  const ModelArchive r = read_model_archive(dir.file("model.ag2gs"));
  const AnchorModel back = AnchorModel::from_archive(r);
  ModelArchive b;
  back.to_archive(b);
  EXPECT_TRUE(same_arrays(a, b));
  EXPECT_EQ(a.meta["anchors"], b.meta["anchors"]);
  EXPECT_EQ(r.meta["other"], "kept");
  EXPECT_EQ(back.grid().origin, m.grid().origin);  // bit-exact doubles through JSON
  EXPECT_EQ(back.grid().top_voxel, m.grid().top_voxel);
  EXPECT_EQ(back.config().init_opacity, m.config().init_opacity);
  EXPECT_EQ(back.config().init_feature, m.config().init_feature);
  EXPECT_EQ(back.size(), m.size());
  for (size_t i = 0; i < m.size(); ++i) ASSERT_EQ(back.find(m.layer()[i], cell_at(m, i)), static_cast<int>(i));
  // An empty model too.
  AnchorModel empty;
  empty.reset(m.grid(), m.config());
  ModelArchive e;
  empty.to_archive(e);
  EXPECT_EQ(AnchorModel::from_archive(e).size(), 0u);
}

TEST(AnchorModel, ArchiveRejectsCorruptArrays) {
  const AnchorModel m = random_model(300, 51, false);
  ModelArchive good;
  m.to_archive(good);
  good.source = "/x/model.ag2gs";
  const int64_t A = m.size(), K = 5;
  auto expect_reject = [&](const std::function<void(ModelArchive&)>& corrupt, std::vector<std::string> needles) {
    ModelArchive bad = good;
    corrupt(bad);
    needles.push_back("/x/model.ag2gs");
    test::expect_error_with<std::runtime_error>([&] { AnchorModel::from_archive(bad); }, needles);
  };
  expect_reject(
      [&](ModelArchive& b) {
        b.put("anchors/quat", std::vector<float>(A * K * 3), {A, K, 3});
      },
      {"anchors/quat", "shape"});
  expect_reject(
      [&](ModelArchive& b) {
        b.put("anchors/sh", std::vector<double>(A * K * 48), {A, K, 16, 3});
      },
      {"anchors/sh", "f64"});
  expect_reject(
      [&](ModelArchive& b) {
        b.put("anchors/offset", std::vector<float>((A - 1) * K * 3), {A - 1, K, 3});
      },
      {"anchors/offset"});
  expect_reject([&](ModelArchive& b) { b.put("anchors/pos", std::vector<float>(A * 4), {A, 4}); }, {"anchors/pos"});
  expect_reject(
      [&](ModelArchive& b) {
        ModelArchive c;
        for (const auto& [name, t] : b.arrays())
          if (name != "anchors/opacity_logit") c.put_tensor(name, t);
        c.meta = b.meta;
        c.source = b.source;
        b = c;
      },
      {"anchors/opacity_logit"});
  expect_reject(
      [&](ModelArchive& b) {
        auto layer = b.get<int32_t>("anchors/layer");
        layer[2] = 3;
        b.put("anchors/layer", layer, {A});
      },
      {"anchors/layer", "anchor 2"});
  expect_reject(
      [&](ModelArchive& b) {  // anchor 4 claims anchor 1's voxel (and position)
        auto cell = b.get<int32_t>("anchors/cell");
        auto pos = b.get<float>("anchors/pos");
        for (int k = 0; k < 3; ++k) {
          cell[3 * 4 + k] = cell[3 * 1 + k];
          pos[3 * 4 + k] = pos[3 * 1 + k];
        }
        b.put("anchors/cell", cell, {A, 3});
        b.put("anchors/pos", pos, {A, 3});
      },
      {"anchors/cell", "share", "1 and 4"});
  expect_reject(
      [&](ModelArchive& b) {
        auto pos = b.get<float>("anchors/pos");
        pos[7] += 1e-3f;
        b.put("anchors/pos", pos, {A, 3});
      },
      {"anchors/pos", "anchor 2", "centre"});
  expect_reject(
      [&](ModelArchive& b) {
        auto v = b.get<float>("anchors/voxel");
        v[0] *= 2;
        b.put("anchors/voxel", v, {A});
      },
      {"anchors/voxel", "anchor 0"});
  expect_reject([&](ModelArchive& b) { b.meta.erase("anchors"); }, {"meta", "anchors"});
  expect_reject([&](ModelArchive& b) { b.meta["anchors"]["config"]["children"] = 4; }, {"anchors/offset", "shape"});
  expect_reject([&](ModelArchive& b) { b.meta["anchors"]["config"]["layers"] = 2; }, {"layers"});
  expect_reject([&](ModelArchive& b) { b.meta["anchors"]["grid"].erase("top_voxel"); }, {"top_voxel"});
  expect_reject([&](ModelArchive& b) { b.meta["anchors"]["format"] = 2; }, {"format 1"});
}

// ---------------------------------------------------------------------------
// Expansion on the device

// Gradients of the expanded Gaussians as a double struct (float-representable
// values) plus their device buffers.
struct GaussianGradBuffers {
  explicit GaussianGradBuffers(Runtime& rt)
      : means(&rt), scales(&rt), quats(&rt), opacities(&rt), sh(&rt), features(&rt) {}
  DeviceBuffer means, scales, quats, opacities, sh, features;
  ref::RefGrads host;
  int sh_degree = 0;
  size_t n = 0;

  DeviceGaussianGrads view() const { return {n, sh_degree, &means, &scales, &quats, &opacities, &sh, &features}; }
};

void fill_random_grads(GaussianGradBuffers& b, size_t n, int sh_degree, uint32_t seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<float> u(-1, 1);
  const int S = sh_coeffs_for_degree(sh_degree);
  auto make = [&](std::vector<double>& host, DeviceBuffer& dev, size_t count) {
    std::vector<float> f(count);
    for (float& x : f) x = u(rng);
    host.assign(f.begin(), f.end());
    dev.upload(f);
  };
  b.n = n;
  b.sh_degree = sh_degree;
  make(b.host.means, b.means, n * 3);
  make(b.host.scales, b.scales, n * 3);
  make(b.host.quats, b.quats, n * 4);
  make(b.host.opacities, b.opacities, n);
  make(b.host.sh, b.sh, n * S * 3);
  make(b.host.features, b.features, n * 3);
}

// Every (name, device, reference) array pair of anchor gradients.
struct GradPair {
  const char* name;
  const std::vector<float>* dev;
  const std::vector<double>* ref;
};
std::vector<GradPair> pairs(const AnchorGrads& d, const ref::RefAnchorGrads& r) {
  return {{"feature", &d.feature, &r.feature},
          {"offset", &d.offset, &r.offset},
          {"scale_logit", &d.scale_logit, &r.scale_logit},
          {"quat", &d.quat, &r.quat},
          {"opacity_logit", &d.opacity_logit, &r.opacity_logit},
          {"sh", &d.sh, &r.sh}};
}

double max_abs(const std::vector<double>& v) {
  double m = 0;
  for (double x : v) m = std::max(m, std::abs(x));
  return m;
}

// Forward: float kernels against the double reference. Measured on PoCL
// (x86): means within 6.0e-8 abs (float rounding of pos + offset l, |mean| <=
// 1.5); scales within 1.0e-7 and opacities within 1.1e-7 relative (exp and a
// division); quats, SH and features are copies and must be bit-identical.
constexpr double kMeanAbsTol = 5e-7, kActivationRelTol = 1e-6;

TEST(Expander, ForwardMatchesReference) {
  Runtime& rt = test::runtime();
  AnchorModel m = random_model(1500, 61, true);
  ASSERT_GT(m.size(), 200u);
  DeviceAnchors dev(rt);
  dev.upload(m);
  Expander ex(rt);
  DeviceGaussians out(rt);
  for (int d = 0; d <= 3; ++d) {
    ex.forward(dev, out, d);
    ASSERT_EQ(out.n, m.gaussians());
    ASSERT_EQ(out.sh_degree, d);
    const ExpandedGaussians ref = expand_reference_double(m, d);
    const GaussianSet exact = ref.to_float();
    const size_t n = out.n;
    std::vector<float> means, scales, quats, opacities, sh, features;
    out.means.download(means, n * 3);
    out.scales.download(scales, n * 3);
    out.quats.download(quats, n * 4);
    out.opacities.download(opacities, n);
    out.sh.download(sh, n * sh_coeffs_for_degree(d) * 3);
    out.features.download(features, n * 3);
    std::printf(" degree %d\n", d);
    test::expect_close("means", test::compare(means, ref.means, kMeanAbsTol, 0));
    test::expect_close("scales", test::compare(scales, ref.scales, 1e-30, kActivationRelTol));
    test::expect_close("opacities", test::compare(opacities, ref.opacities, 1e-30, kActivationRelTol));
    EXPECT_TRUE(same_bytes(quats, exact.quats));
    EXPECT_TRUE(same_bytes(sh, exact.sh));
    EXPECT_TRUE(same_bytes(features, exact.features));
  }
  EXPECT_THROW(ex.forward(dev, out, 4), std::invalid_argument);
  EXPECT_THROW(ex.forward(dev, out, -1), std::invalid_argument);
}

// Backward against the analytic double reference: v_offset, v_quat and the SH
// are exact products or copies (measured error 0); v_scale_logit and
// v_opacity_logit carry the float sigmoid (measured 2.4e-7 relative); v_feature
// sums 5 floats (measured 3.6e-7 abs on a scale of ~4).
constexpr double kBackwardRelTol = 2e-6, kBackwardAbsScale = 1e-6;

void check_backward_against(const AnchorGrads& dev, const ref::RefAnchorGrads& ref) {
  for (const GradPair& p : pairs(dev, ref)) {
    const double scale = max_abs(*p.ref);
    test::expect_close(p.name, test::compare(*p.dev, *p.ref, kBackwardAbsScale * scale + 1e-30, kBackwardRelTol));
  }
}

TEST(Expander, BackwardMatchesReferenceAndFiniteDifferences) {
  Runtime& rt = test::runtime();
  AnchorModel m = random_model(1500, 71, true);
  DeviceAnchors dev(rt);
  dev.upload(m);
  Expander ex(rt);
  DeviceAnchorGrads grads(rt);
  GaussianGradBuffers v(rt);
  for (int d = 0; d <= 3; ++d) {
    fill_random_grads(v, m.gaussians(), d, 100 + d);
    ex.backward(dev, v.view(), grads);
    ASSERT_EQ(grads.anchors, m.size());
    std::printf(" gradient SH degree %d\n", d);
    check_backward_against(grads.download(), ref::expand_backward_reference(m, v.host, d));
  }

  // The analytic reference against central differences of the linear
  // functional F = <v, expand(model)> on a small model, every parameter.
  AnchorModel small = random_model(30, 72, false);
  ASSERT_GE(small.size(), 6u);
  const int d = 2;
  fill_random_grads(v, small.gaussians(), d, 7);
  const ref::RefAnchorGrads analytic = ref::expand_backward_reference(small, v.host, d);
  auto F = [&](const AnchorModel& mm) {
    const ExpandedGaussians e = expand_reference_double(mm, d);
    double s = 0;
    for (size_t i = 0; i < e.means.size(); ++i) s += v.host.means[i] * e.means[i];
    for (size_t i = 0; i < e.scales.size(); ++i) s += v.host.scales[i] * e.scales[i];
    for (size_t i = 0; i < e.quats.size(); ++i) s += v.host.quats[i] * e.quats[i];
    for (size_t i = 0; i < e.opacities.size(); ++i) s += v.host.opacities[i] * e.opacities[i];
    for (size_t i = 0; i < e.sh.size(); ++i) s += v.host.sh[i] * e.sh[i];
    for (size_t i = 0; i < e.features.size(); ++i) s += v.host.features[i] * e.features[i];
    return s;
  };
  using Accessor = std::vector<float>& (AnchorModel::*)();
  const std::pair<Accessor, const std::vector<double>*> arrays[] = {
      {&AnchorModel::feature, &analytic.feature},
      {&AnchorModel::offset, &analytic.offset},
      {&AnchorModel::scale_logit, &analytic.scale_logit},
      {&AnchorModel::quat, &analytic.quat},
      {&AnchorModel::opacity_logit, &analytic.opacity_logit},
      {&AnchorModel::sh, &analytic.sh}};
  double worst = 0;
  for (const auto& [acc, ref] : arrays) {
    std::vector<float>& x = (small.*acc)();
    for (size_t i = 0; i < x.size(); ++i) {
      const float x0 = x[i];
      const float h = 1e-3f * std::max(1.f, std::abs(x0));
      x[i] = x0 + h;
      const double xp = x[i], fp = F(small);
      x[i] = x0 - h;
      const double xm = x[i], fm = F(small);
      x[i] = x0;
      const double fd = (fp - fm) / (xp - xm);
      const double err = std::abs(fd - (*ref)[i]) / std::max(1e-3, std::abs((*ref)[i]));
      worst = std::max(worst, err);
      ASSERT_LT(err, 1e-5) << "entry " << i << " fd " << fd << " analytic " << (*ref)[i];
    }
  }
  std::printf("  reference vs central differences: max rel error %.3g\n", worst);

  // Shape checks on the incoming gradients.
  fill_random_grads(v, m.gaussians() - 1, 1, 3);
  EXPECT_THROW(ex.backward(dev, v.view(), grads), std::invalid_argument);
  fill_random_grads(v, m.gaussians(), 1, 3);
  DeviceGaussianGrads missing = v.view();
  missing.sh = nullptr;
  EXPECT_THROW(ex.backward(dev, missing, grads), std::invalid_argument);
}

// --scale-cap: scale = sigmoid(logit) * cap * l, forward and backward against
// the double reference, the reference against central differences, and a
// fresh child still starts at init_scale voxel edges.
TEST(Expander, ScaleCapMatchesReferenceAndFiniteDifferences) {
  Runtime& rt = test::runtime();
  const float cap = 8.f;
  AnchorModel m = random_model(800, 91, true, cap);
  DeviceAnchors dev(rt);
  dev.upload(m);
  Expander ex(rt);
  DeviceGaussians out(rt);
  ex.forward(dev, out, 1);
  const ExpandedGaussians ref = expand_reference_double(m, 1);
  std::vector<float> scales;
  out.scales.download(scales, out.n * 3);
  test::expect_close("scales", test::compare(scales, ref.scales, 1e-30, kActivationRelTol));
  for (size_t g = 0; g < m.gaussians(); ++g)
    for (int k = 0; k < 3; ++k) {
      const double x = m.scale_logit()[3 * g + k], l = m.voxel()[g / m.children()];
      ASSERT_NEAR(ref.scales[3 * g + k], cap * l / (1.0 + std::exp(-x)), 1e-12 * cap * l);
    }
  DeviceAnchorGrads grads(rt);
  GaussianGradBuffers v(rt);
  fill_random_grads(v, m.gaussians(), 1, 17);
  ex.backward(dev, v.view(), grads);
  const ref::RefAnchorGrads analytic = ref::expand_backward_reference(m, v.host, 1);
  check_backward_against(grads.download(), analytic);
  // d<v, scales>/d logit by central differences on a few children.
  for (size_t i = 0; i < 60; i += 7) {
    std::vector<float>& x = m.scale_logit();
    const float x0 = x[i], h = 1e-3f * std::max(1.f, std::abs(x0));
    auto F = [&] {
      const ExpandedGaussians e = expand_reference_double(m, 1);
      double sum = 0;
      for (size_t j = 0; j < e.scales.size(); ++j) sum += v.host.scales[j] * e.scales[j];
      return sum;
    };
    x[i] = x0 + h;
    const double xp = x[i], fp = F();
    x[i] = x0 - h;
    const double xm = x[i], fm = F();
    x[i] = x0;
    const double fd = (fp - fm) / (xp - xm);
    EXPECT_NEAR(fd, analytic.scale_logit[i], 1e-5 * std::max(1e-3, std::abs(analytic.scale_logit[i]))) << i;
  }
  // A fresh child starts at init_scale voxel edges whatever the cap.
  AnchorModel fresh;
  fresh.reset(m.grid(), m.config());
  fresh.add_anchor(1, Eigen::Vector3i(3, 4, 5), -1, 9);
  const ExpandedGaussians e = expand_reference_double(fresh, 0);
  for (double sc : e.scales) EXPECT_NEAR(sc, fresh.config().init_scale * fresh.voxel()[0], 1e-7);
  // The config refuses a cap below 1 and an initial scale at or above the cap.
  AnchorConfig c = m.config();
  c.scale_cap = 0.5f;
  EXPECT_THROW(c.validate(), std::invalid_argument);
  c.scale_cap = 2.f;
  c.init_scale = 2.f;
  EXPECT_THROW(c.validate(), std::invalid_argument);
}

// --scale-cap-layers 1: the cap holds on the top layer only; children of the
// finer layers stay inside their voxels. Forward against the closed form per
// layer, backward against the double reference, fresh children at init_scale
// voxel edges on every layer.
TEST(Expander, ScaleCapOnTheTopLayerOnly) {
  Runtime& rt = test::runtime();
  AnchorConfig c;
  c.scale_cap = 8.f;
  c.scale_cap_layers = 1;
  VoxelGrid grid = unit_grid(c);
  grid.top_voxel = 0.25;
  AnchorModel m;
  m.reset(grid, c);
  for (int layer = 0; layer < c.layers; ++layer)
    for (int i = 0; i < 40; ++i) m.add_anchor(layer, Eigen::Vector3i(i % 5, i / 5, layer), -1, 7);
  ASSERT_EQ(m.size(), 120u);
  const double init = c.init_scale;
  for (const double sc : expand_reference_double(m, 0).scales) {
    const double ratio = sc / init;
    EXPECT_TRUE(std::abs(ratio - 0.25) < 1e-6 || std::abs(ratio - 0.0625) < 1e-6 || std::abs(ratio - 0.015625) < 1e-6)
        << "a fresh child's scale " << sc << " is not init_scale voxel edges";
  }
  randomise(m, 8, true);
  DeviceAnchors dev(rt);
  dev.upload(m);
  Expander ex(rt);
  DeviceGaussians out(rt);
  ex.forward(dev, out, 1);
  std::vector<float> scales;
  out.scales.download(scales, out.n * 3);
  for (size_t g = 0; g < m.gaussians(); ++g) {
    const size_t a = g / m.children();
    const double l = m.voxel()[a], cap = m.layer()[a] == 0 ? 8.0 : 1.0;
    for (int k = 0; k < 3; ++k) {
      const double want = cap * l / (1.0 + std::exp(-double(m.scale_logit()[3 * g + k])));
      ASSERT_NEAR(scales[3 * g + k], want, kActivationRelTol * want) << "layer " << m.layer()[a];
    }
  }
  DeviceAnchorGrads grads(rt);
  GaussianGradBuffers v(rt);
  fill_random_grads(v, m.gaussians(), 1, 19);
  ex.backward(dev, v.view(), grads);
  check_backward_against(grads.download(), ref::expand_backward_reference(m, v.host, 1));
  // With the finer layers uncapped, a fresh child must start below one voxel edge.
  c.init_scale = 2.f;
  EXPECT_THROW(c.validate(), std::invalid_argument);
  c.scale_cap_layers = 3;
  EXPECT_NO_THROW(c.validate());
  c.scale_cap_layers = 0;
  EXPECT_THROW(c.validate(), std::invalid_argument);
}

TEST(Expander, UploadDownloadRoundTripAndEmptyModel) {
  Runtime& rt = test::runtime();
  AnchorModel m = random_model(500, 81, true);
  DeviceAnchors dev(rt);
  dev.upload(m);
  AnchorModel copy = m;
  for (float& x : copy.sh()) x = 0;
  for (float& x : copy.offset()) x = 0;
  dev.download(copy);
  ModelArchive a, b;
  m.to_archive(a);
  copy.to_archive(b);
  EXPECT_TRUE(same_arrays(a, b));
  copy.remove_anchors(std::vector<uint8_t>(copy.size(), 0));
  EXPECT_THROW(dev.download(copy), std::invalid_argument);

  // Zero anchors: nothing to launch, nothing to throw.
  dev.upload(copy);
  Expander ex(rt);
  DeviceGaussians out(rt);
  ex.forward(dev, out, 3);
  EXPECT_EQ(out.n, 0u);
  DeviceAnchorGrads grads(rt);
  GaussianGradBuffers v(rt);
  fill_random_grads(v, 0, 3, 1);
  ex.backward(dev, v.view(), grads);
  EXPECT_EQ(grads.download().offset.size(), 0u);
}

// Logits far beyond what training reaches: activations saturate to 0 or 1
// (never NaN or Inf) and so do their gradients.
TEST(Expander, ExtremeLogitsStayFinite) {
  Runtime& rt = test::runtime();
  AnchorModel m = random_model(50, 85, false);
  const float extremes[] = {100.f, -100.f, 1e30f, -1e30f, 88.7f, -88.7f};
  for (size_t i = 0; i < m.scale_logit().size(); ++i) m.scale_logit()[i] = extremes[i % 6];
  for (size_t i = 0; i < m.opacity_logit().size(); ++i) m.opacity_logit()[i] = extremes[(i + 1) % 6];
  DeviceAnchors dev(rt);
  dev.upload(m);
  Expander ex(rt);
  DeviceGaussians out(rt);
  ex.forward(dev, out, 0);
  std::vector<float> scales, opacities;
  out.scales.download(scales, m.gaussians() * 3);
  out.opacities.download(opacities, m.gaussians());
  EXPECT_TRUE(test::all_finite(scales));
  EXPECT_TRUE(test::all_finite(opacities));
  for (size_t g = 0; g < m.gaussians(); ++g) {
    EXPECT_NEAR(opacities[g], m.opacity_logit()[g] > 0 ? 1.f : 0.f, 1e-30);  // e^-88.7: a denormal
    for (int k = 0; k < 3; ++k)
      EXPECT_NEAR(scales[3 * g + k], m.scale_logit()[3 * g + k] > 0 ? m.voxel()[g / 5] : 0.f, 1e-30);
  }
  DeviceAnchorGrads grads(rt);
  GaussianGradBuffers v(rt);
  fill_random_grads(v, m.gaussians(), 0, 9);
  ex.backward(dev, v.view(), grads);
  const AnchorGrads a = grads.download();
  EXPECT_TRUE(test::all_finite(a.scale_logit));
  EXPECT_TRUE(test::all_finite(a.opacity_logit));
  for (float x : a.opacity_logit) EXPECT_LT(std::abs(x), 1e-30f);
}

// ---------------------------------------------------------------------------
// The full chain: anchors -> expand -> render -> backward -> expand backward.

ref::RefGaussians to_ref(const ExpandedGaussians& e) {
  ref::RefGaussians r;
  r.sh_degree = e.sh_degree;
  r.means = e.means;
  r.scales = e.scales;
  r.quats = e.quats;
  r.opacities = e.opacities;
  r.sh = e.sh;
  r.features = e.features;
  return r;
}

// A few anchors in front of a 32x24 camera, children of 1..4 px.
AnchorModel chain_model(uint32_t seed) {
  AnchorConfig c;
  VoxelGrid g;
  g.origin = Eigen::Vector3d(-0.9, -0.9, -0.9);
  g.top_voxel = 0.6;
  g.layers = c.layers;
  g.layer_ratio = c.layer_ratio;
  const std::vector<Eigen::Vector3d> pts = {{-0.5, -0.3, 0.1}, {0.2, 0.25, -0.4}, {0.35, -0.4, 0.5}, {-0.2, 0.5, 0.}};
  AnchorModel m;
  m.initialise_from_points(pts, random_colors(pts.size(), seed), g, c, seed);
  randomise(m, seed + 1, false);
  for (float& x : m.opacity_logit()) x = std::clamp(x, -1.5f, 1.5f);
  return m;
}

OutputGrads chain_output_grads(int w, int h, uint32_t seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<float> u(-1.f, 1.f);
  const size_t npix = static_cast<size_t>(w) * h;
  auto fill = [&](size_t n) {
    std::vector<float> v(n);
    for (float& x : v) x = u(rng);
    return v;
  };
  OutputGrads g;
  g.rgb = fill(npix * 3);
  g.feature = fill(npix * 3);
  g.depth = fill(npix);
  g.alpha = fill(npix);
  g.distortion = fill(npix);
  return g;
}

double dot_diff(const std::vector<float>& g, const std::vector<double>& a, const std::vector<double>& b) {
  double s = 0;
  for (size_t i = 0; i < g.size(); ++i) s += g[i] * (a[i] - b[i]);
  return s;
}

AnchorGrads run_chain(const AnchorModel& m, const Camera& cam, const OutputGrads& og, int degree,
                      std::vector<float>* rgb = nullptr) {
  Runtime& rt = test::runtime();
  DeviceAnchors anchors(rt);
  anchors.upload(m);
  Expander ex(rt);
  DeviceGaussians gaussians(rt);
  ex.forward(anchors, gaussians, degree);
  Renderer r(rt);
  r.forward(gaussians, cam, RenderSettings{});
  if (rgb) *rgb = r.download_output().rgb;
  r.backward(og);
  DeviceAnchorGrads grads(rt);
  ex.backward(anchors, r.device_grads(), grads);
  return grads.download();
}

TEST(Expander, ChainThroughRendererMatchesFiniteDifferences) {
  const AnchorModel m = chain_model(91);
  ASSERT_EQ(m.size(), 4u);
  const Camera cam = test::look_at_origin(32, 24);
  const OutputGrads og = chain_output_grads(cam.width, cam.height, 92);
  const int degree = 1;
  const RenderSettings settings;
  const AnchorGrads dev = run_chain(m, cam, og, degree);

  // The device chain against the analytic double chain, every entry, with the
  // renderer's tolerance of tests/host/render/test_render_backward.cpp (measured: 1.0e-5
  // abs, the largest relative error 1.6e-4 on a small quat entry).
  const ref::RefGaussians rg = to_ref(expand_reference_double(m, degree));
  const ref::RefGrads rgrad = ref::render_backward(rg, cam, settings, og);
  const ref::RefAnchorGrads analytic = ref::expand_backward_reference(m, rgrad, degree);
  for (const GradPair& p : pairs(dev, analytic)) {
    const double scale = max_abs(*p.ref);
    EXPECT_GT(scale, 0) << p.name;
    test::expect_close(p.name, test::compare(*p.dev, *p.ref, 5e-5 * scale + 1e-12, 2e-3));
  }

  // The device chain against central differences of the double reference
  // render of the expanded anchors, for a sample of parameters (measured:
  // 3.1e-5 relative at worst, with a floor of 1% of the array's largest
  // gradient). Entries whose perturbation changes a discrete decision of the
  // render are skipped.
  AnchorModel x = m;
  const std::vector<int> base = ref::discrete_decisions(rg, cam, settings);
  auto images = [&](const AnchorModel& mm, bool* same) {
    const ref::RefGaussians g = to_ref(expand_reference_double(mm, degree));
    *same = ref::discrete_decisions(g, cam, settings) == base;
    return ref::render(g, cam, settings);
  };
  using Accessor = std::vector<float>& (AnchorModel::*)();
  struct Probe {
    const char* name;
    Accessor acc;
    const std::vector<float>* dev;
    std::vector<size_t> entries;
  };
  const std::vector<Probe> probes = {
      {"feature", &AnchorModel::feature, &dev.feature, {0, 4, 8, 10}},
      {"offset", &AnchorModel::offset, &dev.offset, {0, 1, 2, 16, 29, 44, 58}},
      {"scale_logit", &AnchorModel::scale_logit, &dev.scale_logit, {0, 5, 22, 37, 50}},
      {"quat", &AnchorModel::quat, &dev.quat, {1, 4, 30, 63, 77}},
      {"opacity_logit", &AnchorModel::opacity_logit, &dev.opacity_logit, {0, 3, 7, 12, 19}},
      {"sh", &AnchorModel::sh, &dev.sh, {0, 2, 4, 11, 48 * 6 + 1, 48 * 13 + 9, 48 * 19 + 3}},
  };
  int checked = 0, skipped = 0;
  double worst = 0;
  for (const Probe& p : probes) {
    double scale = 0;
    for (float g : *p.dev) scale = std::max(scale, std::abs(double(g)));
    for (size_t i : p.entries) {
      std::vector<float>& arr = (x.*p.acc)();
      const float x0 = arr[i];
      const float h = 1e-3f * std::max(1.f, std::abs(x0));
      bool same_p, same_m;
      arr[i] = x0 + h;
      const double xp = arr[i];
      const ref::RefImages ip = images(x, &same_p);
      arr[i] = x0 - h;
      const double xm = arr[i];
      const ref::RefImages im = images(x, &same_m);
      arr[i] = x0;
      if (!same_p || !same_m) {
        ++skipped;
        continue;
      }
      const double fd = (dot_diff(og.rgb, ip.rgb, im.rgb) + dot_diff(og.feature, ip.feature, im.feature) +
                         dot_diff(og.depth, ip.depth, im.depth) + dot_diff(og.alpha, ip.alpha, im.alpha) +
                         dot_diff(og.distortion, ip.distortion, im.distortion)) /
                        (xp - xm);
      const double g = (*p.dev)[i];
      const double err = std::abs(g - fd) / std::max({std::abs(fd), std::abs(g), 1e-2 * scale});
      worst = std::max(worst, err);
      ++checked;
      EXPECT_LT(err, 1e-3) << p.name << "[" << i << "] device " << g << " fd " << fd;
    }
  }
  std::printf("  chain vs central differences: %d checked, %d skipped, max rel error %.3g\n", checked, skipped, worst);
  EXPECT_GE(checked, 25);
  // Coefficients above the active degree get exactly zero.
  for (size_t g = 0; g < m.gaussians(); ++g)
    for (int k = 3 * sh_coeffs_for_degree(degree); k < 48; ++k) ASSERT_EQ(dev.sh[48 * g + k], 0.f);
}

TEST(Expander, ChainGradientsAreBitReproducible) {
  const AnchorModel m = random_model(600, 101, false);
  const Camera cam = test::look_at_origin(64, 48);
  const OutputGrads og = chain_output_grads(cam.width, cam.height, 102);
  std::vector<float> rgb1, rgb2;
  const AnchorGrads a = run_chain(m, cam, og, 3, &rgb1);
  const AnchorGrads b = run_chain(m, cam, og, 3, &rgb2);
  EXPECT_TRUE(same_bytes(rgb1, rgb2));
  double nz = 0;
  for (float x : rgb1) nz += x != 0;
  EXPECT_GT(nz, rgb1.size() / 4);  // the scene covers the image
  EXPECT_TRUE(same_bytes(a.feature, b.feature));
  EXPECT_TRUE(same_bytes(a.offset, b.offset));
  EXPECT_TRUE(same_bytes(a.scale_logit, b.scale_logit));
  EXPECT_TRUE(same_bytes(a.quat, b.quat));
  EXPECT_TRUE(same_bytes(a.opacity_logit, b.opacity_logit));
  EXPECT_TRUE(same_bytes(a.sh, b.sh));
  EXPECT_TRUE(test::all_finite(a.offset) && test::all_finite(a.sh) && test::all_finite(a.feature));
}

// Not a correctness check: the cost of expand forward + backward at the
// design's scale (20k anchors x 5 children), printed for the record.
TEST(Expander, Timing20kAnchors) {
  Runtime& rt = test::runtime();
  AnchorConfig c;
  AnchorModel m;
  m.reset(unit_grid(c), c);
  for (int i = 0; m.size() < 20000; ++i) m.add_anchor(0, Eigen::Vector3i(i % 40, (i / 40) % 40, i / 1600), -1, 1);
  randomise(m, 5, false);
  DeviceAnchors dev(rt);
  dev.upload(m);
  Expander ex(rt);
  DeviceGaussians out(rt);
  DeviceAnchorGrads grads(rt);
  GaussianGradBuffers v(rt);
  fill_random_grads(v, m.gaussians(), 3, 1);
  ex.forward(dev, out, 3);
  ex.backward(dev, v.view(), grads);
  AG2GS_CL_CHECK(rt.queue().finish());
  const int reps = 20;
  auto t0 = std::chrono::steady_clock::now();
  for (int r = 0; r < reps; ++r) ex.forward(dev, out, 3);
  AG2GS_CL_CHECK(rt.queue().finish());
  auto t1 = std::chrono::steady_clock::now();
  for (int r = 0; r < reps; ++r) ex.backward(dev, v.view(), grads);
  AG2GS_CL_CHECK(rt.queue().finish());
  auto t2 = std::chrono::steady_clock::now();
  const double fwd = std::chrono::duration<double, std::milli>(t1 - t0).count() / reps;
  const double bwd = std::chrono::duration<double, std::milli>(t2 - t1).count() / reps;
  std::printf("  expand 20000 anchors x 5 (SH 3) on %s: forward %.3f ms, backward %.3f ms\n", rt.info().name.c_str(),
              fwd, bwd);
}

}  // namespace
}  // namespace ag2gs
