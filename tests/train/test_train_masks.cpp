// Mask losses in stage-1 training (train/trainer.h) on the synthetic sample
// scene at -r 2 (80x60): after a short run the rendered features of different
// ground-truth objects (the scene's exact gt/ ids, never seen by the trainer)
// lie apart while the features within one object stay close, the mask loss
// falls, and two runs give the same bits.
#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <opencv2/imgcodecs.hpp>

#include "host/render/renderer.h"
#include "host/scene/scene.h"
#include "tests/io_test_util.h"
#include "tests/test_util.h"
#include "train/anchors/anchor_model.h"
#include "train/trainer.h"

namespace fs = std::filesystem;

namespace ag2gs {
namespace {

std::string sample_scene() {
  return test::source_path("data_samples/synth_small");
}

constexpr int kObjects = 5;  // synth_small: gt ids 1..5, 0 = ground and backdrop

// How well the rendered features separate the ground-truth objects, over all
// views: per object the mean of the alpha-normalised feature G = F / alpha
// over its pixels (alpha > 0.5, and the 2x2 gt block under the pixel all one
// id, so boundary pixels do not count); "within" is the mean L1 distance of
// an object's pixels to its mean, "between" the smallest L1 distance of two
// object means. Accumulated in double.
struct Separation {
  double within = 0;   // mean over objects of the mean |G - mean_k|_1
  double between = 0;  // min over object pairs of |mean_j - mean_k|_1
  int objects = 0;     // objects with pixels
};

Separation feature_separation(Scene& scene, const AnchorModel& model, int sh_degree) {
  const GaussianSet set = expand_reference(model, sh_degree);
  Renderer renderer(test::runtime());
  struct Px {
    int id;
    std::array<double, 3> g;
  };
  std::vector<Px> px;
  for (const SceneView& view : scene.views()) {
    const RenderOutput out = renderer.render(set, view.camera);
    const cv::Mat gt =
        cv::imread((fs::path(sample_scene()) / "gt" / (view.stem + ".png")).string(), cv::IMREAD_UNCHANGED);
    EXPECT_EQ(gt.type(), CV_16UC1) << view.stem;
    EXPECT_EQ(gt.cols, 2 * out.width);
    EXPECT_EQ(gt.rows, 2 * out.height);
    if (gt.type() != CV_16UC1 || gt.cols != 2 * out.width || gt.rows != 2 * out.height) return {};
    for (int y = 0; y < out.height; ++y)
      for (int x = 0; x < out.width; ++x) {
        const int id = gt.at<uint16_t>(2 * y, 2 * x);
        if (id == 0 || gt.at<uint16_t>(2 * y, 2 * x + 1) != id || gt.at<uint16_t>(2 * y + 1, 2 * x) != id ||
            gt.at<uint16_t>(2 * y + 1, 2 * x + 1) != id)
          continue;
        const size_t p = static_cast<size_t>(y) * out.width + x;
        const double a = out.alpha[p];
        if (!(a > 0.5)) continue;
        px.push_back({id, {out.feature[3 * p] / a, out.feature[3 * p + 1] / a, out.feature[3 * p + 2] / a}});
      }
  }
  std::array<std::array<double, 3>, kObjects + 1> mean{};
  std::array<int64_t, kObjects + 1> n{};
  for (const Px& q : px) {
    EXPECT_LE(q.id, kObjects);
    if (q.id > kObjects) return {};
    for (int c = 0; c < 3; ++c) mean[q.id][c] += q.g[c];
    ++n[q.id];
  }
  for (int k = 1; k <= kObjects; ++k)
    for (int c = 0; c < 3 && n[k] > 0; ++c) mean[k][c] /= static_cast<double>(n[k]);
  std::array<double, kObjects + 1> spread{};
  for (const Px& q : px)
    for (int c = 0; c < 3; ++c) spread[q.id] += std::abs(q.g[c] - mean[q.id][c]);
  Separation s;
  s.between = INFINITY;
  for (int k = 1; k <= kObjects; ++k) {
    if (n[k] == 0) continue;
    ++s.objects;
    s.within += spread[k] / static_cast<double>(n[k]);
    for (int j = 1; j < k; ++j) {
      if (n[j] == 0) continue;
      double d = 0;
      for (int c = 0; c < 3; ++c) d += std::abs(mean[k][c] - mean[j][c]);
      s.between = std::min(s.between, d);
    }
  }
  if (s.objects > 0) s.within /= s.objects;
  return s;
}

TrainConfig mask_config() {
  TrainConfig cfg;
  cfg.iterations = 150;
  cfg.mask_from = 0;
  cfg.seed = 11;
  cfg.anchors.top_cells = 50;
  cfg.grow_every = 0;  // growing is tested elsewhere; keeps the run short
  return cfg;
}

TEST(TrainMasks, FeaturesSeparateGroundTruthObjectsAndMaskLossFalls) {
  SceneOptions so;
  so.resolution = 2;
  auto scene = Scene::open(sample_scene(), so);
  ASSERT_NE(scene->semantics(), SemanticsKind::none);
  TrainConfig cfg = mask_config();
  Trainer trainer(test::runtime(), *scene, cfg);
  const Separation before = feature_separation(*scene, trainer.model(), 0);
  const size_t epoch = scene->train_views().size();
  std::vector<double> mask_loss;
  for (int it = 0; it < cfg.iterations; ++it) {
    const StepStats st = trainer.step();
    ASSERT_FALSE(st.skipped) << "iteration " << st.iteration;
    ASSERT_TRUE(st.with_masks) << "iteration " << st.iteration;
    ASSERT_TRUE(std::isfinite(st.l_is) && std::isfinite(st.l_ic));
    mask_loss.push_back(cfg.w_is * st.l_is + cfg.w_ic * st.l_ic);
  }
  double first = 0, last = 0;
  for (size_t i = 0; i < epoch; ++i) first += mask_loss[i] / epoch;
  for (size_t i = mask_loss.size() - epoch; i < mask_loss.size(); ++i) last += mask_loss[i] / epoch;
  const Separation after = feature_separation(*scene, trainer.model(), trainer.active_sh_degree());
  std::printf("mask loss first epoch %.4f, last epoch %.4f; objects %d: within %.4f -> %.4f, between %.4f -> %.4f\n",
              first, last, after.objects, before.within, after.within, before.between, after.between);
  EXPECT_EQ(after.objects, kObjects);
  EXPECT_LT(last, 0.8 * first);
  // Apart: the closest two objects' means are farther apart than a typical
  // pixel is from its own object's mean, by a clear factor.
  EXPECT_GT(after.between, 2.0 * after.within);
  EXPECT_GT(after.between / after.within, 4.0 * before.between / before.within);

  // Deterministic: a second run gives the same bits.
  Trainer again(test::runtime(), *scene, cfg);
  for (int it = 0; it < cfg.iterations; ++it) again.step();
  EXPECT_TRUE(again.model().feature() == trainer.model().feature());
  EXPECT_TRUE(again.model().opacity_logit() == trainer.model().opacity_logit());
}

// The features are projected into the unit ball after each step (default);
// without it the contrast loss drives them past it. The unmasked pixels form
// one more mask by default (host/losses/mask_loss.h with_unmasked_group): the
// object features then also separate from the ground and backdrop (gt 0).
TEST(TrainMasks, FeaturesStayInTheUnitBall) {
  SceneOptions so;
  so.resolution = 2;
  auto scene = Scene::open(sample_scene(), so);
  TrainConfig cfg = mask_config();
  cfg.iterations = 100;
  cfg.mask_geometry = false;  // so the two runs share their geometry (checked below)
  TrainConfig free_cfg = cfg;
  free_cfg.feature_ball = false;
  Trainer ball(test::runtime(), *scene, cfg), unbounded(test::runtime(), *scene, free_cfg);
  for (int it = 0; it < cfg.iterations; ++it) {
    ASSERT_FALSE(ball.step().skipped);
    ASSERT_FALSE(unbounded.step().skipped);
  }
  auto max_norm = [](const std::vector<float>& f) {
    double m = 0;
    for (size_t a = 0; a + 2 < f.size(); a += 3)
      m = std::max(m, std::sqrt(double(f[a]) * f[a] + double(f[a + 1]) * f[a + 1] + double(f[a + 2]) * f[a + 2]));
    return m;
  };
  const double in_ball = max_norm(ball.model().feature()), free_max = max_norm(unbounded.model().feature());
  std::printf("largest feature norm after %d iterations: %.4f with the ball, %.4f without\n", cfg.iterations, in_ball,
              free_max);
  EXPECT_LE(in_ball, 1.0 + 1e-6);
  EXPECT_GT(in_ball, 0.9);  // the contrast loss does push out to it
  EXPECT_GT(free_max, 1.2);
  // The geometry is the same (features only take the mask losses' gradient).
  EXPECT_TRUE(ball.model().opacity_logit() == unbounded.model().opacity_logit());
}

// With mask_geometry off the mask losses train the features only: every
// other parameter follows the run without mask losses bit for bit (so RGB
// cannot get worse); with mask_geometry (the default, the paper's joint
// loss) they move the geometry too.
TEST(TrainMasks, FeatureOnlyMaskLossesLeaveAppearanceAsWithoutMasks) {
  SceneOptions so;
  so.resolution = 2;
  auto scene = Scene::open(sample_scene(), so);
  TrainConfig joint = mask_config();
  joint.iterations = 30;
  EXPECT_TRUE(joint.mask_geometry) << "the joint loss is the default";
  TrainConfig cfg = joint;
  cfg.mask_geometry = false;
  TrainConfig none = cfg;
  none.w_is = none.w_ic = 0;
  Trainer a(test::runtime(), *scene, cfg), b(test::runtime(), *scene, none), c(test::runtime(), *scene, joint);
  for (int it = 0; it < cfg.iterations; ++it) {
    ASSERT_TRUE(a.step().with_masks);
    ASSERT_FALSE(b.step().with_masks);
    ASSERT_TRUE(c.step().with_masks);
  }
  const AnchorModel &ma = a.model(), &mb = b.model(), &mc = c.model();
  EXPECT_TRUE(ma.offset() == mb.offset());
  EXPECT_TRUE(ma.scale_logit() == mb.scale_logit());
  EXPECT_TRUE(ma.quat() == mb.quat());
  EXPECT_TRUE(ma.opacity_logit() == mb.opacity_logit());
  EXPECT_TRUE(ma.sh() == mb.sh());
  EXPECT_FALSE(ma.feature() == mb.feature());
  EXPECT_FALSE(mc.opacity_logit() == mb.opacity_logit());
  // The feature gradient of the separate pass is the joint pass's (same
  // state before the first step): the features agree after one step.
  Trainer a1(test::runtime(), *scene, cfg), c1(test::runtime(), *scene, joint);
  a1.step();
  c1.step();
  EXPECT_TRUE(a1.model().feature() == c1.model().feature());
}

TEST(TrainMasks, SceneWithoutMasksTrainsAppearanceOnly) {
  // A copy of the sample without language_features/ and masks/.
  test::ScratchDir dir("train_nomasks");
  const fs::path scene_dir = dir.path() / "scene";
  fs::create_directories(scene_dir);
  for (const char* sub : {"images", "sparse"})
    fs::copy(fs::path(sample_scene()) / sub, scene_dir / sub, fs::copy_options::recursive);
  SceneOptions so;
  so.resolution = 2;
  auto scene = Scene::open(scene_dir.string(), so);
  ASSERT_EQ(scene->semantics(), SemanticsKind::none);
  TrainConfig cfg = mask_config();
  cfg.iterations = 20;
  Trainer trainer(test::runtime(), *scene, cfg);
  const std::vector<float> f0 = trainer.model().feature();
  for (int it = 0; it < cfg.iterations; ++it) {
    const StepStats st = trainer.step();
    EXPECT_FALSE(st.with_masks);
    EXPECT_EQ(st.l_is, 0.0);
  }
  EXPECT_TRUE(trainer.model().feature() == f0) << "features changed without a mask loss";
}

}  // namespace
}  // namespace ag2gs
