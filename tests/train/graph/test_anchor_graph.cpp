// Stage 2: the anchor graph (train/graph/anchor_graph.h) against a brute-force
// O(N^2) construction and a hand-made case, its archive round trip and
// validation; the propagation loss (train/graph/propagation_loss.h,
// kernels/propagation_loss.cl) against a double-precision edge-list reference, the
// reference against central finite differences, and determinism across PoCL
// thread counts.
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <random>
#include <string>
#include <utility>
#include <vector>

#include "host/io/model_io.h"
#include "tests/cli_test_util.h"
#include "tests/io_test_util.h"
#include "tests/reference/anchor_graph_reference.h"
#include "tests/reference/propagation_loss_reference.h"
#include "tests/test_util.h"
#include "train/anchors/anchor_model.h"
#include "train/graph/anchor_graph.h"
#include "train/graph/propagation_loss.h"

namespace ag2gs {
namespace {

AnchorConfig small_config(int layer_ratio, int layers) {
  AnchorConfig c;
  c.children = 1;
  c.layers = layers;
  c.layer_ratio = layer_ratio;
  c.sh_degree = 0;
  return c;
}

VoxelGrid grid_for(const AnchorConfig& c, const Eigen::Vector3d& origin, double top_voxel) {
  VoxelGrid g;
  g.origin = origin;
  g.top_voxel = top_voxel;
  g.layer_ratio = c.layer_ratio;
  g.layers = c.layers;
  return g;
}

// Anchors at random layers in a box of `span` top-layer cells per axis around
// the origin cell (negative cells included), `n` attempts (duplicates skipped).
AnchorModel random_model(size_t n, int layer_ratio, int layers, int span, uint32_t seed) {
  AnchorConfig c = small_config(layer_ratio, layers);
  AnchorModel m;
  m.reset(grid_for(c, Eigen::Vector3d(0.3, -1.2, 2.0), 0.37), c);
  std::mt19937 rng(seed);
  std::uniform_int_distribution<int> pick_layer(0, layers - 1);
  for (size_t k = 0; k < n; ++k) {
    const int layer = pick_layer(rng);
    int f = 1;
    for (int l = 0; l < layer; ++l) f *= layer_ratio;
    std::uniform_int_distribution<int> u(-span / 2 * f, (span - span / 2) * f - 1);
    m.add_anchor(layer, Eigen::Vector3i(u(rng), u(rng), u(rng)), -1, seed);
  }
  return m;
}

void expect_graph_equals(const AnchorGraph& g, const std::vector<std::vector<int>>& rows) {
  ASSERT_EQ(g.anchors(), rows.size());
  size_t entries = 0;
  for (size_t i = 0; i < rows.size(); ++i) {
    const std::vector<int> got(g.neighbours().begin() + g.row_offsets()[i],
                               g.neighbours().begin() + g.row_offsets()[i + 1]);
    ASSERT_EQ(got, rows[i]) << "row " << i;
    entries += rows[i].size();
  }
  EXPECT_EQ(g.entries(), entries);
}

std::vector<std::pair<int, int>> edge_list(const AnchorGraph& g) {
  std::vector<std::pair<int, int>> e;
  for (size_t i = 0; i < g.anchors(); ++i)
    for (int k = g.row_offsets()[i]; k < g.row_offsets()[i + 1]; ++k)
      if (g.neighbours()[k] > static_cast<int>(i)) e.emplace_back(static_cast<int>(i), g.neighbours()[k]);
  return e;
}

// ------------------------------------------------------------------ graph

TEST(AnchorGraph, MatchesBruteForce) {
  struct Case {
    int ratio, layers, span, scale;
    size_t n;
  };
  const Case cases[] = {{4, 3, 5, 1, 500}, {4, 3, 5, 2, 500}, {4, 3, 7, 3, 400},
                        {2, 4, 6, 1, 600}, {2, 2, 4, 2, 300}, {4, 1, 8, 1, 400}};
  uint32_t seed = 11;
  for (const Case& c : cases) {
    const AnchorModel m = random_model(c.n, c.ratio, c.layers, c.span, seed++);
    const AnchorGraph g = AnchorGraph::build(m, c.scale);
    SCOPED_TRACE("ratio " + std::to_string(c.ratio) + " layers " + std::to_string(c.layers) + " scale " +
                 std::to_string(c.scale) + " anchors " + std::to_string(m.size()));
    EXPECT_EQ(g.cell_scale(), c.scale);
    expect_graph_equals(g, ref::anchor_graph_rows_reference(m, c.scale));
    EXPECT_NO_THROW(g.validate());
    EXPECT_GT(g.edges(), m.size());  // dense enough to mean something
    EXPECT_TRUE(g.matches(m));
  }
}

TEST(AnchorGraph, EmptyAndSingleAnchor) {
  AnchorConfig c = small_config(4, 3);
  AnchorModel m;
  m.reset(grid_for(c, Eigen::Vector3d::Zero(), 1.0), c);
  AnchorGraph g = AnchorGraph::build(m);
  EXPECT_EQ(g.anchors(), 0u);
  EXPECT_EQ(g.entries(), 0u);
  EXPECT_NO_THROW(g.validate());
  EXPECT_TRUE(g.degree_histogram().empty());
  m.add_anchor(2, Eigen::Vector3i(-3, 5, 7), -1, 1);
  g = AnchorGraph::build(m, 2);
  EXPECT_EQ(g.anchors(), 1u);
  EXPECT_EQ(g.entries(), 0u);
  EXPECT_EQ(g.degree(0), 0);
  EXPECT_EQ(g.degree_histogram(), std::vector<int64_t>({1}));
}

// Exact ground truth by hand (ratio 4, unit top voxels, origin 0):
//   0: layer 0 cell (0,0,0)   top cell (0,0,0)
//   1: layer 2 cell (15,15,15) top cell (0,0,0)   (intra-voxel with 0, across layers)
//   2: layer 1 cell (4,0,0)   top cell (1,0,0)    (26-neighbour of 0 and 1)
//   3: layer 0 cell (2,0,0)   top cell (2,0,0)    (neighbour of 2 only)
//   4: layer 1 cell (-1,-1,-1) top cell (-1,-1,-1) (diagonal neighbour of 0 and 1)
//   5: layer 0 cell (0,2,0)   top cell (0,2,0)    (isolated at scale 1)
// At scale 2 (floor division of the top cells by 2): 0, 1, 2 -> (0,0,0),
// 3 -> (1,0,0), 4 -> (-1,-1,-1), 5 -> (0,1,0): every pair is joined except
// 3-4 (x differs by 2) and 4-5 (y differs by 2).
TEST(AnchorGraph, HandMadeIntraAndInterVoxelEdges) {
  AnchorConfig c = small_config(4, 3);
  AnchorModel m;
  m.reset(grid_for(c, Eigen::Vector3d::Zero(), 1.0), c);
  m.add_anchor(0, Eigen::Vector3i(0, 0, 0), -1, 1);
  m.add_anchor(2, Eigen::Vector3i(15, 15, 15), -1, 1);
  m.add_anchor(1, Eigen::Vector3i(4, 0, 0), -1, 1);
  m.add_anchor(0, Eigen::Vector3i(2, 0, 0), -1, 1);
  m.add_anchor(1, Eigen::Vector3i(-1, -1, -1), -1, 1);
  m.add_anchor(0, Eigen::Vector3i(0, 2, 0), -1, 1);
  ASSERT_EQ(m.size(), 6u);
  expect_graph_equals(AnchorGraph::build(m, 1), {{1, 2, 4}, {0, 2, 4}, {0, 1, 3}, {2}, {0, 1}, {}});
  expect_graph_equals(AnchorGraph::build(m, 2),
                      {{1, 2, 3, 4, 5}, {0, 2, 3, 4, 5}, {0, 1, 3, 4, 5}, {0, 1, 2, 5}, {0, 1, 2}, {0, 1, 2, 3}});
  const AnchorGraph g = AnchorGraph::build(m, 1);
  EXPECT_EQ(g.edges(), 6u);
  // degrees 3,3,3,1,2,0 -> bins: 0 -> 1, [1,2) -> 1, [2,4) -> 4
  EXPECT_EQ(g.degree_histogram(), std::vector<int64_t>({1, 1, 4}));
}

TEST(AnchorGraph, DeterministicAndTracksAnchorChanges) {
  AnchorModel m = random_model(400, 4, 3, 5, 3);
  const AnchorGraph a = AnchorGraph::build(m), b = AnchorGraph::build(m);
  EXPECT_TRUE(a == b);
  // Growing: a new anchor makes the graph stale; the rebuilt one matches brute force.
  ASSERT_GE(m.add_anchor(2, Eigen::Vector3i(100, 100, 100), -1, 3), 0);
  EXPECT_FALSE(a.matches(m));
  AnchorGraph grown = AnchorGraph::build(m);
  EXPECT_TRUE(grown.matches(m));
  expect_graph_equals(grown, ref::anchor_graph_rows_reference(m, 1));
  // Pruning every third anchor: ids shift, the rebuilt graph follows.
  std::vector<uint8_t> keep(m.size(), 1);
  for (size_t i = 0; i < keep.size(); i += 3) keep[i] = 0;
  m.remove_anchors(keep);
  EXPECT_FALSE(grown.matches(m));
  expect_graph_equals(AnchorGraph::build(m), ref::anchor_graph_rows_reference(m, 1));
  EXPECT_THROW(AnchorGraph::build(m, 0), std::invalid_argument);
}

TEST(AnchorGraph, ArchiveRoundTripAndValidation) {
  const AnchorModel m = random_model(300, 4, 3, 8, 5);
  const AnchorGraph g = AnchorGraph::build(m, 2);
  test::ScratchDir dir("graph");
  const std::string path = dir.file("model.ag2gs");
  {
    ModelArchive ar;
    m.to_archive(ar);
    g.to_archive(ar);
    write_model_archive(path, ar);
  }
  const ModelArchive back = read_model_archive(path);
  ASSERT_TRUE(AnchorGraph::in_archive(back));
  const AnchorGraph g2 = AnchorGraph::from_archive(back);
  EXPECT_TRUE(g2 == g);
  EXPECT_EQ(g2.cell_scale(), 2);
  EXPECT_TRUE(g2.matches(AnchorModel::from_archive(back)));

  // A model without a graph, and broken graphs: errors name the file and the fault.
  ModelArchive none;
  m.to_archive(none);
  none.source = path;
  EXPECT_FALSE(AnchorGraph::in_archive(none));
  test::expect_error_with<std::runtime_error>([&] { AnchorGraph::from_archive(none); },
                                              {path, "no meta entry 'graph'"});

  // Asymmetric: the last entry z of some row i becomes v > z (the row stays
  // ascending) where i is not in row v.
  ModelArchive asym = back;
  std::vector<int32_t> nb = back.get<int32_t>("graph/neighbours");
  std::vector<int32_t> off = back.get<int32_t>("graph/row_offsets");
  bool corrupted = false;
  for (size_t i = 0; i < g.anchors() && !corrupted; ++i) {
    if (off[i + 1] == off[i]) continue;
    for (int v = nb[off[i + 1] - 1] + 1; v < static_cast<int>(g.anchors()) && !corrupted; ++v) {
      if (v == static_cast<int>(i) ||
          std::binary_search(nb.begin() + off[v], nb.begin() + off[v + 1], static_cast<int32_t>(i)))
        continue;
      nb[off[i + 1] - 1] = v;
      corrupted = true;
    }
  }
  ASSERT_TRUE(corrupted);
  asym.put("graph/neighbours", nb, {static_cast<int64_t>(nb.size())});
  test::expect_error_with<std::runtime_error>([&] { AnchorGraph::from_archive(asym); }, {path, "not symmetric"});

  ModelArchive self_loop = back;
  nb = back.get<int32_t>("graph/neighbours");
  ASSERT_GT(off[2], off[1]);
  nb[off[1]] = 1;  // an entry of row 1 becomes 1 itself
  self_loop.put("graph/neighbours", nb, {static_cast<int64_t>(nb.size())});
  test::expect_error_with<std::runtime_error>([&] { AnchorGraph::from_archive(self_loop); }, {path});

  ModelArchive short_offsets = back;
  off.pop_back();
  short_offsets.put("graph/row_offsets", off, {static_cast<int64_t>(off.size())});
  test::expect_error_with<std::runtime_error>([&] { AnchorGraph::from_archive(short_offsets); },
                                              {path, "graph/row_offsets"});

  ModelArchive bad_scale = back;
  bad_scale.meta["graph"]["cell_scale"] = 0;
  test::expect_error_with<std::runtime_error>([&] { AnchorGraph::from_archive(bad_scale); }, {path, "cell_scale"});
}

// `ag2gs info MODEL_DIR` reports the stored graph: edges, degree histogram,
// and a stale graph (anchors changed after it was built).
TEST(AnchorGraph, InfoReportsTheGraph) {
  AnchorConfig c = small_config(4, 3);
  AnchorModel m;
  m.reset(grid_for(c, Eigen::Vector3d::Zero(), 1.0), c);
  m.add_anchor(0, Eigen::Vector3i(0, 0, 0), -1, 1);
  m.add_anchor(2, Eigen::Vector3i(15, 15, 15), -1, 1);
  m.add_anchor(1, Eigen::Vector3i(4, 0, 0), -1, 1);
  m.add_anchor(0, Eigen::Vector3i(2, 0, 0), -1, 1);
  m.add_anchor(1, Eigen::Vector3i(-1, -1, -1), -1, 1);
  m.add_anchor(0, Eigen::Vector3i(0, 2, 0), -1, 1);
  const AnchorGraph g = AnchorGraph::build(m);  // degrees 3,3,3,1,2,0 (HandMade above)
  test::ScratchDir dir("graph_info");
  ModelArchive ar;
  m.to_archive(ar);
  g.to_archive(ar);
  write_model_archive(dir.file("model.ag2gs"), ar);
  test::CliResult r = test::run_cli("info " + dir.str());
  ASSERT_EQ(r.code, 0) << r.output;
  EXPECT_NE(r.output.find("anchor graph: 6 anchors, 6 edges (cell scale 1), mean degree 2.00"), std::string::npos)
      << r.output;
  EXPECT_NE(r.output.find("degree histogram: 0: 1, 1-1: 1, 2-3: 4"), std::string::npos) << r.output;
  EXPECT_EQ(r.output.find("stale"), std::string::npos) << r.output;
  m.add_anchor(0, Eigen::Vector3i(9, 9, 9), -1, 1);
  m.to_archive(ar);
  write_model_archive(dir.file("model.ag2gs"), ar);
  r = test::run_cli("info " + dir.str());
  ASSERT_EQ(r.code, 0) << r.output;
  EXPECT_NE(r.output.find("stale"), std::string::npos) << r.output;
}

// ------------------------------------------------------------ prop loss

// Features in three groups by x position (an "object" each) plus noise of
// ~tau: weights inside a group spread over (0, 1], across groups ~0.
std::vector<double> grouped_features(const AnchorModel& m, uint32_t seed, double noise = 0.04) {
  std::mt19937 rng(seed);
  std::normal_distribution<double> nrm(0, noise);
  const double centres[3][3] = {{0.1, 0.2, 0.3}, {0.5, 0.1, -0.2}, {-0.3, 0.4, 0.0}};
  std::vector<double> f(3 * m.size());
  for (size_t i = 0; i < m.size(); ++i) {
    const int grp = std::clamp(static_cast<int>(std::floor(m.pos()[3 * i] * 1.3)) + 1, 0, 2);
    for (int c = 0; c < 3; ++c) f[3 * i + c] = centres[grp][c] + nrm(rng);
  }
  return f;
}

std::vector<float> to_float(const std::vector<double>& v) {
  return std::vector<float>(v.begin(), v.end());
}

TEST(PropagationLossReference, GradientMatchesFiniteDifferences) {
  const AnchorModel m = random_model(120, 4, 2, 3, 21);
  const auto edges = edge_list(AnchorGraph::build(m));
  ASSERT_GT(edges.size(), 100u);
  const std::vector<double> f = grouped_features(m, 4);
  const double tau = 0.05, h = 1e-6;
  for (bool full : {true, false}) {
    const ref::RefPropLoss r = ref::propagation_loss_reference(edges, f, tau, full);
    double max_err = 0, max_g = 0;
    for (size_t k = 0; k < f.size(); ++k) {
      std::vector<double> fp = f, fm = f;
      fp[k] += h;
      fm[k] -= h;
      // Exact gradient: of L itself; stop-gradient: of L with the weights frozen at f.
      const double lp = full ? ref::propagation_loss_reference(edges, fp, tau, full).loss
                             : ref::propagation_loss_frozen_weights(edges, fp, f, tau);
      const double lm = full ? ref::propagation_loss_reference(edges, fm, tau, full).loss
                             : ref::propagation_loss_frozen_weights(edges, fm, f, tau);
      max_err = std::max(max_err, std::abs((lp - lm) / (2 * h) - r.grad[k]));
      max_g = std::max(max_g, std::abs(r.grad[k]));
    }
    std::printf("  %s weights: max |grad| %.3g, max |fd - grad| %.3g\n", full ? "differentiated" : "constant", max_g,
                max_err);
    EXPECT_GT(max_g, 1e-4);
    EXPECT_LT(max_err, 1e-6 * max_g);
    EXPECT_NEAR(ref::propagation_loss_frozen_weights(edges, f, f, tau), r.loss, 1e-15);
  }
  // The two modes differ (some edges are past the sign change at sqrt(2) tau).
  EXPECT_NE(ref::propagation_loss_reference(edges, f, tau, true).grad,
            ref::propagation_loss_reference(edges, f, tau, false).grad);
}

TEST(PropagationLoss, DeviceMatchesReference) {
  const AnchorModel m = random_model(1500, 4, 3, 6, 31);
  const AnchorGraph g = AnchorGraph::build(m);
  const auto edges = edge_list(g);
  const std::vector<double> f = grouped_features(m, 8);
  // The reference sees the float-rounded features the device saw.
  std::vector<double> fr(f.size());
  for (size_t k = 0; k < f.size(); ++k) fr[k] = static_cast<float>(f[k]);
  for (bool full : {false, true})
    for (float weight : {0.01f, 1.0f}) {
      SCOPED_TRACE(std::string(full ? "differentiated" : "constant") + " weights, weight " + std::to_string(weight));
      const ref::RefPropLoss r = ref::propagation_loss_reference(edges, fr, 0.05f, full);
      double gmax = 0;
      for (double v : r.grad) gmax = std::max(gmax, weight * std::abs(v));
      // Gradients accumulate onto what is there: prefill with values of the gradient's size.
      std::mt19937 rng(2);
      std::uniform_real_distribution<double> u(-1, 1);
      std::vector<float> grads(f.size());
      std::vector<double> want(f.size());
      for (size_t k = 0; k < f.size(); ++k) {
        grads[k] = static_cast<float>(u(rng) * gmax);
        want[k] = grads[k] + weight * r.grad[k];
      }
      PropagationLossConfig cfg;
      cfg.differentiate_weights = full;
      PropagationLoss prop(test::runtime(), cfg);
      prop.set_graph(g);
      EXPECT_EQ(prop.edges(), edges.size());
      const double loss = prop.forward_backward(to_float(f), &grads, weight);
      std::printf("  loss device %.9g reference %.9g (%zu edges, %zu anchors), max |grad| %.3g\n", loss, r.loss,
                  edges.size(), m.size(), gmax);
      EXPECT_NEAR(loss, r.loss, 2e-6 * r.loss);
      // float32 row sums of ~100 terms: measured max error 3.5e-7 of the largest entry.
      test::expect_close("grad", test::compare(grads, want, 1e-5 * gmax, 1e-4));
      // Loss only: gradients untouched, same loss bits.
      EXPECT_EQ(prop.forward_backward(to_float(f), nullptr, weight), loss);
    }
}

TEST(PropagationLoss, EmptyGraphsAndBadInput) {
  PropagationLoss prop(test::runtime());
  // No anchors at all.
  std::vector<float> none;
  EXPECT_EQ(prop.forward_backward(none, &none), 0.0);
  // Isolated anchors: no edges, loss 0, gradients unchanged.
  AnchorConfig c = small_config(4, 3);
  AnchorModel m;
  m.reset(grid_for(c, Eigen::Vector3d::Zero(), 1.0), c);
  m.add_anchor(0, Eigen::Vector3i(0, 0, 0), -1, 1);
  m.add_anchor(0, Eigen::Vector3i(5, 0, 0), -1, 1);
  prop.set_graph(AnchorGraph::build(m));
  std::vector<float> f = {0.1f, 0.2f, 0.3f, -0.1f, 0.f, 0.5f}, grads = {1, 2, 3, 4, 5, 6};
  EXPECT_EQ(prop.forward_backward(f, &grads, 1.0f), 0.0);
  EXPECT_EQ(grads, std::vector<float>({1, 2, 3, 4, 5, 6}));
  // Two anchors in one voxel: L = w d exactly, gradient 2 w (f_i - f_j) * weight.
  m.add_anchor(2, Eigen::Vector3i(1, 2, 3), -1, 1);  // inside top cell (0,0,0) with anchor 0
  prop.set_graph(AnchorGraph::build(m));
  ASSERT_EQ(prop.edges(), 1u);
  f = {0.1f, 0.2f, 0.3f, -0.1f, 0.f, 0.5f, 0.13f, 0.16f, 0.3f};
  grads.assign(9, 0.f);
  const double d = 0.03 * 0.03 + 0.04 * 0.04, w = std::exp(-d / (2 * 0.05 * 0.05));
  EXPECT_NEAR(prop.forward_backward(f, &grads, 1.0f), w * d, 1e-6 * w * d);
  EXPECT_NEAR(grads[0], 2 * w * (0.1 - 0.13), 1e-6);
  EXPECT_NEAR(grads[7], -2 * w * (0.2 - 0.16), 1e-6);
  EXPECT_EQ(grads[3], 0.f);
  // Wrong sizes name the fix.
  std::vector<float> short_f(6, 0.f);
  test::expect_error_with<std::invalid_argument>([&] { prop.forward_backward(short_f, nullptr); }, {"3 anchors"});
  DeviceBuffer stale(&test::runtime());
  stale.upload(std::vector<float>(12, 0.f));
  test::expect_error_with<std::invalid_argument>([&] { prop.enqueue(stale, nullptr, 4); },
                                                 {"of 4 anchors", "graph of 3", "rebuild the graph"});
  PropagationLossConfig bad;
  bad.tau = 0;
  EXPECT_THROW(PropagationLoss(test::runtime(), bad), std::invalid_argument);
}

uint64_t prop_hash() {
  const AnchorModel m = random_model(3000, 4, 3, 8, 41);
  const AnchorGraph g = AnchorGraph::build(m);
  const std::vector<float> f = to_float(grouped_features(m, 9));
  uint64_t h = test::hash_vec(g.row_offsets());
  h = test::hash_vec(g.neighbours(), h);
  for (bool full : {false, true}) {
    PropagationLossConfig cfg;
    cfg.differentiate_weights = full;
    PropagationLoss prop(test::runtime(), cfg);
    prop.set_graph(g);
    std::vector<float> grads(f.size(), 0.25f);
    const double loss = prop.forward_backward(f, &grads, 0.01f);
    h = test::hash_bytes(&loss, sizeof loss, h);
    h = test::hash_vec(grads, h);
  }
  return h;
}

// Run by the test below in a child process with a given thread count.
TEST(PropagationLossWorker, WriteHash) {
  const char* out = std::getenv("AG2GS_HASH_OUT");
  if (!out) GTEST_SKIP() << "only run as a child of SameBitsAcrossThreadCounts";
  std::ofstream(out) << prop_hash() << "\n";
}

TEST(PropagationLoss, SameBitsAcrossThreadCounts) {
  char exe[4096];
  const ssize_t len = readlink("/proc/self/exe", exe, sizeof exe - 1);
  ASSERT_GT(len, 0);
  exe[len] = 0;
  std::string hashes[2];
  for (int threads = 1; threads <= 2; ++threads) {
    const std::string file =
        testing::TempDir() + "ag2gs_prop_hash_" + std::to_string(::getpid()) + "_" + std::to_string(threads);
    const std::string cmd = "POCL_MAX_PTHREAD_COUNT=" + std::to_string(threads) + " AG2GS_HASH_OUT=" + file + " " +
                            exe + " --gtest_filter=PropagationLossWorker.WriteHash > /dev/null 2>&1";
    ASSERT_EQ(std::system(cmd.c_str()), 0) << cmd;
    std::ifstream in(file);
    std::getline(in, hashes[threads - 1]);
    std::remove(file.c_str());
    ASSERT_FALSE(hashes[threads - 1].empty());
  }
  EXPECT_EQ(hashes[0], hashes[1]) << "1 thread vs 2 threads";
  EXPECT_EQ(hashes[0], std::to_string(prop_hash())) << "child vs this process";
}

// ---------------------------------------------------------------- timing
// Not part of the suite (DISABLED_): run with
//   build/test_anchor_graph --gtest_also_run_disabled_tests --gtest_filter='*Timing*'
// A shell of anchors like a scanned surface: layer 0 on a sphere of radius
// R top cells, layers 1 and 2 on the same sphere (finer, so more of them).
AnchorModel sphere_model(double radius, bool sorted, uint32_t seed) {
  AnchorConfig c = small_config(4, 3);
  AnchorModel m;
  m.reset(grid_for(c, Eigen::Vector3d::Zero(), 1.0), c);
  std::mt19937 rng(seed);
  std::normal_distribution<double> nrm(0, 1);
  const size_t points = static_cast<size_t>(40 * radius * radius);
  std::vector<std::pair<uint64_t, Eigen::Vector3i>> cells;
  for (size_t k = 0; k < points; ++k) {
    Eigen::Vector3d p(nrm(rng), nrm(rng), nrm(rng));
    p = p.normalized() * radius;
    const int layer = k % 10 == 0 ? 0 : (k % 10 < 5 ? 1 : 2);
    const Eigen::Vector3i c = m.grid().cell_of(layer, p);
    cells.emplace_back(anchor_voxel_key(layer, c), c);
  }
  // Random order scatters neighbours over memory; sorted is (layer, x, y, z),
  // the order initialise_from_points creates.
  if (sorted) std::sort(cells.begin(), cells.end(), [](const auto& a, const auto& b) { return a.first < b.first; });
  for (const auto& [key, c] : cells) m.add_anchor(static_cast<int>(key >> 60), c, -1, seed);
  return m;
}

TEST(AnchorGraphTiming, DISABLED_BuildAndLoss) {
  for (const auto& [radius, sorted] : {std::pair(50.0, true), std::pair(85.0, true), std::pair(85.0, false)}) {
    const AnchorModel m = sphere_model(radius, sorted, 1);
    std::printf("  anchors in %s order\n", sorted ? "(layer, x, y, z)" : "random");
    auto t0 = std::chrono::steady_clock::now();
    const AnchorGraph g = AnchorGraph::build(m);
    auto t1 = std::chrono::steady_clock::now();
    const auto hist = g.degree_histogram();
    int max_deg = 0;
    for (size_t i = 0; i < g.anchors(); ++i) max_deg = std::max(max_deg, g.degree(i));
    std::printf("  %zu anchors: graph build %.1f ms, %zu edges, mean degree %.1f, max %d\n", m.size(),
                std::chrono::duration<double, std::milli>(t1 - t0).count(), g.edges(),
                2.0 * g.edges() / std::max<size_t>(1, m.size()), max_deg);
    const AnchorGraph g2 = AnchorGraph::build(m, 2);
    auto t2 = std::chrono::steady_clock::now();
    std::printf("  scale 2: build %.1f ms, %zu edges\n", std::chrono::duration<double, std::milli>(t2 - t1).count(),
                g2.edges());
    auto tv = std::chrono::steady_clock::now();
    g.validate();
    std::printf("  validate %.1f ms\n",
                std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - tv).count());

    Runtime& rt = test::runtime();
    PropagationLoss prop(rt);
    prop.set_graph(g);
    DeviceBuffer feat(&rt), grads(&rt);
    feat.upload(to_float(grouped_features(m, 3)));
    grads.upload(std::vector<float>(3 * m.size(), 0.f));
    prop.enqueue(feat, &grads, m.size(), 0.01f);  // warm-up (kernel build)
    prop.result();
    rt.set_profiling(true);
    rt.take_timings();
    const int reps = 10;
    auto t3 = std::chrono::steady_clock::now();
    for (int r = 0; r < reps; ++r) {
      prop.enqueue(feat, &grads, m.size(), 0.01f);
      prop.result();
    }
    auto t4 = std::chrono::steady_clock::now();
    const auto timings = rt.take_timings();
    rt.set_profiling(false);
    auto per_call = [&](const char* k) { return timings.count(k) ? timings.at(k) / reps : -1.0; };
    std::printf("  loss+gradient: %.2f ms per call wall, kernels: prop_edges %.2f ms, prop_grad %.2f ms\n",
                std::chrono::duration<double, std::milli>(t4 - t3).count() / reps, per_call("prop_edges"),
                per_call("prop_grad"));
    auto ts = std::chrono::steady_clock::now();
    prop.set_graph(g);
    std::printf("  set_graph (edge list + upload) %.1f ms\n",
                std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - ts).count());
  }
}

