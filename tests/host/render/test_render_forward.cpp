// Device forward pass against the double-precision reference
// (tests/reference), element-wise, on random scenes and odd image sizes.
#include <algorithm>

#include "tests/reference/reference_renderer.h"
#include "tests/test_util.h"

namespace ag2gs {
namespace {

using test::compare;
using test::expect_close;

struct Case {
  int w, h;
  size_t n;
  int sh;
  uint32_t seed;
};

// Tolerances, measured on PoCL (native_exp, float32) over the cases below:
// colours/features/alpha agree to ~1e-5 where no decision flips; a pixel
// where a float-vs-double threshold (alpha >= 1/255, T >= 1e-4) decided the
// other way, or where two Gaussians' depths are so close that float and
// double sort them differently (alpha is order-independent, colour is not),
// differs by more: at 100k Gaussians 75 of 250k values, at most 0.016.
constexpr double kAbs = 3e-5, kRel = 1e-4, kFlip = 0.02, kFlipFraction = 2e-3;  // worst measured: 9e-6 abs, 2.9e-5 rel

void check_forward(const Case& c, const RenderSettings& settings = {}) {
  test::SceneSpec spec;
  spec.n = c.n;
  spec.sh_degree = c.sh;
  if (c.n > 10000) spec.log_scale_lo = -6, spec.log_scale_hi = -3.5;
  GaussianSet g = test::random_scene(spec, c.seed);
  Camera cam = test::look_at_origin(c.w, c.h);
  Renderer r(test::runtime());
  RenderOutput out = r.render(g, cam, settings);
  ref::RefImages ref = ref::render(g, cam, settings);
  std::printf("%dx%d, %zu Gaussians, %zu intersections\n", c.w, c.h, c.n, r.stats().n_intersections);
  expect_close("rgb", compare(out.rgb, ref.rgb, kAbs, kRel, kFlip), kFlipFraction);
  expect_close("feature", compare(out.feature, ref.feature, kAbs, kRel, kFlip), kFlipFraction);
  expect_close("alpha", compare(out.alpha, ref.alpha, kAbs, kRel, kFlip), kFlipFraction);
  // Depth sums w z: z ~ 4 here, so a flipped 1/255 contribution moves it ~0.02.
  expect_close("depth", compare(out.depth, ref.depth, 4 * kAbs, kRel, 8 * kFlip), kFlipFraction);
  expect_close("distortion", compare(out.distortion, ref.distortion, 1e-5, 1e-3, 1e-3), kFlipFraction);
  EXPECT_EQ(out.radii.size(), ref.radii.size());
  size_t radius_mismatch = 0, visible = 0;
  for (size_t i = 0; i < out.radii.size(); ++i) {
    visible += ref.radii[i] > 0;
    if ((out.radii[i] > 0) != (ref.radii[i] > 0) || std::abs(out.radii[i] - ref.radii[i]) > 1) ++radius_mismatch;
  }
  EXPECT_LE(radius_mismatch, c.n / 1000) << "culling or extent differs from the reference";
  if (c.n >= 10) EXPECT_GT(visible, 0u) << "the scene must be in view for this test to mean anything";
}

TEST(RenderForward, OnePixel) {
  check_forward({1, 1, 50, 1, 1});
}
TEST(RenderForward, OddSize17x9) {
  check_forward({17, 9, 40, 2, 2});
}
TEST(RenderForward, SingleGaussian) {
  check_forward({64, 48, 1, 0, 3});
}
TEST(RenderForward, Odd333x250) {
  check_forward({333, 250, 1000, 3, 4});
}
TEST(RenderForward, Many333x250) {
  check_forward({333, 250, 100000, 1, 5});
}
TEST(RenderForward, Background) {
  RenderSettings s;
  s.background = {0.2f, 0.5f, 1.0f};
  check_forward({40, 30, 30, 1, 6}, s);
}
// The coarse levels of coarse-to-fine training render with other low-passes
// (TrainConfig::coarse_lowpass): wider and narrower than the default 0.3.
TEST(RenderForward, OtherLowpass) {
  for (float lp : {0.075f, 1.2f}) {
    RenderSettings s;
    s.lowpass = lp;
    check_forward({40, 30, 30, 1, 8}, s);
  }
}
TEST(RenderForward, LowpassWidensEverySplat) {
  // A Gaussian far below a pixel at the origin: its image is the low-pass
  // itself, so each pixel's alpha is opacity x exp(-d^2 / (2 lowpass)), d
  // the distance from the projected mean to the pixel centre (i + 0.5).
  test::SceneSpec spec;
  spec.n = 1;
  GaussianSet g = test::random_scene(spec, 9);
  for (int k = 0; k < 3; ++k) g.means[k] = 0.f, g.scales[k] = 1e-6f;
  g.opacities[0] = 0.5f;
  const Camera cam = test::look_at_origin(33, 33);
  const double u = cam.fx * cam.t.x() / cam.t.z() + cam.cx, v = cam.fy * cam.t.y() / cam.t.z() + cam.cy;
  Renderer r(test::runtime());
  for (float lp : {0.3f, 1.2f}) {
    RenderSettings s;
    s.lowpass = lp;
    RenderOutput out = r.render(g, cam, s);
    int checked = 0;
    for (int y = 12; y < 21; ++y)
      for (int x = 12; x < 21; ++x) {
        const double d2 = (x + 0.5 - u) * (x + 0.5 - u) + (y + 0.5 - v) * (y + 0.5 - v);
        const double want = 0.5 * std::exp(-0.5 * d2 / lp);
        if (want < 2.0 / 255) continue;  // near the 1/255 cut
        EXPECT_NEAR(out.alpha[y * 33 + x], want, 2e-4) << "lowpass " << lp << " at " << x << "," << y;
        ++checked;
      }
    EXPECT_GE(checked, lp > 1 ? 20 : 5) << lp;
  }
}
TEST(RenderForward, LowerActiveShDegree) {
  RenderSettings s;
  s.sh_degree = 1;
  check_forward({40, 30, 30, 3, 7}, s);
}

}  // namespace
}  // namespace ag2gs

