// The double-precision reference rasterizer's analytic backward against central
// finite differences of its own forward pass, for every input array, plus a few
// forward identities. Scenes are small and random; a parameter whose
// perturbation changes a discrete decision (visibility, order, a clamp, a
// per-pixel skip or stop) is skipped, since the FD would straddle a jump.
#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <functional>
#include <limits>
#include <random>
#include <string>
#include <vector>

#include "tests/reference/reference_renderer.h"

namespace ag2gs::ref {
namespace {

// ---------------------------------------------------------------------------
// Scenes

struct Scene {
  RefGaussians g;
  Camera cam;
  RenderSettings settings;
};

double uniform(std::mt19937& rng, double lo, double hi) {
  return std::uniform_real_distribution<double>(lo, hi)(rng);
}

// A 24x18 camera with an off-centre principal point and a random pose.
Camera make_camera(std::mt19937& rng) {
  Camera cam;
  cam.width = 24;
  cam.height = 18;
  cam.fx = 22;
  cam.fy = 21;
  cam.cx = 12.3;
  cam.cy = 8.6;
  const Eigen::Vector3d axis =
      Eigen::Vector3d(uniform(rng, -1, 1), uniform(rng, -1, 1), uniform(rng, -1, 1)).normalized();
  cam.R = Eigen::AngleAxisd(uniform(rng, 0.1, 0.6), axis).toRotationMatrix();
  cam.t = Eigen::Vector3d(uniform(rng, -0.5, 0.5), uniform(rng, -0.5, 0.5), uniform(rng, -0.5, 0.5));
  return cam;
}

// Appends one Gaussian whose mean is p_cam in camera space.
void add_gaussian(Scene& s, std::mt19937& rng, const Eigen::Vector3d& p_cam, double scale, double opacity) {
  RefGaussians& g = s.g;
  const Eigen::Vector3d mean = s.cam.R.transpose() * (p_cam - s.cam.t);
  for (int c = 0; c < 3; ++c) g.means.push_back(mean[c]);
  // moderate anisotropy: axis ratios up to 3
  for (int c = 0; c < 3; ++c) g.scales.push_back(scale * uniform(rng, 0.6, 1.8));
  // an unnormalised quaternion
  std::normal_distribution<double> normal;
  Eigen::Vector4d q(normal(rng), normal(rng), normal(rng), normal(rng));
  q *= uniform(rng, 0.5, 2.0) / q.norm();
  for (int c = 0; c < 4; ++c) g.quats.push_back(q[c]);
  g.opacities.push_back(opacity);
  const int K = g.sh_coeffs();
  for (int k = 0; k < K; ++k)
    for (int c = 0; c < 3; ++c) g.sh.push_back(k == 0 ? uniform(rng, -1.2, 1.2) : uniform(rng, -0.4, 0.4));
  for (int c = 0; c < 3; ++c) g.features.push_back(uniform(rng, -1, 1));
}

// n Gaussians well inside the view (|u - cx| <= 6.6 px, |v - cy| <= 5.3 px),
// depth 2..5, projected standard deviations of about 0.5..3 px.
Scene random_scene(unsigned seed, int n, int sh_degree) {
  std::mt19937 rng(seed);
  Scene s;
  s.cam = make_camera(rng);
  s.g.sh_degree = sh_degree;
  for (int i = 0; i < n; ++i) {
    const double z = uniform(rng, 2, 5);
    const Eigen::Vector3d p(uniform(rng, -0.3, 0.3) * z, uniform(rng, -0.25, 0.25) * z, z);
    add_gaussian(s, rng, p, uniform(rng, 0.04, 0.12) * z, uniform(rng, 0.2, 0.8));
  }
  return s;
}

// ---------------------------------------------------------------------------
// Upstream gradients and the scalar loss L = sum <grad, output>.

enum OutputMask { kRgb = 1, kFeature = 2, kDepth = 4, kAlpha = 8, kDistortion = 16, kAll = 31 };

OutputGrads random_output_grads(unsigned seed, const Camera& cam, int mask) {
  std::mt19937 rng(seed);
  const size_t npix = static_cast<size_t>(cam.width) * cam.height;
  auto fill = [&](std::vector<float>& v, size_t n) {
    v.resize(n);
    for (float& x : v) x = static_cast<float>(uniform(rng, -1, 1));
  };
  OutputGrads og;
  if (mask & kRgb) fill(og.rgb, 3 * npix);
  if (mask & kFeature) fill(og.feature, 3 * npix);
  if (mask & kDepth) fill(og.depth, npix);
  if (mask & kAlpha) fill(og.alpha, npix);
  if (mask & kDistortion) fill(og.distortion, npix);
  return og;
}

// L(a) - L(b) = sum <grad, out_a - out_b>, differenced per pixel so that the
// pixels a perturbation does not touch add exactly nothing (summing L(a) and
// L(b) separately would add round-off of the order eps |L|).
double dot_difference(const std::vector<float>& g, const std::vector<double>& a, const std::vector<double>& b) {
  double s = 0;
  for (size_t i = 0; i < g.size(); ++i) s += g[i] * (a[i] - b[i]);
  return s;
}

double loss_difference(const RefImages& a, const RefImages& b, const OutputGrads& og) {
  return dot_difference(og.rgb, a.rgb, b.rgb) + dot_difference(og.feature, a.feature, b.feature) +
         dot_difference(og.depth, a.depth, b.depth) + dot_difference(og.alpha, a.alpha, b.alpha) +
         dot_difference(og.distortion, a.distortion, b.distortion);
}

// ---------------------------------------------------------------------------
// The finite-difference checker.

// Central differences with step h = kRelStep max(|x|, kStepFloor): relative
// above |x| = 1, absolute 1e-6 below (smaller steps only add round-off).
constexpr double kRelStep = 1e-6;
constexpr double kStepFloor = 1.0;

// Error measure: |analytic - fd| / max(|analytic|, |fd|, floor), where
// floor = kErrorFloorRel * (largest |analytic| of that array). The floor keeps
// entries that are ~0 analytically from being judged by FD round-off alone.
constexpr double kErrorFloorRel = 1e-4;

struct Report {
  std::string name;
  int checked = 0, skipped = 0;
  double max_error = 0;  // the error measure above, max over checked entries
  double max_abs = 0;    // largest |analytic| gradient in the array
  size_t worst = 0;
};

// Checks analytic[i] against the FD of the loss along parameter i of x, for
// all i. images() renders at the current x, decisions() gives its discrete
// state; a parameter is skipped when the decisions at x - h or x + h differ
// from those at x.
Report check_array(const std::string& name, std::vector<double>& x, const std::vector<double>& analytic,
                   const OutputGrads& og, const std::function<RefImages()>& images,
                   const std::function<std::vector<int>()>& decisions) {
  Report r;
  r.name = name;
  for (double a : analytic) r.max_abs = std::max(r.max_abs, std::abs(a));
  const double floor = std::max(kErrorFloorRel * r.max_abs, std::numeric_limits<double>::min());
  const std::vector<int> base = decisions();
  for (size_t i = 0; i < x.size(); ++i) {
    const double x0 = x[i];
    const double h = kRelStep * std::max(std::abs(x0), kStepFloor);
    x[i] = x0 + h;
    const double xp = x[i];
    const RefImages ip = images();
    const bool same_p = decisions() == base;
    x[i] = x0 - h;
    const double xm = x[i];
    const RefImages im = images();
    const bool same_m = decisions() == base;
    x[i] = x0;
    if (!same_p || !same_m) {
      ++r.skipped;
      continue;
    }
    const double fd = loss_difference(ip, im, og) / (xp - xm);
    const double err = std::abs(fd - analytic[i]) / std::max({std::abs(fd), std::abs(analytic[i]), floor});
    if (err > r.max_error) {
      r.max_error = err;
      r.worst = i;
    }
    ++r.checked;
  }
  return r;
}

void print(const Report& r) {
  std::printf("  %-9s checked %4d skipped %3d  max |grad| %9.3g  max rel error %9.3g (entry %zu)\n", r.name.c_str(),
              r.checked, r.skipped, r.max_abs, r.max_error, r.worst);
}

struct ArraySpec {
  const char* name;
  std::vector<double> RefGaussians::*input;
  std::vector<double> RefGrads::*grad;
};

const ArraySpec kArrays[] = {
    {"means", &RefGaussians::means, &RefGrads::means}, {"scales", &RefGaussians::scales, &RefGrads::scales},
    {"quats", &RefGaussians::quats, &RefGrads::quats}, {"opacities", &RefGaussians::opacities, &RefGrads::opacities},
    {"sh", &RefGaussians::sh, &RefGrads::sh},          {"features", &RefGaussians::features, &RefGrads::features},
};

// FD of the full render w.r.t. every input array; returns one report per array.
std::vector<Report> check_render_gradients(Scene s, const OutputGrads& og) {
  const RefGrads grads = render_backward(s.g, s.cam, s.settings, og);
  auto f = [&] { return render(s.g, s.cam, s.settings); };
  auto dec = [&] { return discrete_decisions(s.g, s.cam, s.settings); };
  std::vector<Report> reports;
  for (const ArraySpec& a : kArrays) reports.push_back(check_array(a.name, s.g.*a.input, grads.*a.grad, og, f, dec));
  return reports;
}

// Tolerance on the error measure. Measured on the scenes below (gcc 12, -O2,
// x86-64): worst 8.5e-6 (scales with only the distortion gradient non-zero, a
// tiny loss), otherwise at most 2.7e-6 (sh, quats); means, opacities and
// features 1e-10..1e-7. The errors shrink with larger steps, i.e. they are FD
// round-off, not model error; 1e-4 leaves room for other compilers and FMA.
constexpr double kTolerance = 1e-4;

// Runs the checker and the sanity conditions that make a pass meaningful:
// something was checked, few parameters were skipped, and every array has a
// non-zero gradient (unless allowed to be all zero).
void expect_gradients_match(const Scene& s, const OutputGrads& og, const std::vector<std::string>& may_be_zero = {}) {
  const std::vector<Report> reports = check_render_gradients(s, og);
  for (const Report& r : reports) {
    print(r);
    EXPECT_GT(r.checked, 0) << r.name;
    EXPECT_LE(r.skipped, r.checked / 10 + 1) << r.name << ": too many skipped parameters";
    if (std::find(may_be_zero.begin(), may_be_zero.end(), r.name) == may_be_zero.end()) {
      EXPECT_GT(r.max_abs, 0) << r.name << ": gradient is all zero";
    }
    EXPECT_LT(r.max_error, kTolerance) << r.name << " entry " << r.worst;
  }
}

// ---------------------------------------------------------------------------
// Gradient tests

TEST(ReferenceGradients, AllInputsAllOutputsSh3) {
  for (unsigned seed : {1u, 2u}) {
    Scene s = random_scene(seed, 12, 3);
    const OutputGrads og = random_output_grads(100 + seed, s.cam, kAll);
    expect_gradients_match(s, og);
  }
}

TEST(ReferenceGradients, ManyGaussiansWithEarlyStops) {
  // 20 overlapping Gaussians; some pixels reach T < 1e-4 with the opacities raised.
  Scene s = random_scene(7, 20, 1);
  for (double& o : s.g.opacities) o = std::min(0.95, o + 0.3);
  const OutputGrads og = random_output_grads(107, s.cam, kAll);
  const std::vector<int> dec = discrete_decisions(s.g, s.cam, s.settings);
  int stops = 0;
  for (size_t i = 4 * s.g.size(); i < dec.size(); ++i) stops += dec[i] >= 0 && dec[i] % 8 == 4;
  std::printf("  pixels with an early stop: %d\n", stops);
  EXPECT_GT(stops, 0);
  expect_gradients_match(s, og);
}

TEST(ReferenceGradients, ActiveDegreeBelowSetDegree) {
  Scene s = random_scene(3, 10, 3);
  s.settings.sh_degree = 1;
  const OutputGrads og = random_output_grads(103, s.cam, kAll);
  expect_gradients_match(s, og);
  // Coefficients above the active degree get exactly 0.
  const RefGrads grads = render_backward(s.g, s.cam, s.settings, og);
  const int K = s.g.sh_coeffs();
  double above = 0, below = 0;
  for (size_t n = 0; n < s.g.size(); ++n)
    for (int k = 0; k < K; ++k)
      for (int c = 0; c < 3; ++c) {
        const double v = std::abs(grads.sh[(n * K + k) * 3 + c]);
        (k >= 4 ? above : below) += v;
      }
  EXPECT_EQ(above, 0.0);
  EXPECT_GT(below, 0.0);
}

TEST(ReferenceGradients, ShDegreeZero) {
  Scene s = random_scene(4, 10, 0);
  const OutputGrads og = random_output_grads(104, s.cam, kAll);
  expect_gradients_match(s, og);
}

TEST(ReferenceGradients, OnlyDistortion) {
  Scene s = random_scene(5, 12, 2);
  const OutputGrads og = random_output_grads(105, s.cam, kDistortion);
  // Distortion depends on neither colour nor feature.
  expect_gradients_match(s, og, {"sh", "features"});
  const RefGrads grads = render_backward(s.g, s.cam, s.settings, og);
  for (double v : grads.sh) ASSERT_EQ(v, 0.0);
  for (double v : grads.features) ASSERT_EQ(v, 0.0);
}

TEST(ReferenceGradients, OnlyAlpha) {
  Scene s = random_scene(6, 12, 1);
  const OutputGrads og = random_output_grads(106, s.cam, kAlpha);
  expect_gradients_match(s, og, {"sh", "features"});
}

TEST(ReferenceGradients, NonZeroBackground) {
  Scene s = random_scene(8, 8, 2);
  s.settings.background = {0.3f, -0.7f, 1.2f};
  const OutputGrads og = random_output_grads(108, s.cam, kRgb);
  expect_gradients_match(s, og, {"features"});
}

TEST(ReferenceGradients, OtherLowpass) {
  for (float lp : {0.075f, 1.2f}) {
    Scene s = random_scene(8, 8, 2);
    s.settings.lowpass = lp;
    const OutputGrads og = random_output_grads(108, s.cam, kRgb);
    expect_gradients_match(s, og, {"features"});
  }
}

TEST(ReferenceGradients, AlphaClampAtCentres) {
  // Opacities near 1: pixels near the centres hit alpha = 0.99 (no gradient to
  // opacity or sigma there), the rest do not.
  Scene s = random_scene(9, 8, 1);
  for (double& o : s.g.opacities) o = 0.999;
  const OutputGrads og = random_output_grads(109, s.cam, kAll);
  const std::vector<int> dec = discrete_decisions(s.g, s.cam, s.settings);
  int clamped = 0;
  for (size_t i = 4 * s.g.size(); i < dec.size(); ++i) clamped += dec[i] >= 0 && dec[i] % 8 == 3;
  std::printf("  pixel/Gaussian pairs with a clamped alpha: %d\n", clamped);
  EXPECT_GT(clamped, 0);
  expect_gradients_match(s, og);
}

TEST(ReferenceGradients, JacobianClampActive) {
  // Two large Gaussians whose centres lie outside the clamp limits (x/z beyond
  // lim_xp, y/z below -lim_yn) but whose footprints still reach the image.
  std::mt19937 rng(10);
  Scene s = random_scene(10, 4, 1);
  add_gaussian(s, rng, Eigen::Vector3d(0.95 * 3, 0.1 * 3, 3), 0.6, 0.7);
  add_gaussian(s, rng, Eigen::Vector3d(-0.1 * 2.5, -0.65 * 2.5, 2.5), 0.5, 0.7);
  const std::vector<RefProjected> P = project(s.g, s.cam, s.settings);
  ASSERT_TRUE(P[4].visible);
  ASSERT_TRUE(P[5].visible);
  EXPECT_EQ(P[4].clamp_x, 1);
  EXPECT_EQ(P[5].clamp_y, -1);
  const OutputGrads og = random_output_grads(110, s.cam, kAll);
  expect_gradients_match(s, og);
  // The clamped Gaussians are blended somewhere and their means get gradients.
  const RefGrads grads = render_backward(s.g, s.cam, s.settings, og);
  for (int n : {4, 5})
    EXPECT_GT(std::abs(grads.means[3 * n]) + std::abs(grads.means[3 * n + 1]) + std::abs(grads.means[3 * n + 2]), 0.0)
        << "Gaussian " << n;
}

TEST(ReferenceGradients, BlendBackwardAndMeans2d) {
  // FD of blend() w.r.t. the projected quantities, which checks means2d (the
  // gradient w.r.t. (u, v)) and blend_backward on its own.
  Scene s = random_scene(11, 12, 2);
  s.settings.background = {0.2f, 0.5f, -0.1f};
  const OutputGrads og = random_output_grads(111, s.cam, kAll);
  std::vector<RefProjected> P = project(s.g, s.cam, s.settings);
  const std::vector<RefProjectedGrads> vP = blend_backward(P, s.cam, s.settings, og);
  const RefGrads grads = render_backward(s.g, s.cam, s.settings, og);

  // Flatten (u, v, A, B, C, z, opacity, rgb, feature) per visible Gaussian.
  std::vector<double*> params;
  std::vector<double> analytic;
  for (size_t n = 0; n < P.size(); ++n) {
    if (!P[n].visible) continue;
    RefProjected& p = P[n];
    const RefProjectedGrads& v = vP[n];
    EXPECT_EQ(grads.means2d[2 * n], v.u);
    EXPECT_EQ(grads.means2d[2 * n + 1], v.v);
    double* ps[] = {&p.u,      &p.v,      &p.conic[0], &p.conic[1],   &p.conic[2],   &p.z,         &p.opacity,
                    &p.rgb[0], &p.rgb[1], &p.rgb[2],   &p.feature[0], &p.feature[1], &p.feature[2]};
    const double vs[] = {v.u,      v.v,      v.conic[0], v.conic[1],   v.conic[2],   v.z,         v.opacity,
                         v.rgb[0], v.rgb[1], v.rgb[2],   v.feature[0], v.feature[1], v.feature[2]};
    for (int k = 0; k < 13; ++k) {
      params.push_back(ps[k]);
      analytic.push_back(vs[k]);
    }
  }
  ASSERT_GT(params.size(), 0u);
  std::vector<double> x(params.size());
  for (size_t i = 0; i < x.size(); ++i) x[i] = *params[i];
  auto sync = [&] {
    for (size_t i = 0; i < x.size(); ++i) *params[i] = x[i];
  };
  auto f = [&] {
    sync();
    return blend(P, s.cam, s.settings);
  };
  auto dec = [&] {
    sync();
    return discrete_decisions(P, s.cam, s.settings);
  };
  const Report r = check_array("projected", x, analytic, og, f, dec);
  print(r);
  EXPECT_GT(r.checked, 0);
  EXPECT_LE(r.skipped, r.checked / 10 + 1);
  EXPECT_GT(r.max_abs, 0);
  EXPECT_LT(r.max_error, kTolerance);
}

TEST(ReferenceGradients, SkipHookCatchesADiscontinuity) {
  // Put Gaussian 2 exactly on the alpha >= 1/255 cut at one pixel two pixels
  // right of its centre: o = exp(sigma)/255. The checker must skip its opacity,
  // and without the hook the FD across the jump would be far off.
  Scene s = random_scene(18, 6, 1);
  const std::vector<RefProjected> P = project(s.g, s.cam, s.settings);
  ASSERT_TRUE(P[2].visible);
  const double dx = P[2].u - (std::floor(P[2].u) + 2.5), dy = P[2].v - (std::floor(P[2].v) + 0.5);
  const double sigma = 0.5 * (P[2].conic[0] * dx * dx + P[2].conic[2] * dy * dy) + P[2].conic[1] * dx * dy;
  s.g.opacities[2] = std::exp(sigma) / 255;
  ASSERT_LT(s.g.opacities[2], 0.99);
  const OutputGrads og = random_output_grads(118, s.cam, kAll);
  const RefGrads grads = render_backward(s.g, s.cam, s.settings, og);
  auto f = [&] { return render(s.g, s.cam, s.settings); };
  auto dec = [&] { return discrete_decisions(s.g, s.cam, s.settings); };
  const Report r = check_array("opacities", s.g.opacities, grads.opacities, og, f, dec);
  print(r);
  EXPECT_EQ(r.skipped, 1);
  EXPECT_EQ(r.checked, 5);
  EXPECT_LT(r.max_error, kTolerance);
  // Without the hook: the jump dominates the difference quotient.
  const double o = s.g.opacities[2], h = kRelStep;
  s.g.opacities[2] = o + h;
  const RefImages ip = render(s.g, s.cam, s.settings);
  s.g.opacities[2] = o - h;
  const RefImages im = render(s.g, s.cam, s.settings);
  const double fd = loss_difference(ip, im, og) / (2 * h);
  std::printf("  FD across the jump %g, analytic %g\n", fd, grads.opacities[2]);
  EXPECT_GT(std::abs(fd - grads.opacities[2]), 10 * std::abs(grads.opacities[2]));
}

TEST(ReferenceGradients, CheckerDetectsAWrongGradient) {
  // The checker itself must be able to fail: a 0.1% error in one entry is caught.
  Scene s = random_scene(12, 6, 1);
  const OutputGrads og = random_output_grads(112, s.cam, kAll);
  RefGrads grads = render_backward(s.g, s.cam, s.settings, og);
  size_t big = 0;
  for (size_t i = 0; i < grads.scales.size(); ++i)
    if (std::abs(grads.scales[i]) > std::abs(grads.scales[big])) big = i;
  grads.scales[big] *= 1.001;
  auto f = [&] { return render(s.g, s.cam, s.settings); };
  auto dec = [&] { return discrete_decisions(s.g, s.cam, s.settings); };
  const Report r = check_array("scales", s.g.scales, grads.scales, og, f, dec);
  EXPECT_GT(r.max_error, kTolerance);
  EXPECT_EQ(r.worst, big);
}

// ---------------------------------------------------------------------------
// Forward identities

TEST(ReferenceForward, DistortionAlphaAndColourIdentities) {
  // With the blended weights w_i and mapped depths m_i of each pixel (recovered
  // from a brute-force front-to-back pass over the projected Gaussians):
  //   distortion = sum_{i<j} w_i w_j (m_i - m_j)^2,  alpha = sum w_i = 1 - T,
  //   rgb = sum w_i c_i + T background.
  Scene s = random_scene(13, 10, 2);
  s.settings.background = {0.1f, 0.2f, 0.3f};
  const std::vector<RefProjected> P = project(s.g, s.cam, s.settings);
  const RefImages im = render(s.g, s.cam, s.settings);
  std::vector<int> order;
  for (size_t n = 0; n < P.size(); ++n)
    if (P[n].visible) order.push_back(static_cast<int>(n));
  std::sort(order.begin(), order.end(), [&](int a, int b) { return P[a].z < P[b].z; });
  const double fn = s.settings.dist_near, ff = s.settings.dist_far;
  int blended_total = 0;
  for (int j = 0; j < s.cam.height; ++j)
    for (int i = 0; i < s.cam.width; ++i) {
      std::vector<double> w, m;
      double T = 1, rgb[3] = {0, 0, 0};
      for (int id : order) {
        const RefProjected& g = P[id];
        const double dx = g.u - (i + 0.5), dy = g.v - (j + 0.5);
        const double sigma = 0.5 * (g.conic[0] * dx * dx + g.conic[2] * dy * dy) + g.conic[1] * dx * dy;
        const double alpha = std::min(0.99, g.opacity * std::exp(-sigma));
        if (sigma < 0 || alpha < 1.0 / 255) continue;
        if (T * (1 - alpha) < 1e-4) break;
        w.push_back(alpha * T);
        m.push_back(ff / (ff - fn) * (1 - fn / g.z));
        for (int c = 0; c < 3; ++c) rgb[c] += alpha * T * g.rgb[c];
        T *= 1 - alpha;
      }
      double dist = 0, wsum = 0;
      for (size_t a = 0; a < w.size(); ++a) {
        wsum += w[a];
        for (size_t b = a + 1; b < w.size(); ++b) dist += w[a] * w[b] * (m[a] - m[b]) * (m[a] - m[b]);
      }
      const size_t pix = static_cast<size_t>(j) * s.cam.width + i;
      blended_total += static_cast<int>(w.size());
      EXPECT_EQ(im.n_contrib[pix], static_cast<int>(w.size()));
      EXPECT_NEAR(im.distortion[pix], dist, 1e-12 * (1 + dist));
      EXPECT_NEAR(im.alpha[pix], wsum, 1e-12);
      EXPECT_NEAR(im.alpha[pix], 1 - T, 1e-12);
      for (int c = 0; c < 3; ++c) EXPECT_NEAR(im.rgb[3 * pix + c], rgb[c] + T * s.settings.background[c], 1e-12);
    }
  EXPECT_GT(blended_total, 0);
}

TEST(ReferenceForward, CulledGaussiansDoNotChangeTheImage) {
  Scene s = random_scene(14, 6, 1);
  const RefImages base = render(s.g, s.cam, s.settings);
  std::mt19937 rng(15);
  Scene t = s;
  // below the opacity threshold, behind the camera, NaN scale, zero quaternion
  add_gaussian(t, rng, Eigen::Vector3d(0, 0, 3), 0.3, 0.5 / 255);
  add_gaussian(t, rng, Eigen::Vector3d(0, 0, -3), 0.3, 0.5);
  add_gaussian(t, rng, Eigen::Vector3d(0, 0, 3), 0.3, 0.5);
  t.g.scales[3 * 8] = std::nan("");
  add_gaussian(t, rng, Eigen::Vector3d(0, 0, 3), 0.3, 0.5);
  for (int c = 0; c < 4; ++c) t.g.quats[4 * 9 + c] = 0;
  // far outside the view
  add_gaussian(t, rng, Eigen::Vector3d(30, 0, 3), 0.1, 0.5);
  const RefImages im = render(t.g, t.cam, t.settings);
  for (size_t n = 6; n < 11; ++n) EXPECT_EQ(im.radii[n], 0) << n;
  EXPECT_EQ(im.rgb, base.rgb);
  EXPECT_EQ(im.depth, base.depth);
  EXPECT_EQ(im.distortion, base.distortion);
  const RefGrads grads = render_backward(t.g, t.cam, t.settings, random_output_grads(115, t.cam, kAll));
  for (size_t n = 6; n < 11; ++n) EXPECT_EQ(grads.opacities[n], 0.0);
}

TEST(ReferenceForward, ZeroGaussiansGiveBackground) {
  Scene s = random_scene(16, 0, 0);
  s.settings.background = {0.25f, 0.5f, 0.75f};
  const RefImages im = render(s.g, s.cam, s.settings);
  ASSERT_EQ(im.rgb.size(), 3u * 24 * 18);
  for (size_t p = 0; p < im.alpha.size(); ++p) {
    EXPECT_EQ(im.alpha[p], 0.0);
    for (int c = 0; c < 3; ++c) EXPECT_EQ(im.rgb[3 * p + c], s.settings.background[c]);
  }
}

TEST(ReferenceForward, FloatOverloadsMatchDouble) {
  Scene s = random_scene(17, 5, 2);
  GaussianSet set;
  set.sh_degree = s.g.sh_degree;
  auto to_float = [](const std::vector<double>& v) { return std::vector<float>(v.begin(), v.end()); };
  set.means = to_float(s.g.means);
  set.scales = to_float(s.g.scales);
  set.quats = to_float(s.g.quats);
  set.opacities = to_float(s.g.opacities);
  set.sh = to_float(s.g.sh);
  set.features = to_float(s.g.features);
  const RefGaussians g = to_double(set);
  EXPECT_EQ(render(set, s.cam, s.settings).rgb, render(g, s.cam, s.settings).rgb);
  const OutputGrads og = random_output_grads(117, s.cam, kAll);
  EXPECT_EQ(render_backward(set, s.cam, s.settings, og).means, render_backward(g, s.cam, s.settings, og).means);
}

}  // namespace
}  // namespace ag2gs::ref