// The graph and loss of a trained model: AG2GS_MODEL=path/to/model.ag2gs.
TEST(AnchorGraphTiming, DISABLED_TrainedModel) {
  const char* path = std::getenv("AG2GS_MODEL");
  if (!path) GTEST_SKIP() << "set AG2GS_MODEL";
  const AnchorModel m = AnchorModel::from_archive(read_model_archive(path));
  for (int scale : {1, 2}) {
    auto t0 = std::chrono::steady_clock::now();
    const AnchorGraph g = AnchorGraph::build(m, scale);
    const double ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
    std::printf("  %s: %zu anchors, scale %d: build %.1f ms, %zu edges, mean degree %.1f\n", path, m.size(), scale, ms,
                g.edges(), 2.0 * g.edges() / std::max<size_t>(1, m.size()));
    PropagationLoss prop(test::runtime());
    prop.set_graph(g);
    std::vector<float> grads(m.feature().size(), 0.f);
    t0 = std::chrono::steady_clock::now();
    const double loss = prop.forward_backward(m.feature(), &grads, 1.0f);
    double gmax = 0;
    for (float v : grads) gmax = std::max(gmax, std::abs(static_cast<double>(v)));
    std::printf("  L_prop %.4g, max |dL/df| %.3g, one call %.1f ms (with upload)\n", loss, gmax,
                std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count());
  }
}

}  // namespace
}  // namespace ag2gs
