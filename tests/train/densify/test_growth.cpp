// Anchor growing and pruning (train/densify/anchor_growth.h, kernels/anchor_growth.cl): the
// statistics kernel against a double-precision host computation, the
// decision step on a hand-made model (one case per rule), the gather maps
// with the optimiser state, determinism, and the device round trip after a
// decision (upload, expansion, render, more statistics).
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <random>
#include <vector>

#include "host/optim/adam.h"
#include "tests/reference/growth_stats_reference.h"
#include "tests/test_util.h"
#include "train/anchors/anchor_model.h"
#include "train/anchors/expander.h"
#include "train/densify/anchor_growth.h"
#include "train/eta.h"

namespace ag2gs {
namespace {

using test::runtime;

// Unit top voxels from the origin: layer L has edge 4^-L, exact cell math.
VoxelGrid unit_grid(const AnchorConfig& c) {
  VoxelGrid g;
  g.top_voxel = 1.0;
  g.layer_ratio = c.layer_ratio;
  g.layers = c.layers;
  return g;
}

Eigen::Vector3i cell_at(const AnchorModel& m, size_t a) {
  return Eigen::Vector3i(m.cell()[3 * a], m.cell()[3 * a + 1], m.cell()[3 * a + 2]);
}

// Feeds `steps` identical views: pixel gradients [N,2] and radii [N]; an
// entry of `seen_steps` >= 0 limits that child to the first seen_steps views.
void feed(AnchorGrowth& growth, const std::vector<float>& v_px, const std::vector<int>& radii, int steps, int w, int h,
          const std::vector<int>& seen_steps = {}) {
  DeviceBuffer grads(&runtime());
  grads.upload(v_px);
  for (int s = 0; s < steps; ++s) {
    std::vector<int> r = radii;
    for (size_t g = 0; g < seen_steps.size(); ++g)
      if (seen_steps[g] >= 0 && s >= seen_steps[g]) r[g] = 0;
    growth.accumulate(grads, r, w, h);
  }
}

// ---------------------------------------------------------------------------
// Config

TEST(GrowthConfig, ValidateScaleAndSchedule) {
  GrowthConfig c;
  EXPECT_NO_THROW(c.validate());
  for (auto mutate : std::vector<void (*)(GrowthConfig&)>{
           [](GrowthConfig& x) { x.grad_threshold = 0; }, [](GrowthConfig& x) { x.layer_factor = NAN; },
           [](GrowthConfig& x) { x.every = -1; }, [](GrowthConfig& x) { x.min_observations = 0; },
           [](GrowthConfig& x) { x.min_seen_fraction = 1.5f; }, [](GrowthConfig& x) { x.prune_opacity = 1; },
           [](GrowthConfig& x) { x.unseen_window = -2; }}) {
    GrowthConfig b;
    mutate(b);
    EXPECT_THROW(b.validate(), std::invalid_argument);
    EXPECT_THROW(AnchorGrowth(runtime(), b), std::invalid_argument);
  }
  // The official schedule (500..20k every 100 of 30k) for a 2000-iteration run.
  const GrowthConfig s = c.scale_to(2000);
  EXPECT_EQ(s.every, 10);   // 7 rounds up to the minimum round length
  EXPECT_EQ(s.start, 33);   // 500 / 15
  EXPECT_EQ(s.stop, 1333);  // 20000 / 15
  EXPECT_EQ(c.scale_to(15000).every, 50);
  EXPECT_EQ(c.scale_to(15000).start, 250);
  EXPECT_EQ(c.scale_to(15000).stop, 10000);
  EXPECT_EQ(c.scale_to(35000).stop, 20000);  // longer runs keep it
  EXPECT_EQ(c.scale_to(10000, 30000, 1).every, 33);
  EXPECT_THROW(c.scale_to(0), std::invalid_argument);
  EXPECT_FALSE(c.due(400));
  EXPECT_TRUE(c.due(500));
  EXPECT_FALSE(c.due(501));
  EXPECT_TRUE(c.due(20000));
  EXPECT_FALSE(c.due(20100));
  EXPECT_FALSE(c.collecting(400));
  EXPECT_TRUE(c.collecting(401));
  EXPECT_TRUE(c.collecting(20000));
  EXPECT_FALSE(c.collecting(20001));
  GrowthConfig off;
  off.every = 0;
  EXPECT_FALSE(off.due(500));
  EXPECT_FALSE(off.collecting(500));
}

// ---------------------------------------------------------------------------
// Statistics kernel

TEST(GrowthStats, KernelMatchesDoubleReference) {
  const size_t n = 1001;  // not a multiple of the work-group size
  std::mt19937 rng(7);
  std::normal_distribution<float> nrm(0.f, 1e-5f);
  std::uniform_real_distribution<double> u01(0, 1);
  struct View {
    int w, h;
    std::vector<float> v;
    std::vector<int> radii;
  };
  std::vector<View> views;
  for (int s = 0; s < 5; ++s) {
    View vw{64 + 37 * s, 48 + 11 * s, std::vector<float>(2 * n), std::vector<int>(n)};
    for (size_t g = 0; g < n; ++g) {
      vw.v[2 * g] = nrm(rng) * (1 + s);
      vw.v[2 * g + 1] = nrm(rng);
      vw.radii[g] = u01(rng) < 0.3 ? 0 : 1 + static_cast<int>(u01(rng) * 20);
    }
    views.push_back(vw);
  }
  views[2].v[2 * 5] = NAN;  // visible, non-finite: counts, adds nothing
  views[2].radii[5] = 3;
  views[3].v[2 * 6 + 1] = 1e30f;  // overflows to inf in float: likewise
  views[3].radii[6] = 2;
  for (size_t g = 990; g < n; ++g)
    for (View& vw : views) vw.radii[g] = 0;  // never seen

  for (bool ndc : {true, false}) {
    GrowthConfig c;
    c.ndc = ndc;
    AnchorGrowth growth(runtime(), c);
    growth.reset(n);
    ref::RefGrowthStats want = ref::growth_stats_reference(n);
    DeviceBuffer grads(&runtime());
    for (const View& vw : views) {
      grads.upload(vw.v);
      growth.accumulate(grads, vw.radii, vw.w, vw.h);
      ref::accumulate_growth_stats(want, vw.v, vw.radii, vw.w, vw.h, ndc);
    }
    const GrowthStatsHost st = growth.download();
    EXPECT_EQ(st.steps, 5);
    EXPECT_EQ(st.step, 5);
    double worst = 0;
    for (size_t g = 0; g < n; ++g) {
      ASSERT_EQ(st.count[g], want.count[g]) << g;
      ASSERT_EQ(st.last_seen[g], want.last_seen[g]) << g;
      const double err = std::abs(st.grad_sum[g] - want.grad_sum[g]);
      if (want.grad_sum[g] > 0) worst = std::max(worst, err / want.grad_sum[g]);
      // Measured: 1.5e-7 relative at worst (float products, a square root
      // and up to 5 sums); the bound leaves a factor of ~7.
      ASSERT_LE(err, 1e-6 * want.grad_sum[g]) << g << " device " << st.grad_sum[g] << " reference " << want.grad_sum[g];
    }
    std::printf("  ndc=%d: max rel error %.3g\n", ndc, worst);
    EXPECT_EQ(st.count[5], want.count[5]);
    EXPECT_GE(want.count[5], 1);
    EXPECT_EQ(st.count[995], 0);
    EXPECT_EQ(st.grad_sum[995], 0.f);
  }
}

TEST(GrowthStats, ChecksSizes) {
  AnchorGrowth growth(runtime(), GrowthConfig{});
  growth.reset(100);
  DeviceBuffer grads(&runtime());
  grads.upload(std::vector<float>(200, 0.f));
  EXPECT_THROW(growth.accumulate(grads, std::vector<int>(99, 1), 10, 10), std::invalid_argument);
  EXPECT_THROW(growth.accumulate(grads, std::vector<int>(100, 1), 0, 10), std::invalid_argument);
  DeviceBuffer small(&runtime());
  small.upload(std::vector<float>(100, 0.f));
  EXPECT_THROW(growth.accumulate(small, std::vector<int>(100, 1), 10, 10), std::invalid_argument);
  AnchorModel m;
  AnchorConfig c;
  m.reset(unit_grid(c), c);
  m.add_anchor(0, Eigen::Vector3i(0, 0, 0), -1, 1);
  EXPECT_THROW(growth.step(m, 1), std::invalid_argument);  // 5 Gaussians, stats for 100
  growth.reset(0);                                         // an empty model works too
  growth.accumulate(grads, std::vector<int>{}, 10, 10);
  AnchorModel empty;
  empty.reset(unit_grid(c), c);
  const GrowthResult r = growth.step(empty, 1);
  EXPECT_FALSE(r.changed());
  EXPECT_EQ(r.anchors_after, 0u);
}

// ---------------------------------------------------------------------------
// Decision step on a hand-made model
//
// Anchors (K = 5, children at their anchor's centre unless noted, opacity 0.5):
//   a0 layer 0 cell (0,0,0): rows 2 and 3 large gradients, means in the same
//      layer-1 voxel (3,2,2) -> one anchor, parent row 2
//   a1 layer 0 cell (2,0,0): row 5 large, its layer-1 voxel (10,2,2) is a5's ->
//      nothing; row 6 just below the threshold; row 7 large but visible in 3
//      of 10 views (< 40%) -> nothing
//   a2 layer 2 cell (1,1,1): row 10 huge, finest layer -> nothing
//   a3 layer 0 cell (4,0,0): opacity 0.0025 -> pruned; row 15 large -> an
//      anchor at layer-1 voxel (18,2,2) inheriting the low opacity, kept
//   a4 layer 0 cell (6,0,0): never visible -> pruned
//   a5 layer 1 cell (10,2,2): row 25 between 1x and 2x the threshold -> nothing
//      (layer 1 needs 2x); row 26 above 2x -> anchor at layer-2 voxel (42,10,10)
constexpr int kW = 200, kH = 100;  // NDC scale (100, 50)
constexpr float kLarge = 1e-5f;    // pixels: 1e-3 NDC along x, far above 1.5e-4

struct Scenario {
  AnchorModel model;
  std::vector<float> v_px;  // [30,2]
  std::vector<int> radii;   // [30]
  std::vector<int> seen;    // [30] views seen (-1: all)
};

Scenario scenario() {
  Scenario s;
  AnchorConfig c;
  s.model.reset(unit_grid(c), c);
  const int layers[6] = {0, 0, 2, 0, 0, 1};
  const Eigen::Vector3i cells[6] = {{0, 0, 0}, {2, 0, 0}, {1, 1, 1}, {4, 0, 0}, {6, 0, 0}, {10, 2, 2}};
  for (int a = 0; a < 6; ++a) EXPECT_EQ(s.model.add_anchor(layers[a], cells[a], -1, 11 + a), a);
  const size_t n = s.model.gaussians();
  std::fill(s.model.offset().begin(), s.model.offset().end(), 0.f);
  for (size_t g = 0; g < n; ++g) s.model.opacity_logit()[g] = 0.01f * g;  // distinct, ~0.5
  for (size_t g = 0; g < n; ++g) s.model.sh()[g * 48] = 0.1f * g;
  s.model.offset()[2 * 3] = 0.3f;   // row 2 mean (0.8, 0.5, 0.5)
  s.model.offset()[3 * 3] = 0.35f;  // row 3 mean (0.85, 0.55, 0.5)
  s.model.offset()[3 * 3 + 1] = 0.05f;
  s.model.offset()[7 * 3] = 0.3f;  // row 7 mean (2.8, 0.5, 0.5): voxel (11,2,2) is free
  for (int i = 0; i < 5; ++i) s.model.opacity_logit()[15 + i] = -6.f;
  s.v_px.assign(2 * n, 0.f);
  s.radii.assign(n, 4);
  s.seen.assign(n, -1);
  for (int g = 20; g < 25; ++g) s.radii[g] = 0;  // a4
  auto set = [&](int g, float ndc) { s.v_px[2 * g] = ndc / (0.5f * kW); };
  for (int g : {2, 3, 5, 7, 15}) set(g, 1e-3f);
  set(6, 1.4e-4f);
  set(10, 1.f);
  set(25, 2.5e-4f);
  set(26, 4e-4f);
  s.seen[7] = 3;
  return s;
}

struct Ran {
  AnchorModel before, after;
  GrowthResult r;
  GrowthStatsHost stats_after;
};

Ran run_scenario(const GrowthConfig& config = {}, uint64_t seed = 5) {
  Scenario s = scenario();
  AnchorGrowth growth(runtime(), config);
  growth.reset(s.model.gaussians());
  feed(growth, s.v_px, s.radii, 10, kW, kH, s.seen);
  Ran out;
  out.before = s.model;
  out.r = growth.step(s.model, seed);
  out.after = s.model;
  out.stats_after = growth.download();
  return out;
}

TEST(GrowthDecision, GrowsOneFinerAnchorPerRequestedVoxel) {
  const Ran x = run_scenario();
  const GrowthResult& r = x.r;
  EXPECT_EQ(r.requests, 5);  // rows 2, 3, 5, 15, 26
  EXPECT_EQ(r.added, 3);
  EXPECT_EQ(r.anchors_before, 6u);
  EXPECT_EQ(r.gaussians_before, 30u);
  // Survivors a0 a1 a2 a5, then the new anchors in voxel-key order.
  ASSERT_EQ(r.anchor_rows, (std::vector<int>{0, 1, 2, 5, -1, -1, -1}));
  ASSERT_EQ(x.after.size(), 7u);
  EXPECT_EQ(r.anchors_after, 7u);
  EXPECT_EQ(r.gaussians_after, 35u);
  const AnchorModel& m = x.after;
  EXPECT_EQ(m.layer()[4], 1);
  EXPECT_EQ(cell_at(m, 4), Eigen::Vector3i(3, 2, 2));
  EXPECT_EQ(m.layer()[5], 1);
  EXPECT_EQ(cell_at(m, 5), Eigen::Vector3i(18, 2, 2));
  EXPECT_EQ(m.layer()[6], 2);
  EXPECT_EQ(cell_at(m, 6), Eigen::Vector3i(42, 10, 10));
  EXPECT_EQ(m.voxel()[6], 1.f / 16);
  for (int k = 0; k < 3; ++k) EXPECT_EQ(m.pos()[3 * 4 + k], static_cast<float>(m.grid().centre(1, {3, 2, 2})[k]));
  // Two children asked for voxel (3,2,2): one anchor, parent the lower row (2).
  // New children: the parent child's SH, opacity at most the initial one.
  const double o0 = m.config().init_opacity;
  const float init_logit = static_cast<float>(std::log(o0 / (1 - o0)));
  for (int i = 0; i < 5; ++i) {
    EXPECT_EQ(m.opacity_logit()[4 * 5 + i], std::min(x.before.opacity_logit()[2], init_logit));
    EXPECT_EQ(m.sh()[(4 * 5 + i) * 48], x.before.sh()[2 * 48]);
    EXPECT_EQ(m.opacity_logit()[6 * 5 + i], std::min(x.before.opacity_logit()[26], init_logit));
  }
  // The occupied voxel (10,2,2) (row 5), the finest layer (row 10), the row
  // below the threshold (6), below 2x on layer 1 (25), seen too rarely (7).
  EXPECT_EQ(m.find(1, {10, 2, 2}), 3);
  EXPECT_EQ(m.find(1, {11, 2, 2}), -1);
  for (size_t a = 0; a < m.size(); ++a) EXPECT_NE(m.layer()[a], 3);
  m.check();
}

// Budgets: a round adds at most what round_growth and max_gaussians allow,
// and the voxels whose child asks hardest (gradient over its layer's
// threshold) win. In the scenario, (3,2,2) and (18,2,2) on layer 1 ask at
// 6.7x the threshold, (42,10,10) on layer 2 at 1.3x.
TEST(GrowthDecision, BudgetsKeepTheHardestAskingVoxels) {
  GrowthConfig per_round;
  per_round.round_growth = 0.3f;  // ceil(0.3 x 6 anchors) = 2
  per_round.min_round_anchors = 0;
  const Ran a = run_scenario(per_round);
  EXPECT_EQ(a.r.added, 2);
  EXPECT_EQ(a.r.over_budget, 1);
  EXPECT_GE(a.after.find(1, {3, 2, 2}), 0);
  EXPECT_GE(a.after.find(1, {18, 2, 2}), 0);
  EXPECT_EQ(a.after.find(2, {42, 10, 10}), -1);
  a.after.check();
  // The floor of a round: at least min_round_anchors.
  per_round.min_round_anchors = 64;
  EXPECT_EQ(run_scenario(per_round).r.added, 3);

  GrowthConfig total;
  total.max_gaussians = 41;  // 30 children now: room for two anchors of 5
  const Ran b = run_scenario(total);
  EXPECT_EQ(b.r.added, 2);
  EXPECT_EQ(b.r.over_budget, 1);
  EXPECT_EQ(b.after.find(2, {42, 10, 10}), -1);
  total.max_gaussians = 34;  // no room for one more anchor
  EXPECT_EQ(run_scenario(total).r.added, 0);
  total.max_gaussians = 0;  // no limit
  EXPECT_EQ(run_scenario(total).r.added, 3);
}

// Sideways growth (same_layer): a growing child whose mean left its anchor's
// voxel asks for an anchor of its own layer there, on the finest layer too;
// children inside their voxel ask for nothing more.
TEST(GrowthDecision, SameLayerGrowthFollowsChildrenOutOfTheirVoxel) {
  GrowthConfig sideways;
  sideways.same_layer = true;
  // The base scenario keeps every mean inside its own voxel: same decisions.
  const Ran base = run_scenario(), same = run_scenario(sideways);
  EXPECT_EQ(same.r.added, base.r.added);
  EXPECT_EQ(same.r.anchor_rows, base.r.anchor_rows);

  Scenario s = scenario();
  const float l2 = s.model.voxel()[2];  // a2 is on layer 2 (the finest)
  s.model.offset()[2 * 3] = 0.7f;       // row 2 mean x = 1.2: layer-0 cell (1,0,0), free
  s.model.offset()[10 * 3 + 1] = 0.9f;  // row 10 mean leaves a2's cell along y
  s.model.offset()[6 * 3] = 0.9f;       // row 6 below the threshold: stays put
  AnchorGrowth growth(runtime(), sideways);
  growth.reset(s.model.gaussians());
  feed(growth, s.v_px, s.radii, 10, kW, kH, s.seen);
  AnchorModel m = s.model;
  const GrowthResult r = growth.step(m, 5);
  // Row 2 asks for layer-1 (4,2,2) (row 3 asks for (3,2,2)) and layer-0
  // (1,0,0); row 10 asks for layer-2 (1,2,1) beside a2; rows 5, 15, 26 as before.
  EXPECT_GE(m.find(0, {1, 0, 0}), 0);
  EXPECT_GE(m.find(1, {4, 2, 2}), 0);
  EXPECT_GE(m.find(1, {3, 2, 2}), 0);
  const Eigen::Vector3d c2(m.grid().centre(2, {1, 1, 1}));
  const Eigen::Vector3i beside = m.grid().cell_of(2, c2 + Eigen::Vector3d(0, 0.9 * l2, 0));
  EXPECT_EQ(beside, Eigen::Vector3i(1, 2, 1));
  EXPECT_GE(m.find(2, beside), 0);
  EXPECT_EQ(m.find(0, {3, 0, 0}), -1);  // row 6 (a1, below the threshold) moved out but does not grow
  EXPECT_EQ(r.added, base.r.added + 3);
  m.check();
}

// Split growth (split_voxels): one large child, 0.9 x 0.6 x 0.1 world units
// (3.6 x 2.4 x 0.4 voxels of layer 1), turned 90 degrees about z so its
// longest axis points along world y. Besides the anchor at its mean it asks
// at +-1 sigma along each of its two longest axes that spans split_voxels
// finer voxels; the children of its anchors take its scale / 1.6, at least
// init_scale voxels. A small child of another anchor (0.2 world units, 0.8
// finer voxels) grows as published: one anchor, init_scale.
TEST(GrowthDecision, SplitGrowthCoversALargeChildAndHandsDownItsScale) {
  AnchorConfig c;
  c.children = 2;
  c.scale_cap = 64;
  auto grow = [&](float split_voxels) {
    AnchorModel m;
    m.reset(unit_grid(c), c);
    EXPECT_EQ(m.add_anchor(0, {2, 2, 2}, -1, 3), 0);
    EXPECT_EQ(m.add_anchor(0, {6, 2, 2}, -1, 3), 1);
    std::fill(m.offset().begin(), m.offset().end(), 0.f);
    const double sigma[3] = {0.9, 0.6, 0.1};
    for (int k = 0; k < 3; ++k) m.scale_logit()[k] = static_cast<float>(std::log(sigma[k] / (64 - sigma[k])));
    for (int k = 0; k < 3; ++k) m.scale_logit()[3 * 2 + k] = static_cast<float>(std::log(0.2 / (64 - 0.2)));
    const float h = static_cast<float>(std::sqrt(0.5));
    const float quarter_turn_z[4] = {h, 0, 0, h};
    std::copy_n(quarter_turn_z, 4, &m.quat()[0]);
    GrowthConfig g;
    g.split_voxels = split_voxels;
    AnchorGrowth growth(runtime(), g);
    growth.reset(m.gaussians());
    std::vector<float> v_px(2 * m.gaussians(), 0.f);
    v_px[0] = v_px[2 * 2] = 1e-3f / (0.5f * kW);  // children 0 and 2 ask, 1 and 3 do not
    feed(growth, v_px, std::vector<int>(m.gaussians(), 4), 10, kW, kH);
    growth.step(m, 5);
    m.check();
    return m;
  };
  const AnchorModel off = grow(0), on = grow(2), long_only = grow(3);
  ASSERT_EQ(off.size(), 4u);
  EXPECT_GE(off.find(1, {10, 10, 10}), 2);
  EXPECT_GE(off.find(1, {26, 10, 10}), 2);  // the small child's, at (6.5, 2.5, 2.5)
  ASSERT_EQ(on.size(), 8u);
  const int small = on.find(1, {26, 10, 10});
  ASSERT_GE(small, 2);
  for (const Eigen::Vector3i& cell :
       {Eigen::Vector3i(10, 10, 10), Eigen::Vector3i(10, 13, 10), Eigen::Vector3i(10, 6, 10),
        Eigen::Vector3i(7, 10, 10), Eigen::Vector3i(12, 10, 10)})
    EXPECT_GE(on.find(1, cell), 2) << cell.transpose();
  ASSERT_EQ(long_only.size(), 6u);  // 2.4 voxels < 3: the second axis asks for nothing
  EXPECT_EQ(long_only.find(1, {7, 10, 10}), -1);
  EXPECT_GE(long_only.find(1, {10, 13, 10}), 2);

  // Grown children: the parent's scale / 1.6 per axis (z held at 0.5 voxel
  // of 0.25), its rotation; without split, init_scale voxels.
  const double expect_on[3] = {0.9 / 1.6, 0.6 / 1.6, 0.5 * 0.25};
  auto world_scale = [](const AnchorModel& m, size_t g, int k) {
    return 64 * 0.25 / (1 + std::exp(-double(m.scale_logit()[3 * g + k])));
  };
  for (size_t a = 2; a < on.size(); ++a)
    for (size_t g = 2 * a; g < 2 * a + 2; ++g) {
      for (int k = 0; k < 3; ++k)
        EXPECT_NEAR(world_scale(on, g, k), static_cast<int>(a) == small ? 0.125 : expect_on[k], 1e-6)
            << "anchor " << a << " child " << g << " axis " << k;
      if (static_cast<int>(a) != small)
        for (int k = 0; k < 4; ++k) EXPECT_EQ(on.quat()[4 * g + k], on.quat()[k]);
    }
  for (size_t g = 4; g < off.gaussians(); ++g)
    for (int k = 0; k < 3; ++k) EXPECT_NEAR(world_scale(off, g, k), 0.125, 1e-6);
}

TEST(GrowthDecision, PrunesLowOpacityAndUnseenButNotNewAnchors) {
  const Ran x = run_scenario();
  EXPECT_EQ(x.r.pruned, 2);
  EXPECT_EQ(x.r.pruned_opacity, 1);  // a3
  EXPECT_EQ(x.r.pruned_unseen, 1);   // a4
  EXPECT_EQ(x.after.find(0, {4, 0, 0}), -1);
  EXPECT_EQ(x.after.find(0, {6, 0, 0}), -1);
  // Grown from a3's child: opacity 0.0025, born this step, kept.
  const int fresh = x.after.find(1, {18, 2, 2});
  ASSERT_GE(fresh, 0);
  EXPECT_EQ(x.after.opacity_logit()[fresh * 5], -6.f);

  // Switches: neither rule when off.
  GrowthConfig c;
  c.prune_opacity = 0;
  c.prune_unseen = false;
  const Ran y = run_scenario(c);
  EXPECT_EQ(y.r.pruned, 0);
  EXPECT_EQ(y.r.added, 3);
  EXPECT_EQ(y.r.anchor_rows, (std::vector<int>{0, 1, 2, 3, 4, 5, -1, -1, -1}));
  // Without min_seen_fraction row 7 grows too.
  GrowthConfig f;
  f.min_seen_fraction = 0;
  EXPECT_EQ(run_scenario(f).r.added, 4);
}

// Under the budget, a child seen in fewer than 40% of the steps ranks by its
// mean gradient times the square of its share of that bar: row 7, seen in 3
// of 10 steps (share 0.75, factor 0.5625), asks at 8x its threshold, above
// rows 2/3 and 15 (6.7x), but ranks at 4.5x and loses the two places to
// them; it still beats (42,10,10) at 1.3x when there are three.
TEST(GrowthDecision, BudgetRanksRarelySeenChildrenBelowWellSeenOnes) {
  auto run = [](float round_growth) {
    Scenario s = scenario();
    s.v_px[2 * 7] = 1.2e-3f / (0.5f * kW);
    GrowthConfig c;
    c.min_seen_fraction = 0;
    c.round_growth = round_growth;
    c.min_round_anchors = 0;
    AnchorGrowth growth(runtime(), c);
    growth.reset(s.model.gaussians());
    feed(growth, s.v_px, s.radii, 10, kW, kH, s.seen);
    const GrowthResult r = growth.step(s.model, 5);
    return std::make_pair(r, s.model);
  };
  const auto [two, m2] = run(0.3f);  // ceil(0.3 x 6) = 2 places for 4 voxels
  EXPECT_EQ(two.added, 2);
  EXPECT_EQ(two.over_budget, 2);
  EXPECT_GE(m2.find(1, {3, 2, 2}), 0);
  EXPECT_GE(m2.find(1, {18, 2, 2}), 0);
  EXPECT_EQ(m2.find(1, {11, 2, 2}), -1) << "the rarely seen child took a place";
  const auto [three, m3] = run(0.5f);  // 3 places
  EXPECT_EQ(three.added, 3);
  EXPECT_GE(m3.find(1, {11, 2, 2}), 0);
  EXPECT_EQ(m3.find(2, {42, 10, 10}), -1);
}

// recycle_opacity: the transparent children of a kept anchor become copies
// of its most opaque child, the pair exactly as opaque as that child was,
// with fresh moments; anchors without a worthy donor, anchors grown in the
// same step and everything when it is off stay as they were.
TEST(GrowthDecision, RecyclesTransparentChildrenAsCopiesOfTheMostOpaque) {
  auto run = [](float recycle) {
    Scenario s = scenario();
    s.model.opacity_logit()[1] = -7.f;  // a0: rows 1 and 3 transparent, row 4 (logit 0.04) the donor
    s.model.opacity_logit()[3] = -7.f;
    for (int i = 0; i < 5; ++i) s.model.opacity_logit()[25 + i] = -5.f + i * 0.1f;  // a5: the best 0.0099,
    s.model.opacity_logit()[27] = -7.f;  // below 2 x 0.005: no donor for this transparent one
    GrowthConfig c;
    c.recycle_opacity = recycle;
    c.prune_opacity = 0;  // keep a3 (all at 0.0025) and a5 to show they are left alone
    AnchorGrowth growth(runtime(), c);
    growth.reset(s.model.gaussians());
    feed(growth, s.v_px, s.radii, 10, kW, kH, s.seen);
    Ran out;
    out.before = s.model;
    out.r = growth.step(s.model, 5);
    out.after = s.model;
    return out;
  };
  const Ran off = run(0.f), on = run(0.005f), again = run(0.005f);
  EXPECT_EQ(off.r.recycled, 0);
  EXPECT_EQ(on.r.recycled, 2);
  // Same decisions otherwise, and the same bytes twice.
  EXPECT_EQ(on.r.anchor_rows, off.r.anchor_rows);
  EXPECT_EQ(on.after.offset(), again.after.offset());
  EXPECT_EQ(on.after.opacity_logit(), again.after.opacity_logit());

  const AnchorModel &b = on.before, &m = on.after;
  auto sig = [](double x) { return 1.0 / (1.0 + std::exp(-x)); };
  const double donor_before = sig(b.opacity_logit()[4]);
  // 1 - (1 - o1)(1 - o3)(1 - o4) over the three rows is the donor's opacity.
  const double cover =
      1.0 - (1.0 - sig(m.opacity_logit()[1])) * (1.0 - sig(m.opacity_logit()[3])) * (1.0 - sig(m.opacity_logit()[4]));
  EXPECT_NEAR(cover, donor_before, 1e-6);
  for (int g : {1, 3}) {
    EXPECT_EQ(on.r.child_rows[g], -1) << g;  // fresh moments
    for (int k = 0; k < 3; ++k) {
      EXPECT_EQ(m.scale_logit()[3 * g + k], b.scale_logit()[3 * 4 + k]);
      EXPECT_LE(std::abs(m.offset()[3 * g + k] - b.offset()[3 * 4 + k]), 0.1f + 1e-6f);
    }
    for (int k = 0; k < 4; ++k) EXPECT_EQ(m.quat()[4 * g + k], b.quat()[4 * 4 + k]);
    for (int k = 0; k < 48; ++k) EXPECT_EQ(m.sh()[48 * g + k], b.sh()[48 * 4 + k]);
  }
  EXPECT_NE(m.offset()[3], m.offset()[9]);                                     // the two copies are jittered apart
  EXPECT_EQ(on.r.anchor_rows, (std::vector<int>{0, 1, 2, 3, 5, -1, -1, -1}));  // a4 unseen
  for (int g = 0; g < 25; ++g) {
    if (g == 1 || g == 3 || g == 4) continue;  // the copies and the donor (its opacity checked above)
    // Everything else keeps its row, moments and values: a0's rows 0 and 2,
    // a3 (all at 0.0025, no donor) and a5 (no donor either).
    const int o = on.r.child_rows[g];
    EXPECT_EQ(o, off.r.child_rows[g]) << g;
    if (o < 0) continue;  // grown this step
    EXPECT_EQ(m.opacity_logit()[g], b.opacity_logit()[o]) << g;
  }
  EXPECT_EQ(on.r.child_rows[22], 27);
  // The grown anchors (children at a3's 0.0025, born this step) are left alone.
  const int fresh = m.find(1, {18, 2, 2});
  ASSERT_GE(fresh, 0);
  for (int i = 0; i < 5; ++i) EXPECT_EQ(m.opacity_logit()[fresh * 5 + i], -6.f);
  m.check();
}

TEST(GrowthDecision, MinSeenFractionIsInclusive) {
  // Row 7 (large gradient, free voxel) visible in exactly 4 of 10 views:
  // 0.4 of the round is enough, although 0.4f * 10 in double is 4.00000006.
  Scenario s = scenario();
  s.seen[7] = 4;
  AnchorGrowth growth(runtime(), GrowthConfig{});
  growth.reset(s.model.gaussians());
  feed(growth, s.v_px, s.radii, 10, kW, kH, s.seen);
  const GrowthResult r = growth.step(s.model, 5);
  EXPECT_EQ(r.added, 4);
  EXPECT_GE(s.model.find(1, {11, 2, 2}), 0);
}

TEST(GrowthDecision, UnseenWindowSpansDecisions) {
  Scenario s = scenario();
  GrowthConfig c;
  c.unseen_window = 25;
  c.prune_opacity = 0;
  c.grad_threshold = 1.f;  // no growth
  AnchorGrowth growth(runtime(), c);
  growth.reset(s.model.gaussians());
  feed(growth, s.v_px, s.radii, 10, kW, kH);
  GrowthResult r = growth.step(s.model, 1);
  EXPECT_EQ(r.pruned, 0);  // unseen for 10 of 25 steps
  EXPECT_FALSE(r.changed());
  feed(growth, s.v_px, s.radii, 10, kW, kH);
  EXPECT_EQ(growth.step(s.model, 1).pruned, 0);  // 20
  // a1 becomes visible only through child 6, once, then nobody is seen but a0.
  std::vector<int> radii = s.radii;
  std::fill(radii.begin() + 5, radii.end(), 0);
  radii[6] = 1;
  feed(growth, s.v_px, radii, 1, kW, kH);
  radii[6] = 0;
  feed(growth, s.v_px, radii, 9, kW, kH);
  r = growth.step(s.model, 1);  // step 30: a4 unseen since 0, a2 a3 a5 since 20, a1 since 21
  EXPECT_EQ(r.pruned_unseen, 1);
  EXPECT_EQ(r.anchor_rows, (std::vector<int>{0, 1, 2, 3, 5}));
  // No accumulation since the last decision: no unseen pruning at all.
  EXPECT_EQ(growth.step(s.model, 1).pruned, 0);
}

TEST(GrowthDecision, StatisticsResetAndFollowRows) {
  const Ran x = run_scenario();
  const GrowthStatsHost& st = x.stats_after;
  ASSERT_EQ(st.grad_sum.size(), 35u);
  EXPECT_EQ(st.steps, 0);
  EXPECT_EQ(st.step, 10);
  for (size_t g = 0; g < 35; ++g) {
    EXPECT_EQ(st.grad_sum[g], 0.f);
    EXPECT_EQ(st.count[g], 0);
    const int old = x.r.child_rows[g];
    // Old rows: last seen at step 10 (row 7 at 3); new rows: born at 10.
    EXPECT_EQ(st.last_seen[g], old == 7 ? 3 : 10) << g;
  }
}

TEST(GrowthDecision, GatherMapsKeepOptimiserMoments) {
  const Ran x = run_scenario();
  const GrowthResult& r = x.r;
  ASSERT_EQ(r.child_rows.size(), 35u);
  for (size_t g = 0; g < 35; ++g) {
    const int a = r.anchor_rows[g / 5];
    EXPECT_EQ(r.child_rows[g], a < 0 ? -1 : a * 5 + static_cast<int>(g % 5));
  }
  // Every kept row carries its parameters along.
  for (size_t g = 0; g < 35; ++g) {
    const int o = r.child_rows[g];
    if (o < 0) continue;
    EXPECT_EQ(x.after.opacity_logit()[g], x.before.opacity_logit()[o]);
    EXPECT_EQ(x.after.sh()[g * 48], x.before.sh()[o * 48]);
  }
  // AdamGroup::gather with the map: kept rows keep their moments, new rows zero.
  AdamGroup group(runtime(), "offset", 30, 3);
  std::vector<float> m(90), v(90);
  for (size_t i = 0; i < 90; ++i) {
    m[i] = 1.f + i;
    v[i] = 1000.f + i;
  }
  group.exp_avg().upload(m);
  group.exp_avg_sq().upload(v);
  group.gather(r.child_rows);
  ASSERT_EQ(group.rows(), 35u);
  std::vector<float> m2, v2;
  group.exp_avg().download(m2, 105);
  group.exp_avg_sq().download(v2, 105);
  for (size_t g = 0; g < 35; ++g) {
    const int o = r.child_rows[g];
    for (int k = 0; k < 3; ++k) {
      EXPECT_EQ(m2[g * 3 + k], o < 0 ? 0.f : m[o * 3 + k]) << g;
      EXPECT_EQ(v2[g * 3 + k], o < 0 ? 0.f : v[o * 3 + k]) << g;
    }
  }
  AdamGroup feature(runtime(), "feature", 6, 3);
  feature.gather(r.anchor_rows);
  EXPECT_EQ(feature.rows(), 7u);
}

// ---------------------------------------------------------------------------
// Determinism and the device round trip

// A model from random points on layer 0 with random offsets and opacities.
AnchorModel random_model(size_t points, uint32_t seed) {
  AnchorConfig c;
  c.top_cells = 16;
  SceneBounds b;
  b.lo = Eigen::Vector3d(-1, -1, -1);
  b.hi = Eigen::Vector3d(1, 1, 1);
  const VoxelGrid grid = VoxelGrid::from_bounds(b, c);
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(-1, 1);
  std::vector<Eigen::Vector3d> p(points);
  for (auto& x : p) x = Eigen::Vector3d(u(rng), u(rng), u(rng));
  AnchorModel m;
  m.initialise_from_points(p, {}, grid, c, seed);
  std::normal_distribution<float> nrm(0.f, 1.f);
  // Opacity logits share a per-anchor level, so some anchors are faint as a whole.
  for (size_t a = 0; a < m.size(); ++a) {
    const float level = -1.f + 1.5f * nrm(rng);
    for (int i = 0; i < m.children(); ++i) m.opacity_logit()[a * m.children() + i] = level + 0.3f * nrm(rng);
  }
  for (float& o : m.offset()) o = 0.6f * nrm(rng);
  for (size_t g = 0; g < m.gaussians(); ++g) m.sh()[g * 48] = nrm(rng);
  return m;
}

template <typename T>
bool same_bytes(const std::vector<T>& a, const std::vector<T>& b) {
  return a.size() == b.size() && (a.empty() || std::memcmp(a.data(), b.data(), a.size() * sizeof(T)) == 0);
}

TEST(GrowthDecision, Deterministic) {
  const AnchorModel base = random_model(3000, 21);
  ASSERT_GT(base.size(), 500u);
  const size_t n = base.gaussians();
  std::mt19937 rng(22);
  std::exponential_distribution<float> ex(1.f);
  std::vector<float> v(2 * n);
  std::vector<int> radii(n);
  for (size_t g = 0; g < n; ++g) {
    v[2 * g] = 3e-6f * ex(rng);
    v[2 * g + 1] = 3e-6f * ex(rng);
    radii[g] = (g * 2654435761u) % 7 == 0 ? 0 : 2;
  }
  GrowthConfig c;
  c.grad_threshold = 2e-4f;
  c.prune_opacity = 0.1f;
  AnchorModel out[2];
  GrowthResult res[2];
  GrowthStatsHost st[2];
  for (int run = 0; run < 2; ++run) {
    out[run] = base;
    AnchorGrowth growth(runtime(), c);
    growth.reset(n);
    feed(growth, v, radii, 4, 320, 240);
    res[run] = growth.step(out[run], 99);
    st[run] = growth.download();
  }
  std::printf("  %zu anchors: %d requests, %d added, %d pruned (%d opacity, %d unseen)\n", base.size(), res[0].requests,
              res[0].added, res[0].pruned, res[0].pruned_opacity, res[0].pruned_unseen);
  EXPECT_GT(res[0].added, 20);
  EXPECT_LT(res[0].added, res[0].requests);  // some voxels requested twice or taken
  EXPECT_GT(res[0].pruned_opacity, 10);
  EXPECT_EQ(res[0].anchor_rows, res[1].anchor_rows);
  EXPECT_EQ(res[0].child_rows, res[1].child_rows);
  EXPECT_TRUE(same_bytes(out[0].pos(), out[1].pos()));
  EXPECT_TRUE(same_bytes(out[0].cell(), out[1].cell()));
  EXPECT_TRUE(same_bytes(out[0].layer(), out[1].layer()));
  EXPECT_TRUE(same_bytes(out[0].feature(), out[1].feature()));
  EXPECT_TRUE(same_bytes(out[0].offset(), out[1].offset()));
  EXPECT_TRUE(same_bytes(out[0].scale_logit(), out[1].scale_logit()));
  EXPECT_TRUE(same_bytes(out[0].quat(), out[1].quat()));
  EXPECT_TRUE(same_bytes(out[0].opacity_logit(), out[1].opacity_logit()));
  EXPECT_TRUE(same_bytes(out[0].sh(), out[1].sh()));
  EXPECT_TRUE(same_bytes(st[0].last_seen, st[1].last_seen));
  // New anchors in voxel-key order, none duplicated.
  for (size_t a = 0; a + 1 < out[0].size(); ++a) {
    if (res[0].anchor_rows[a] >= 0 || res[0].anchor_rows[a + 1] >= 0) continue;
    EXPECT_LT(anchor_voxel_key(out[0].layer()[a], cell_at(out[0], a)),
              anchor_voxel_key(out[0].layer()[a + 1], cell_at(out[0], a + 1)));
  }
}

TEST(GrowthDecision, DeviceRoundTripAfterGrowthAndPrune) {
  Runtime& rt = runtime();
  AnchorModel model = random_model(1500, 31);
  const Camera cam = test::look_at_origin(96, 64, 4.0, 3.0);  // sees part of the cube
  DeviceAnchors anchors(rt);
  Expander expander(rt);
  DeviceGaussians gaussians(rt);
  Renderer renderer(rt);
  GrowthConfig c;
  c.grad_threshold = 1e-6f;  // enough to grow from a few random renders
  c.prune_opacity = 0.2f;
  c.unseen_window = 0;
  AnchorGrowth growth(rt, c);
  anchors.upload(model);
  growth.reset(model.gaussians());
  std::mt19937 rng(32);
  std::normal_distribution<float> nrm(0.f, 1.f);
  auto render_and_accumulate = [&](int views) {
    for (int v = 0; v < views; ++v) {
      expander.forward(anchors, gaussians, 0);
      ASSERT_EQ(gaussians.n, model.gaussians());
      renderer.forward(gaussians, cam, RenderSettings{});
      const RenderOutput out = renderer.download_output();
      ASSERT_EQ(out.radii.size(), model.gaussians());
      OutputGrads og;
      og.rgb.resize(size_t(cam.width) * cam.height * 3);
      for (float& x : og.rgb) x = nrm(rng) * 1e-3f;
      renderer.backward(og);
      growth.accumulate(*renderer.device_grads().means2d, out.radii, cam.width, cam.height);
    }
  };
  render_and_accumulate(3);
  const GrowthStatsHost st = growth.download();
  size_t seen = 0;
  for (int cnt : st.count) seen += cnt > 0;
  EXPECT_GT(seen, model.gaussians() / 4);
  EXPECT_LT(seen, model.gaussians());  // the camera sees part of the scene

  anchors.download(model);
  const GrowthResult r = growth.step(model, 7);
  std::printf("  %zu -> %zu anchors: %d added, %d pruned (%d opacity, %d unseen)\n", r.anchors_before, r.anchors_after,
              r.added, r.pruned, r.pruned_opacity, r.pruned_unseen);
  EXPECT_GT(r.added, 0);
  EXPECT_GT(r.pruned_opacity, 0);
  EXPECT_GT(r.pruned_unseen, 0);
  ASSERT_EQ(r.gaussians_after, model.gaussians());
  ASSERT_EQ(growth.gaussians(), model.gaussians());
  anchors.upload(model);
  EXPECT_EQ(anchors.gaussians(), model.gaussians());
  // The device expansion of the new model equals the host reference.
  expander.forward(anchors, gaussians, 0);
  ASSERT_EQ(gaussians.n, model.gaussians());
  std::vector<float> means;
  gaussians.means.download(means, gaussians.n * 3);
  const GaussianSet ref = expand_reference(model, 0);
  ASSERT_EQ(ref.means.size(), means.size());
  for (size_t i = 0; i < means.size(); ++i) ASSERT_NEAR(means[i], ref.means[i], 1e-6 * (1 + std::abs(ref.means[i])));
  // Training continues with the new sizes.
  render_and_accumulate(2);
  EXPECT_EQ(growth.download().steps, 2);
}

// Many rounds of growth on a random model with large gradients everywhere
// never take it past its budget, and with the per-round budget the count
// rises by at most that fraction each round.
TEST(GrowthDecision, RoundsNeverExceedTheBudget) {
  AnchorModel m = random_model(3000, 31);
  for (float& o : m.opacity_logit()) o = 2.f;  // nothing pruned for opacity
  GrowthConfig c;
  c.grad_threshold = 1e-6f;
  c.same_layer = true;
  c.round_growth = 0.1f;
  c.min_round_anchors = 8;
  c.max_gaussians = m.gaussians() * 2;
  AnchorGrowth growth(runtime(), c);
  std::mt19937 rng(32);
  std::exponential_distribution<float> ex(1.f);
  for (int round = 0; round < 12; ++round) {
    const size_t n = m.gaussians();
    growth.reset(n);
    std::vector<float> v(2 * n);
    for (float& x : v) x = 1e-4f * ex(rng);
    feed(growth, v, std::vector<int>(n, 2), 3, 320, 240);
    const size_t anchors = m.size();
    const GrowthResult r = growth.step(m, 40 + round);
    EXPECT_LE(r.gaussians_after, c.max_gaussians) << "round " << round;
    EXPECT_LE(static_cast<size_t>(r.added), std::max<size_t>(8, (anchors + 9) / 10)) << "round " << round;
    EXPECT_GT(r.requests, r.added);
  }
  EXPECT_GT(m.gaussians(), c.max_gaussians - static_cast<size_t>(3 * m.children()));  // the budget was used
  m.check();
}

}  // namespace
}  // namespace ag2gs

