// Training state over time (stages/trainer.h, `ag2gs train`) on the synthetic
// sample scene at -r 2 (80x60): the 3DGS opacity reset.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>

#include "host/scene.h"
#include "io_test_util.h"
#include "stages/anchor_model.h"
#include "stages/trainer.h"
#include "test_util.h"

namespace fs = std::filesystem;

namespace ag2gs {
namespace {

std::string sample_scene() { return test::source_path("data_samples/synth_small"); }

std::vector<float> download(DeviceBuffer& b, size_t n) {
  std::vector<float> v;
  b.download(v, n);
  return v;
}

bool all_zero(const std::vector<float>& v) {
  return std::all_of(v.begin(), v.end(), [](float x) { return x == 0.f; });
}

// Two runs that differ only in the reset: up to the reset iteration they are
// the same, so the run with the reset must hold exactly min(p, logit(0.01))
// of the other's opacities p, with zeroed opacity moments and the other
// groups untouched; no reset once growing has stopped.
TEST(TrainState, OpacityResetCapsOpacityAndZeroesItsMoments) {
  SceneOptions so;
  so.resolution = 2;
  auto scene = Scene::open(sample_scene(), so);
  TrainConfig cfg;
  cfg.iterations = 70;  // resets while growing runs: until iteration 46 (2/3)
  cfg.seed = 2;
  cfg.anchors.top_cells = 50;
  cfg.grow_every = 0;
  cfg.opacity_reset_every = 20;
  TrainConfig off = cfg;
  off.opacity_reset_every = 0;
  Trainer a(test::runtime(), *scene, cfg), b(test::runtime(), *scene, off);
  const float cap = std::log(0.01f / 0.99f);
  for (int it = 1; it <= cfg.iterations; ++it) {
    const StepStats sa = a.step(), sb = b.step();
    EXPECT_EQ(sa.opacity_reset, it == 20 || it == 40) << it;
    EXPECT_FALSE(sb.opacity_reset);
    if (it == 20) {
      const std::vector<float>& pa = a.model().opacity_logit();
      const std::vector<float>& pb = b.model().opacity_logit();
      ASSERT_EQ(pa.size(), pb.size());
      size_t capped = 0;
      for (size_t i = 0; i < pa.size(); ++i) {
        ASSERT_EQ(pa[i], std::min(pb[i], cap)) << i;
        capped += pb[i] > cap;
      }
      std::printf("reset at 20: %zu of %zu opacities capped\n", capped, pa.size());
      EXPECT_GT(capped, pa.size() / 2);
      AdamGroup& ga = a.adam_group("opacity");
      EXPECT_TRUE(all_zero(download(ga.exp_avg(), ga.size())));
      EXPECT_TRUE(all_zero(download(ga.exp_avg_sq(), ga.size())));
      EXPECT_EQ(ga.steps(), 20);
      AdamGroup& gb = b.adam_group("opacity");
      EXPECT_FALSE(all_zero(download(gb.exp_avg(), gb.size())));
      // Other parameters are not touched by the reset.
      EXPECT_TRUE(a.model().sh() == b.model().sh());
      EXPECT_FALSE(all_zero(download(a.adam_group("sh_dc").exp_avg(), a.adam_group("sh_dc").size())));
    }
  }
}

}  // namespace
}  // namespace ag2gs