namespace ag2gs {
namespace {

// Without features the other outputs keep their bits and the feature planes
// come out zero (RenderSettings::features, a training-speed switch).
TEST(RenderForward, WithoutFeaturesSameImageZeroFeatures) {
  test::SceneSpec spec;
  spec.n = 2000;
  GaussianSet g = test::random_scene(spec, 21);
  Camera cam = test::look_at_origin(97, 61);
  Renderer r(test::runtime());
  RenderSettings with, without;
  without.features = false;
  const RenderOutput a = r.render(g, cam, with);
  const RenderOutput b = r.render(g, cam, without);
  EXPECT_TRUE(a.rgb == b.rgb);
  EXPECT_TRUE(a.alpha == b.alpha);
  EXPECT_TRUE(a.depth == b.depth);
  EXPECT_TRUE(a.distortion == b.distortion);
  EXPECT_TRUE(std::any_of(a.feature.begin(), a.feature.end(), [](float x) { return x != 0.f; }));
  EXPECT_TRUE(std::all_of(b.feature.begin(), b.feature.end(), [](float x) { return x == 0.f; }));
  // Such a frame takes no feature gradient.
  OutputGrads og;
  og.feature.assign(b.feature.size(), 1.f);
  EXPECT_THROW(r.render_backward(og), std::logic_error);
}

// The sort plan (the CPU block sort at any block size, the GPU work-group
// sort at any digit width, work-group and tile, frames sorted and scanned
// in one launch each: 12000 Gaussians in 12 tiles of 1024) sets only the speed: a
// stable sort has one result, so every plan gives the same pictures and
// gradients, bit for bit, a partial last block and a single block included.
// (tests/host/render/test_radix_sort.cpp checks the sort itself.)
TEST(RenderForward, SortPlanChangesNoBit) {
  test::SceneSpec spec;
  spec.n = 12000;
  GaussianSet g = test::random_scene(spec, 23);
  Camera cam = test::look_at_origin(333, 250);
  auto run = [&](const char* plan, RenderOutput* out, std::vector<float>* grad_means) {
    setenv("AG2GS_SORT", plan, 1);
    Renderer r(test::runtime());
    unsetenv("AG2GS_SORT");
    *out = r.render(g, cam, RenderSettings{});
    OutputGrads og;
    og.rgb.assign(out->rgb.size(), 0.f);
    for (size_t i = 0; i < og.rgb.size(); ++i) og.rgb[i] = static_cast<float>((i * 7919) % 13) / 13.f - 0.5f;
    *grad_means = r.render_backward(og).means;
  };
  RenderOutput ref, other;
  std::vector<float> ref_grad, grad;
  run("block:4096", &ref, &ref_grad);
  for (const char* plan :
       {"block:256", "block:33", "block:65536", "group", "group:5:64:3", "group:2:32:1:2", "group:4:32:32:auto:64"}) {
    run(plan, &other, &grad);
    EXPECT_TRUE(ref.rgb == other.rgb) << "plan " << plan;
    EXPECT_TRUE(ref.alpha == other.alpha) << "plan " << plan;
    EXPECT_TRUE(ref.depth == other.depth) << "plan " << plan;
    EXPECT_TRUE(ref.n_contrib == other.n_contrib) << "plan " << plan;
    EXPECT_TRUE(ref_grad == grad) << "plan " << plan;
  }
  for (const char* bad : {"block:0", "block:64k", "group:6:256:8"}) {
    setenv("AG2GS_SORT", bad, 1);
    EXPECT_THROW(Renderer{test::runtime()}, std::invalid_argument) << bad;
  }
  unsetenv("AG2GS_SORT");
}

}  // namespace
}  // namespace ag2gs
