// Coarse-to-fine training (TrainConfig::downscales / res_schedule, `ag2gs
// train --downscales N --res-schedule K`): the downscaled camera against the
// double-precision reference renderer, the box filter against its definition,
// the schedule of levels (masks force the full resolution), and a run split
// across a level change that resumes to the bytes of the straight run.
#include <gtest/gtest.h>

#include <cmath>

#include "host/scene/scene.h"
#include "tests/io_test_util.h"
#include "tests/reference/reference_renderer.h"
#include "tests/test_util.h"
#include "train/trainer.h"

namespace ag2gs {
namespace {

std::string sample_scene() {
  return test::source_path("data_samples/synth_small");
}

TEST(TrainCoarse, BoxDownscaleIsTheBlockMean) {
  Image img;
  img.width = 7;  // not a multiple of 2 or 3: the last column is cropped
  img.height = 6;
  img.rgb.resize(static_cast<size_t>(img.width) * img.height * 3);
  for (size_t i = 0; i < img.rgb.size(); ++i) img.rgb[i] = static_cast<float>((i * 37) % 101) / 100.f;
  for (int f : {2, 3}) {
    const int w = img.width / f, h = img.height / f;
    std::vector<float> out(static_cast<size_t>(w) * h * 3, -1.f);
    box_downscale_planar(img, f, out.data());
    for (int c = 0; c < 3; ++c)
      for (int y = 0; y < h; ++y)
        for (int x = 0; x < w; ++x) {
          double sum = 0;
          for (int dy = 0; dy < f; ++dy)
            for (int dx = 0; dx < f; ++dx) sum += img.rgb[((y * f + dy) * img.width + x * f + dx) * 3 + c];
          EXPECT_NEAR(out[(c * h + y) * w + x], sum / (f * f), 1e-6) << "factor " << f << " at " << x << "," << y;
        }
  }
}

// Mean absolute difference between the box-filtered large image and the
// small one, both from the reference renderer.
double mismatch(const GaussianSet& g, const Camera& big, const Camera& small, int f) {
  const ref::RefImages a = ref::render(g, big, {});
  const ref::RefImages b = ref::render(g, small, {});
  Image img;
  img.width = a.width;
  img.height = a.height;
  img.rgb.assign(a.rgb.begin(), a.rgb.end());
  std::vector<float> boxed(static_cast<size_t>(b.width) * b.height * 3);
  box_downscale_planar(img, f, boxed.data());
  const size_t npix = static_cast<size_t>(b.width) * b.height;
  double sum = 0;
  for (size_t p = 0; p < npix; ++p)
    for (int c = 0; c < 3; ++c) sum += std::abs(boxed[c * npix + p] - b.rgb[p * 3 + c]);
  return sum / (npix * 3);
}

// The small camera sees the scene where the box filter puts it: rendering
// through downscaled_camera matches the block means of the full render far
// better than a camera off by half a small pixel (the usual convention slip).
TEST(TrainCoarse, DownscaledCameraMatchesTheBoxFilteredRender) {
  test::SceneSpec spec;
  spec.n = 60;
  spec.log_scale_lo = -2.5;  // smooth blobs a few pixels wide
  spec.log_scale_hi = -1.5;
  spec.sh_degree = 0;
  const GaussianSet g = test::random_scene(spec, 11);
  const Camera big = test::look_at_origin(192, 144);
  for (int f : {2, 4}) {
    const Camera small = downscaled_camera(big, f);
    EXPECT_EQ(small.width, 192 / f);
    EXPECT_EQ(small.height, 144 / f);
    Camera shifted = small;
    shifted.cx += 0.5;
    shifted.cy += 0.5;
    const double good = mismatch(g, big, small, f), bad = mismatch(g, big, shifted, f);
    std::printf("factor %d: mean |box(full) - small| %.5f, with a half-pixel shift %.5f\n", f, good, bad);
    EXPECT_LT(good, 0.5 * bad);
    EXPECT_LT(good, 0.02);
  }
}

TrainConfig coarse_config() {
  TrainConfig cfg;
  cfg.iterations = 60;
  cfg.seed = 2;
  cfg.anchors.top_cells = 50;
  cfg.grow_from = 20;
  cfg.grow_every = 20;
  cfg.grow_until = 50;
  cfg.grow_threshold = 1e-3;
  cfg.mask_from = 45;
  cfg.prop_iters = 0;
  cfg.downscales = 2;
  cfg.res_schedule = 15;
  return cfg;
}

// Downscale 4, then 2 from iteration 15; the mask losses (from 25 here)
// always run at the loaded resolution.
TEST(TrainCoarse, ScheduleOfLevels) {
  SceneOptions so;
  so.resolution = 2;
  auto scene = Scene::open(sample_scene(), so);
  TrainConfig cfg = coarse_config();
  cfg.mask_from = 25;  // during level 1: forces full resolution from here
  Trainer t(test::runtime(), *scene, cfg);
  for (int it = 0; it < cfg.iterations; ++it) {
    const StepStats st = t.step();
    const int want = it < 15 ? 4 : it < 25 ? 2 : 1;
    ASSERT_EQ(st.downscale, want) << "iteration " << it;
    ASSERT_EQ(st.with_masks, it >= 25) << "iteration " << it;
    ASSERT_FALSE(st.skipped);
  }
}

TEST(TrainCoarse, ResumeAcrossALevelChangeGivesTheBytesOfTheStraightRun) {
  SceneOptions so;
  so.resolution = 2;
  auto scene = Scene::open(sample_scene(), so);
  const TrainConfig cfg = coarse_config();
  test::ScratchDir dir("train_coarse_resume");
  {
    Trainer straight(test::runtime(), *scene, cfg);
    for (int it = 0; it < cfg.iterations; ++it) straight.step();
    straight.save(dir.file("straight"));
  }
  {
    Trainer first(test::runtime(), *scene, cfg);
    for (int it = 0; it < 22; ++it) first.step();  // inside level 1
    first.save(dir.file("split"));
  }
  {
    Trainer second(test::runtime(), *scene, cfg);
    second.resume(dir.file("split"));
    ASSERT_EQ(second.iteration(), 22);
    for (int it = second.iteration(); it < cfg.iterations; ++it) second.step();
    second.save(dir.file("split"));
  }
  test::expect_same_model_files(dir.file("straight"), dir.file("split"), "the straight and the resumed run");
}

TEST(TrainCoarse, ConfigRoundTripsAndOldFilesMeanFullResolution) {
  TrainConfig cfg = coarse_config();
  const TrainConfig back = TrainConfig::from_json(cfg.to_json());
  EXPECT_EQ(back.downscales, 2);
  EXPECT_EQ(back.res_schedule, 15);
  EXPECT_EQ(back.coarse_lowpass, cfg.coarse_lowpass);
  nlohmann::json old = cfg.to_json();
  old.erase("downscales");
  old.erase("res_schedule");
  old.erase("coarse_lowpass");
  EXPECT_EQ(TrainConfig::from_json(old).downscales, 0);
  // Files from before the option rendered 0.3 px at every level.
  EXPECT_EQ(TrainConfig::from_json(old).coarse_lowpass, 1.0);
  EXPECT_FLOAT_EQ(cfg.lowpass_at_level(0), 0.3f);
  cfg.coarse_lowpass = 0.5;
  EXPECT_FLOAT_EQ(cfg.lowpass_at_level(2), 0.075f);
  for (double bad : {0.0, -0.5, 1.5, std::nan("")}) {
    cfg.coarse_lowpass = bad;
    EXPECT_THROW(cfg.validate(), std::invalid_argument) << bad;
  }
  cfg.coarse_lowpass = 1;
  cfg.downscales = 7;
  EXPECT_THROW(cfg.validate(), std::invalid_argument);
  cfg.downscales = -2;
  EXPECT_THROW(cfg.validate(), std::invalid_argument);
  cfg.downscales = 1;
  cfg.res_schedule = -1;
  EXPECT_THROW(cfg.validate(), std::invalid_argument);
  // -1 and 0 are the defaults: chosen from the images and the iterations.
  cfg.downscales = -1;
  cfg.res_schedule = 0;
  EXPECT_NO_THROW(cfg.validate());
}

// The default coarse-to-fine: as many halvings (at most 3) as keep the
// shorter image side at 64 pixels or more, full resolution from 85% of
// the run and by iteration 3000 per level in long runs; the trainer holds
// the chosen values (so checkpoints do).
TEST(TrainCoarse, DefaultLevelsComeFromTheImagesAndTheScheduleFromTheIterations) {
  EXPECT_EQ(TrainConfig::auto_downscales(120), 0);  // the sample at 160x120
  EXPECT_EQ(TrainConfig::auto_downscales(127), 0);
  EXPECT_EQ(TrainConfig::auto_downscales(128), 1);
  EXPECT_EQ(TrainConfig::auto_downscales(300), 2);  // the cup at -r 2, 400x300
  EXPECT_EQ(TrainConfig::auto_downscales(512), 3);
  EXPECT_EQ(TrainConfig::auto_downscales(4000), 3);
  EXPECT_EQ(TrainConfig::auto_res_schedule(2000, 2), 850);  // full from iteration 1700
  EXPECT_EQ(TrainConfig::auto_res_schedule(2000, 3), 566);
  EXPECT_EQ(TrainConfig::auto_res_schedule(30000, 2), 3000);
  EXPECT_EQ(TrainConfig::auto_res_schedule(30000, 3), 3000);
  EXPECT_EQ(TrainConfig::auto_res_schedule(3, 3), 1);
  EXPECT_EQ(TrainConfig::auto_res_schedule(100, 0), 1);
  SceneOptions so;
  auto scene = Scene::open(sample_scene(), so);  // 160x120: no coarse level
  TrainConfig c;
  c.iterations = 400;
  Trainer t(test::runtime(), *scene, c);
  EXPECT_EQ(t.config().downscales, 0);
  EXPECT_EQ(t.config().res_schedule, 1);
  EXPECT_EQ(t.config().resolution_level(0), 0);
  EXPECT_EQ(t.config().to_json()["downscales"], 0);
  // A resolved config stays as it is.
  c.downscales = 2;
  Trainer t2(test::runtime(), *scene, c);
  EXPECT_EQ(t2.config().downscales, 2);
  EXPECT_EQ(t2.config().res_schedule, 170);  // 0.85 x 400 / 2
  EXPECT_EQ(t2.config().resolution_level(169), 2);
  EXPECT_EQ(t2.config().resolution_level(170), 1);
  EXPECT_EQ(t2.config().resolution_level(339), 1);
  EXPECT_EQ(t2.config().resolution_level(340), 0);
}

}  // namespace
}  // namespace ag2gs
