// The device photometric loss (L1 + SSIM, host/losses/image_loss.h) against the
// double-precision reference (tests/reference/image_loss_reference.h), whose
// analytic gradient is itself checked against central finite differences.
//
// Tolerances, measured on PoCL (float32 blurs; the tests print the errors):
//   loss, l1, ssim, mse: |dev - ref| <= kValueTol (worst measured 4.6e-7)
//   gradient: |dev - ref| <= kGradTol * max|ref| per image (worst measured
//     1.8e-5 of scale: float cancellation in the raw-moment partials, the
//     same formulation as 3DGS's autograd and fused-ssim);
//   images with low-variance windows: kGradTolSaturated (worst measured
//     3e-5 on the saturated images here, 1e-4 on the benchmark's smooth
//     low-contrast pair: partials of size ~1 / (sxx + syy + C2) cancel)
//   reference vs central finite differences: kFdTol * max|grad| (worst 3e-8)
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <random>
#include <vector>

#include "host/losses/image_loss.h"
#include "tests/reference/image_loss_reference.h"
#include "tests/test_util.h"

namespace ag2gs {
namespace {

constexpr double kValueTol = 2e-6;
constexpr double kGradTol = 5e-5;
constexpr double kGradTolSaturated = 5e-4;
constexpr double kFdTol = 2e-7;

// A smooth random image in [0, 1] (a few plane waves and a little noise):
// windows with both flat and textured content, like a photograph.
std::vector<float> smooth_image(int w, int h, uint32_t seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(0, 1);
  std::vector<float> img(static_cast<size_t>(w) * h * 3);
  for (int c = 0; c < 3; ++c) {
    double a[3], b[3], ph[3], amp[3];
    for (int k = 0; k < 3; ++k) {
      a[k] = (u(rng) - 0.5) * 0.8;
      b[k] = (u(rng) - 0.5) * 0.8;
      ph[k] = u(rng) * 6.283;
      amp[k] = 0.1 + 0.15 * u(rng);
    }
    for (int y = 0; y < h; ++y)
      for (int x = 0; x < w; ++x) {
        double v = 0.5 + 0.03 * (u(rng) - 0.5);
        for (int k = 0; k < 3; ++k) v += amp[k] * std::sin(a[k] * x + b[k] * y + ph[k]);
        img[(static_cast<size_t>(y) * w + x) * 3 + c] = static_cast<float>(std::clamp(v, 0.0, 1.0));
      }
  }
  return img;
}

// A rendering of `target`: the target plus smooth and noisy errors, each
// value at least 0.01 away from the target (away from the kink of |x - y|).
std::vector<float> perturbed(const std::vector<float>& target, int w, int h, uint32_t seed) {
  std::vector<float> bias = smooth_image(w, h, seed + 1000);
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(-1, 1);
  std::vector<float> out(target.size());
  for (size_t i = 0; i < target.size(); ++i) {
    double d = 0.2 * (bias[i] - 0.5) + 0.05 * u(rng);
    if (std::abs(d) < 0.01) d = d < 0 ? -0.01 : 0.01;
    out[i] = static_cast<float>(target[i] + d);
  }
  return out;
}

std::vector<float> random_weights(int w, int h, uint32_t seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<float> u(0, 1);
  std::vector<float> wt(static_cast<size_t>(w) * h);
  for (auto& v : wt) v = u(rng) < 0.3f ? 0.f : u(rng);  // a mask with soft values
  return wt;
}

double max_abs(const std::vector<double>& v) {
  double m = 0;
  for (double x : v) m = std::max(m, std::abs(x));
  return m;
}

void check_values(const ImageLossResult& d, const ref::RefImageLoss& r) {
  std::printf("  loss %.9f (ref %.9f)  l1 %.3g  ssim %.3g  mse %.3g  errors %.2g %.2g %.2g %.2g\n", d.loss, r.loss,
              d.l1, d.ssim, d.mse, std::abs(d.loss - r.loss), std::abs(d.l1 - r.l1), std::abs(d.ssim - r.ssim),
              std::abs(d.mse - r.mse));
  EXPECT_NEAR(d.loss, r.loss, kValueTol);
  EXPECT_NEAR(d.l1, r.l1, kValueTol);
  EXPECT_NEAR(d.ssim, r.ssim, kValueTol);
  EXPECT_NEAR(d.mse, r.mse, kValueTol);
}

void check_grad(const std::vector<float>& dev, const std::vector<double>& ref) {
  const double scale = max_abs(ref);
  auto c = test::compare(dev, ref, kGradTol * scale + 1e-30, 0.0);
  std::printf("  grad scale %.3g  max abs %.3g (%.2g of scale)  violations %zu/%zu\n", scale, c.max_abs,
              scale > 0 ? c.max_abs / scale : 0.0, c.violations, c.n);
  EXPECT_EQ(c.violations, 0u);
  EXPECT_EQ(c.nan_mismatch, 0u);
}

void check_against_reference(int w, int h, uint32_t seed, float lambda, bool weighted, ImageLossOptions opt = {}) {
  std::printf("%dx%d lambda %.2f%s wg %d lanes %d\n", w, h, lambda, weighted ? " weighted" : "", opt.work_group,
              opt.lanes);
  const auto target = smooth_image(w, h, seed);
  const auto rendered = perturbed(target, w, h, seed + 7);
  const auto weights = random_weights(w, h, seed + 3);
  ImageLoss loss(test::runtime(), opt);
  std::vector<float> grad;
  ImageLossResult d = loss.forward_backward(rendered, target, w, h, lambda, &grad, weighted ? &weights : nullptr);
  ref::RefImageLoss r = ref::image_loss(rendered, target, w, h, lambda, true, weighted ? &weights : nullptr);
  check_values(d, r);
  check_grad(grad, r.grad);
}

// ---------------------------------------------------------------- reference

// Central differences of the reference loss in every input value.
void check_reference_fd(int w, int h, uint32_t seed, double lambda, bool weighted) {
  const auto tf = smooth_image(w, h, seed);
  const auto xf = perturbed(tf, w, h, seed + 1);
  const auto wf = random_weights(w, h, seed + 2);
  std::vector<double> x(xf.begin(), xf.end()), y(tf.begin(), tf.end()), wt(wf.begin(), wf.end());
  const std::vector<double>* wp = weighted ? &wt : nullptr;
  const auto r = ref::image_loss(x, y, w, h, lambda, true, wp);
  const double scale = max_abs(r.grad), step = 1e-6;
  double worst = 0;
  for (size_t i = 0; i < x.size(); ++i) {
    auto xp = x, xm = x;
    xp[i] += step;
    xm[i] -= step;
    const double fd =
        (ref::image_loss(xp, y, w, h, lambda, false, wp).loss - ref::image_loss(xm, y, w, h, lambda, false, wp).loss) /
        (2 * step);
    worst = std::max(worst, std::abs(fd - r.grad[i]));
  }
  std::printf("%dx%d lambda %.2f%s: max |fd - analytic| %.3g (%.2g of scale %.3g)\n", w, h, lambda,
              weighted ? " weighted" : "", worst, worst / scale, scale);
  EXPECT_LE(worst, kFdTol * scale);
}

TEST(ImageLossReference, GradientMatchesFiniteDifferences) {
  check_reference_fd(7, 5, 1, 0.2, false);
  check_reference_fd(17, 9, 2, 0.2, false);
  check_reference_fd(13, 12, 3, 0.2, true);
  check_reference_fd(1, 1, 4, 0.2, false);
  check_reference_fd(6, 7, 5, 1.0, false);  // SSIM only
}

TEST(ImageLossReference, Identities) {
  const auto img = smooth_image(12, 9, 5);
  auto r = ref::image_loss(img, img, 12, 9, 0.2, true);
  EXPECT_NEAR(r.ssim, 1.0, 1e-15);
  EXPECT_NEAR(r.loss, 0.0, 1e-15);
  EXPECT_LE(max_abs(r.grad), 1e-15);  // SSIM is at its maximum, sign(0) = 0
  // The window sums to 1 and is 3DGS's gaussian(11, 1.5).
  auto g = ref::ssim_window_1d();
  double s = 0;
  for (double v : g) s += v;
  EXPECT_NEAR(s, 1.0, 1e-15);
  EXPECT_NEAR(g[5], 0.266011724, 1e-8);
}

// ---------------------------------------------------------------- device

TEST(ImageLoss, ForwardBackwardMatchReference) {
  const int sizes[][2] = {{1, 1}, {7, 5}, {17, 9}, {64, 48}, {161, 120}};
  uint32_t seed = 10;
  for (auto& s : sizes) check_against_reference(s[0], s[1], seed++, kSsimLambda, false);
}

TEST(ImageLoss, WeightedMatchesReference) {
  check_against_reference(17, 9, 20, kSsimLambda, true);
  check_against_reference(64, 48, 21, kSsimLambda, true);
}

TEST(ImageLoss, LambdaExtremes) {
  check_against_reference(33, 20, 30, 0.f, false);  // L1 only
  check_against_reference(33, 20, 31, 1.f, false);  // SSIM only
}

// Another device's configuration on this one: the GPU layout (one pixel per
// work-item, 64-wide groups). Partial sums and image edges fall differently;
// the loss must still match the reference, and without weights the gradient
// must be the same bits (with weights, 1 / (3 sum w) is a float sum grouped
// by the configuration). One configuration only: each is a program build of
// ~3 s on a cold kernel cache.
TEST(ImageLoss, GpuLayout) {
  const int w = 37, h = 23;
  const ImageLossOptions gpu{64, 1};
  if (static_cast<size_t>(gpu.work_group) > test::runtime().info().max_work_group) GTEST_SKIP();
  check_against_reference(w, h, 40, kSsimLambda, true, gpu);
  check_against_reference(w, h, 41, kSsimLambda, false, gpu);
  const auto target = smooth_image(w, h, 42);
  const auto rendered = perturbed(target, w, h, 43);
  std::vector<float> g_default, g_gpu;
  ImageLoss(test::runtime()).forward_backward(rendered, target, w, h, kSsimLambda, &g_default);
  ImageLoss(test::runtime(), gpu).forward_backward(rendered, target, w, h, kSsimLambda, &g_gpu);
  EXPECT_EQ(test::hash_vec(g_gpu), test::hash_vec(g_default));
}

// Saturated regions (pixels clamped at 0 or 1 in both images): windows of
// zero variance, D2 = C2, where the partials are largest and cancel most in
// float. Measured separately, with the bound for low-variance images.
TEST(ImageLoss, SaturatedRegions) {
  const int w = 96, h = 64;
  auto target = smooth_image(w, h, 45);
  auto rendered = perturbed(target, w, h, 46);
  for (size_t i = 0; i < target.size(); ++i) {
    target[i] = std::clamp(3.f * (target[i] - 0.5f) + 0.5f, 0.f, 1.f);
    rendered[i] = std::clamp(3.f * (rendered[i] - 0.5f) + 0.5f, 0.f, 1.f);
  }
  ImageLoss loss(test::runtime());
  std::vector<float> grad;
  ImageLossResult d = loss.forward_backward(rendered, target, w, h, kSsimLambda, &grad);
  ref::RefImageLoss r = ref::image_loss(rendered, target, w, h, kSsimLambda, true);
  check_values(d, r);
  const double scale = max_abs(r.grad);
  auto c = test::compare(grad, r.grad, kGradTolSaturated * scale, 0.0);
  std::printf("  grad scale %.3g  max abs %.3g (%.2g of scale)\n", scale, c.max_abs, c.max_abs / scale);
  EXPECT_EQ(c.violations, 0u);
}

TEST(ImageLoss, IdenticalImagesGiveSsimOneAndLossZero) {
  const auto img = smooth_image(45, 31, 50);
  ImageLoss loss(test::runtime());
  std::vector<float> grad;
  ImageLossResult r = loss.forward_backward(img, img, 45, 31, kSsimLambda, &grad);
  std::printf("  ssim %.12f loss %.3g psnr %g\n", r.ssim, r.loss, r.psnr());
  EXPECT_EQ(r.ssim, 1.0);
  EXPECT_EQ(r.l1, 0.0);
  EXPECT_EQ(r.loss, 0.0);
  EXPECT_TRUE(std::isinf(r.psnr()));
  float gmax = 0;
  for (float g : grad) gmax = std::max(gmax, std::abs(g));
  // Zero analytically (SSIM at its maximum, sign(0) = 0); in float the
  // partials cancel to ~1e-5 of the gradient's unit 1 / (3 H W) (measured 7.6e-6).
  const double unit = 1.0 / (3.0 * 45 * 31);
  std::printf("  max |grad| %.3g (%.2g of 1/(3HW))\n", gmax, gmax / unit);
  EXPECT_LE(gmax, 1e-4 * unit);
  // A constant image: zero variance everywhere.
  std::vector<float> flat(45 * 31 * 3, 0.25f);
  r = loss.forward_backward(flat, flat, 45, 31, kSsimLambda, &grad);
  EXPECT_EQ(r.ssim, 1.0);
  EXPECT_EQ(r.loss, 0.0);
}

TEST(ImageLoss, Psnr) {
  EXPECT_NEAR(psnr_from_mse(0.01), 20.0, 1e-12);
  EXPECT_NEAR(psnr_from_mse(1e-4), 40.0, 1e-12);
  // Constant offset 0.1 everywhere: mse 0.01.
  std::vector<float> a(20 * 10 * 3, 0.3f), b(20 * 10 * 3, 0.4f);
  ImageLoss loss(test::runtime());
  auto r = loss.forward_backward(a, b, 20, 10);
  EXPECT_NEAR(r.mse, 0.01, 1e-7);
  EXPECT_NEAR(r.psnr(), 20.0, 1e-4);
  EXPECT_NEAR(r.l1, 0.1, 1e-7);
}

TEST(ImageLoss, Deterministic) {
  const int w = 97, h = 61;
  const auto target = smooth_image(w, h, 60);
  const auto rendered = perturbed(target, w, h, 61);
  ImageLoss a(test::runtime()), b(test::runtime());
  std::vector<float> ga, gb;
  auto ra = a.forward_backward(rendered, target, w, h, kSsimLambda, &ga);
  auto rb = b.forward_backward(rendered, target, w, h, kSsimLambda, &gb);
  auto rc = a.forward_backward(rendered, target, w, h, kSsimLambda, &gb);
  EXPECT_EQ(ra.loss, rb.loss);
  EXPECT_EQ(ra.ssim, rb.ssim);
  EXPECT_EQ(ra.loss, rc.loss);
  EXPECT_EQ(test::hash_vec(ga), test::hash_vec(gb));
}

// Weights of one are the unweighted loss, bit for bit; all-zero weights give
// a zero loss and gradient instead of 0/0.
TEST(ImageLoss, WeightEdgeCases) {
  const int w = 30, h = 21;
  const auto target = smooth_image(w, h, 70);
  const auto rendered = perturbed(target, w, h, 71);
  ImageLoss loss(test::runtime());
  std::vector<float> g0, g1;
  std::vector<float> ones(w * h, 1.f), zeros(w * h, 0.f);
  auto r0 = loss.forward_backward(rendered, target, w, h, kSsimLambda, &g0);
  auto r1 = loss.forward_backward(rendered, target, w, h, kSsimLambda, &g1, &ones);
  EXPECT_EQ(r0.loss, r1.loss);
  EXPECT_EQ(test::hash_vec(g0), test::hash_vec(g1));
  auto rz = loss.forward_backward(rendered, target, w, h, kSsimLambda, &g1, &zeros);
  EXPECT_EQ(rz.loss, 0.0);
  EXPECT_EQ(rz.ssim, 1.0);
  for (float g : g1) ASSERT_EQ(g, 0.f);
}

// The device API: planar images ([3,H,W], the renderer's layout) give the
// same bits as interleaved ones; forward-only gives the same loss.
TEST(ImageLoss, DeviceApiPlanarLayout) {
  const int w = 41, h = 26;
  const size_t npix = static_cast<size_t>(w) * h;
  const auto target = smooth_image(w, h, 80);
  const auto rendered = perturbed(target, w, h, 81);
  auto planar = [&](const std::vector<float>& v) {
    std::vector<float> out(v.size());
    for (size_t p = 0; p < npix; ++p)
      for (int c = 0; c < 3; ++c) out[c * npix + p] = v[p * 3 + c];
    return out;
  };
  Runtime& rt = test::runtime();
  DeviceBuffer x(&rt), y(&rt), grad(&rt);
  x.upload(planar(rendered));
  y.upload(planar(target));
  ImageLoss loss(rt);
  ImageLossResult rp = loss.forward_backward(x, y, w, h, kSsimLambda, &grad, nullptr, ImageLayout::kPlanar);
  std::vector<float> gp;
  grad.download(gp, npix * 3);
  std::vector<float> gi;
  ImageLossResult ri = loss.forward_backward(rendered, target, w, h, kSsimLambda, &gi);
  EXPECT_EQ(rp.loss, ri.loss);
  EXPECT_EQ(test::hash_vec(gp), test::hash_vec(planar(gi)));
  loss.enqueue(x, y, w, h, kSsimLambda, nullptr, nullptr, ImageLayout::kPlanar);
  EXPECT_EQ(loss.result().loss, ri.loss);
}

TEST(ImageLoss, RejectsBadArguments) {
  ImageLoss loss(test::runtime());
  std::vector<float> a(12 * 3), b(12 * 3), g;
  EXPECT_THROW(loss.forward_backward(a, b, 4, 4), std::invalid_argument);  // 16 pixels expected
  EXPECT_THROW(loss.forward_backward(a, b, 0, 12), std::invalid_argument);
  EXPECT_THROW(loss.forward_backward(a, b, 4, 3, 1.5f), std::invalid_argument);
  std::vector<float> wrong_weights(5);
  EXPECT_THROW(loss.forward_backward(a, b, 4, 3, 0.2f, &g, &wrong_weights), std::invalid_argument);
  DeviceBuffer x(&test::runtime());
  x.upload(a);
  EXPECT_THROW(loss.enqueue(x, x, 4, 3, 0.2f, &x), std::invalid_argument);
  EXPECT_THROW(loss.enqueue(x, x, 40, 30), std::invalid_argument);  // buffer too small
  EXPECT_THROW(ImageLoss(test::runtime(), ImageLossOptions{3, 0}), std::invalid_argument);
  EXPECT_THROW(ImageLoss(test::runtime(), ImageLossOptions{0, 3}), std::invalid_argument);
  ImageLoss fresh(test::runtime());
  EXPECT_THROW(fresh.result(), std::logic_error);
}

}  // namespace
}  // namespace ag2gs