namespace ag2gs {
namespace {

TEST(Eta, SecondsLeftFollowTheCountToItsEnd) {
  // A fixed count: every step at the recent step time.
  EXPECT_DOUBLE_EQ(estimate_seconds_left(1000, 50, 10000, 0, 10000), 50);
  // Rising evenly to 3x over the 400 growing steps, then 600 steps at 3x.
  EXPECT_DOUBLE_EQ(estimate_seconds_left(1000, 50, 10000, 400, 30000), (400 * 2.0 + 600 * 3.0) * 0.05);
  // An end below the count now (pruning) or not finite does not shorten or break it.
  EXPECT_DOUBLE_EQ(estimate_seconds_left(1000, 50, 10000, 400, 5000), 50);
  EXPECT_DOUBLE_EQ(estimate_seconds_left(1000, 50, 10000, 400, INFINITY), 50);
  EXPECT_EQ(estimate_seconds_left(0, 50, 10000, 0, 10000), 0);
  EXPECT_EQ(estimate_seconds_left(10, 0, 10000, 0, 10000), 0);
  // Growth models: the budget bounds the geometric one, the tapering one
  // adds half of the last round per round left.
  EXPECT_DOUBLE_EQ(growth_end_geometric(2000, 1000, 1, 3, 0), 16000);
  EXPECT_DOUBLE_EQ(growth_end_geometric(2000, 1000, 1, 3, 5000), 5000);
  EXPECT_DOUBLE_EQ(growth_end_geometric(2000, 1000, 1, 0, 5000), 2000);
  EXPECT_DOUBLE_EQ(growth_end_tapering(2000, 400, 10), 4000);
  EXPECT_DOUBLE_EQ(growth_end_tapering(2000, 400, 0), 2000);
}

TEST(Eta, TheBaselinesEtaMatchesALoggedRun) {
  // `ag2gs baseline` on the fox (-r 4, 7000 iterations, densifying every 100
  // until 3500), from its log: iteration, Gaussians, the last round's net
  // gain, the step time over the last 100 iterations (ms) and the seconds the
  // run actually took from there.
  struct Row {
    int it;
    size_t count, added;
    double step_ms, actual_s;
  };
  const Row rows[] = {{500, 17476, 4774, 111.1, 3894},   {1000, 60377, 8921, 263.2, 3797},
                      {1500, 98903, 6785, 476.2, 3608},  {2000, 125868, 4871, 500.0, 3367},
                      {2500, 144735, 3167, 714.3, 3023}, {3000, 157953, 2454, 714.3, 2693},
                      {3500, 143771, 2584, 666.7, 2363}, {4000, 143771, 0, 666.7, 2042}};
  for (const Row& r : rows) {
    const int growing = std::max(0, 3500 - r.it);
    const double eta = estimate_seconds_left(7000 - r.it, r.step_ms, r.count, growing,
                                             growth_end_tapering(r.count, r.added, growing / 100));
    EXPECT_NEAR(eta / r.actual_s, 1.0, 0.25) << "iteration " << r.it << ": " << eta << " s, took " << r.actual_s;
  }
  // The rule it replaced (the mean round factor so far, no budget) promised
  // days at iteration 1000.
  const double old_end = growth_end_geometric(60377, 12702, 5, 25, 0);
  EXPECT_GT(estimate_seconds_left(6000, 263.2, 60377, 2500, old_end), 100 * 3797.0);
}

}  // namespace
}  // namespace ag2gs
