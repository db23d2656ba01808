// The device mask losses (L_is, L_ic, host/losses/mask_loss.h) against the
// double-precision reference (tests/reference/mask_loss_reference.h), whose
// analytic gradients are themselves checked against central finite
// differences away from the kinks of |.|.
//
// Tolerances, measured on PoCL (float32 sums; the tests print the errors),
// with test features kept kKinkMargin away from the kinks of |.| so float and
// double agree on every sign:
//   l_is, l_ic: |dev - ref| <= kLossTol * max(|ref|, 1e-3)   (worst measured 1.1e-7)
//   gradients: |dev - ref| <= kGradTol * max|ref| per case    (worst measured
//     1.3e-7 for the feature, 1.6e-7 for alpha)
//   reference vs central finite differences (step 1e-6):
//     kFdTol * max|grad| + 1e-9                               (worst measured 1.8e-10 absolute)
#include <gtest/gtest.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <random>
#include <vector>

#include "host/losses/mask_loss.h"
#include "tests/reference/mask_loss_reference.h"
#include "tests/test_util.h"

namespace ag2gs {
namespace {

constexpr double kLossTol = 2e-6;
constexpr double kGradTol = 2e-6;
constexpr double kFdTol = 1e-6;
constexpr double kKinkMargin = 1e-4;  // test features stay this far from |.|'s kinks

double max_abs(const std::vector<double>& v) {
  double m = 0;
  for (double x : v) m = std::max(m, std::abs(x));
  return m;
}

// Label maps: layer 0 a Voronoi partition of the image into the first masks
// with some background (-1); layer 1 (when present) a coarser partition into
// the remaining masks, overlapping layer 0's.
ViewMasks make_masks(int w, int h, int count, int layers, uint32_t seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(0, 1);
  ViewMasks m;
  m.width = w;
  m.height = h;
  m.layers = count == 0 ? std::max(layers, 0) : layers;
  m.count = count;
  const size_t npix = static_cast<size_t>(w) * h;
  m.labels.assign(npix * m.layers, -1);
  if (count == 0 || layers == 0) return m;
  const int first = layers == 1 ? count : std::max(1, (count + 1) / 2);
  for (int l = 0; l < layers; ++l) {
    const int lo = l == 0 ? 0 : first, hi = l == 0 ? first : count;
    if (hi <= lo) continue;
    std::vector<double> sx, sy;
    for (int j = lo; j < hi; ++j) {
      sx.push_back(u(rng) * w);
      sy.push_back(u(rng) * h);
    }
    for (int y = 0; y < h; ++y)
      for (int x = 0; x < w; ++x) {
        int best = 0;
        double bd = 1e30;
        for (size_t k = 0; k < sx.size(); ++k) {
          const double d = (x + 0.5 - sx[k]) * (x + 0.5 - sx[k]) + (y + 0.5 - sy[k]) * (y + 0.5 - sy[k]);
          if (d < bd) bd = d, best = static_cast<int>(k);
        }
        const double background = l == 0 ? 0.15 : 0.4;
        m.labels[static_cast<size_t>(l) * npix + static_cast<size_t>(y) * w + x] = u(rng) < background ? -1 : lo + best;
      }
  }
  return m;
}

// G (the normalised feature) per pixel: a colour per layer-0 mask plus noise,
// pushed until every value lies kKinkMargin away from the means of its masks
// (over the pixels that `alpha`, when given, keeps). Values equal to their
// mean (masks of one pixel) stay: their difference is exactly 0 in float too.
std::vector<double> make_g(const ViewMasks& m, uint32_t seed, const std::vector<float>* alpha = nullptr) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(0, 1);
  const size_t npix = static_cast<size_t>(m.width) * m.height;
  std::vector<double> base(static_cast<size_t>(std::max(m.count, 1)) * 3);
  for (double& b : base) b = u(rng) * 2 - 1;
  std::vector<double> g(npix * 3);
  for (size_t p = 0; p < npix; ++p) {
    const int j = m.layers > 0 ? m.labels[p] : -1;
    for (int c = 0; c < 3; ++c) g[p * 3 + c] = (j >= 0 ? base[j * 3 + c] : 0.3) + 0.4 * (u(rng) - 0.5);
  }
  // Validity only (G itself is what the reference sees with alpha 1).
  std::vector<double> keep(npix, 1.0);
  if (alpha)
    for (size_t p = 0; p < npix; ++p) keep[p] = (*alpha)[p] >= kMaskAlphaMin ? 1.0 : 0.0;
  for (int iter = 0; iter < 20; ++iter) {
    auto r = ref::mask_loss(g, &keep, m.labels, m.layers, m.count, m.width, m.height, false);
    bool moved = false;
    for (size_t p = 0; p < npix; ++p)
      for (int l = 0; l < m.layers && keep[p] > 0; ++l) {
        const int j = m.labels[static_cast<size_t>(l) * npix + p];
        if (j < 0) continue;
        for (int c = 0; c < 3; ++c) {
          const double d = g[p * 3 + c] - r.means[j * 3 + c];
          if (d != 0 && std::abs(d) < kKinkMargin) {
            g[p * 3 + c] += 3 * kKinkMargin;
            moved = true;
          }
        }
      }
    if (!moved) break;
  }
  return g;
}

// Alpha in [0.2, 1] with about a tenth of the pixels below the threshold
// (in [0, 0.08]): excluded.
std::vector<float> make_alpha(size_t npix, uint32_t seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<float> u(0, 1);
  std::vector<float> a(npix);
  for (float& v : a) v = u(rng) < 0.1f ? 0.08f * u(rng) : 0.2f + 0.8f * u(rng);
  return a;
}

std::vector<float> to_planar(const std::vector<float>& v, size_t npix) {
  std::vector<float> out(v.size());
  for (size_t p = 0; p < npix; ++p)
    for (int c = 0; c < 3; ++c) out[c * npix + p] = v[p * 3 + c];
  return out;
}
std::vector<float> from_planar(const std::vector<float>& v, size_t npix) {
  std::vector<float> out(v.size());
  for (size_t p = 0; p < npix; ++p)
    for (int c = 0; c < 3; ++c) out[p * 3 + c] = v[c * npix + p];
  return out;
}

struct Case {
  int w, h, count, layers;
  bool planar, with_alpha;
  uint32_t seed;
};

struct Errors {
  double loss = 0, grad = 0, grad_alpha = 0;
};
Errors g_worst;

void check_case(const Case& k, MaskLoss& loss, float w_is = 2.5f, float w_ic = 0.25f) {
  const ViewMasks masks = make_masks(k.w, k.h, k.count, k.layers, k.seed);
  const size_t npix = static_cast<size_t>(k.w) * k.h;
  std::vector<float> alpha = make_alpha(npix, k.seed + 2);
  const std::vector<double> g = make_g(masks, k.seed + 1, k.with_alpha ? &alpha : nullptr);
  std::vector<float> feature(npix * 3);
  for (size_t p = 0; p < npix; ++p)
    for (int c = 0; c < 3; ++c) feature[p * 3 + c] = static_cast<float>(g[p * 3 + c] * (k.with_alpha ? alpha[p] : 1.0));
  const std::vector<float>* ap = k.with_alpha ? &alpha : nullptr;

  loss.set_masks(masks);
  std::vector<float> gf, ga;
  const ImageLayout layout = k.planar ? ImageLayout::kPlanar : ImageLayout::kInterleaved;
  MaskLossResult d =
      loss.forward_backward(k.planar ? to_planar(feature, npix) : feature, ap, k.w, k.h, w_is, w_ic, &gf, &ga, layout);
  if (k.planar) gf = from_planar(gf, npix);
  auto r = ref::mask_loss(feature, ap, masks.labels, masks.layers, masks.count, k.w, k.h, true);

  std::vector<double> rg(npix * 3), ra(npix);
  for (size_t i = 0; i < rg.size(); ++i) rg[i] = w_is * r.grad_is[i] + w_ic * r.grad_ic[i];
  for (size_t i = 0; i < ra.size(); ++i) ra[i] = w_is * r.grad_alpha_is[i] + w_ic * r.grad_alpha_ic[i];
  const double e_is = std::abs(d.l_is - r.l_is), e_ic = std::abs(d.l_ic - r.l_ic);
  const double gscale = max_abs(rg), ascale = max_abs(ra);
  auto cg = test::compare(gf, rg, kGradTol * gscale, 0.0);
  auto ca = test::compare(ga, ra, kGradTol * ascale, 0.0);
  std::printf(
      "  %3dx%-3d masks %2d/%2d layers %d %s%s  l_is %.6f (err %.2g) l_ic %.6f (err %.2g)  grad err %.2g of %.3g  "
      "alpha grad err %.2g of %.3g  margins %.2g %.2g\n",
      k.w, k.h, d.masks, k.count, k.layers, k.planar ? "planar" : "interl", k.with_alpha ? " alpha" : "", d.l_is, e_is,
      d.l_ic, e_ic, gscale > 0 ? cg.max_abs / gscale : cg.max_abs, gscale,
      ascale > 0 ? ca.max_abs / ascale : ca.max_abs, ascale, r.margin_is, r.margin_ic);
  EXPECT_EQ(d.masks, r.masks);
  EXPECT_EQ(d.mask_pixels, r.mask_pixels);
  EXPECT_LE(e_is, kLossTol * std::max(r.l_is, 1e-3));
  EXPECT_LE(e_ic, kLossTol * std::max(r.l_ic, 1e-3));
  EXPECT_EQ(cg.violations, 0u);
  EXPECT_EQ(ca.violations, 0u);
  EXPECT_EQ(cg.nan_mismatch + ca.nan_mismatch, 0u);
  EXPECT_TRUE(test::all_finite(gf));
  EXPECT_TRUE(test::all_finite(ga));
  g_worst.loss = std::max({g_worst.loss, e_is / std::max(r.l_is, 1e-3), e_ic / std::max(r.l_ic, 1e-3)});
  if (gscale > 0) g_worst.grad = std::max(g_worst.grad, cg.max_abs / gscale);
  if (ascale > 0) g_worst.grad_alpha = std::max(g_worst.grad_alpha, ca.max_abs / ascale);
}

// ---------------------------------------------------------------- reference

// Central differences of l_is and l_ic of the reference in every feature and
// alpha value (alpha at excluded pixels is left alone: a step there).
void check_reference_fd(int w, int h, int count, int layers, bool with_alpha, uint32_t seed) {
  const ViewMasks m = make_masks(w, h, count, layers, seed);
  const size_t npix = static_cast<size_t>(w) * h;
  const std::vector<float> af = make_alpha(npix, seed + 2);
  const std::vector<double> g = make_g(m, seed + 1, with_alpha ? &af : nullptr);
  std::vector<double> alpha(af.begin(), af.end()), f(npix * 3);
  for (size_t p = 0; p < npix; ++p)
    for (int c = 0; c < 3; ++c) f[p * 3 + c] = g[p * 3 + c] * (with_alpha ? alpha[p] : 1.0);
  const std::vector<double>* ap = with_alpha ? &alpha : nullptr;
  const auto r = ref::mask_loss(f, ap, m.labels, m.layers, m.count, w, h, true);
  const double step = 1e-6;
  ASSERT_GT(r.margin_is, 20 * step);
  ASSERT_GT(r.margin_ic, 20 * step);
  auto eval = [&](const std::vector<double>& ff, const std::vector<double>& aa) {
    return ref::mask_loss(ff, with_alpha ? &aa : nullptr, m.labels, m.layers, m.count, w, h, false);
  };
  double worst_is = 0, worst_ic = 0;
  for (size_t i = 0; i < f.size(); ++i) {
    auto fp = f, fm = f;
    fp[i] += step;
    fm[i] -= step;
    const auto a = eval(fp, alpha), b = eval(fm, alpha);
    worst_is = std::max(worst_is, std::abs((a.l_is - b.l_is) / (2 * step) - r.grad_is[i]));
    worst_ic = std::max(worst_ic, std::abs((a.l_ic - b.l_ic) / (2 * step) - r.grad_ic[i]));
  }
  double worst_a = 0;
  if (with_alpha)
    for (size_t p = 0; p < npix; ++p) {
      if (!(alpha[p] >= 0.1)) continue;
      auto ap2 = alpha, am = alpha;
      ap2[p] += step;
      am[p] -= step;
      const auto a = eval(f, ap2), b = eval(f, am);
      worst_a = std::max(worst_a, std::abs((a.l_is - b.l_is) / (2 * step) - r.grad_alpha_is[p]));
      worst_a = std::max(worst_a, std::abs((a.l_ic - b.l_ic) / (2 * step) - r.grad_alpha_ic[p]));
    }
  const double s_is = max_abs(r.grad_is), s_ic = max_abs(r.grad_ic);
  const double s_a = std::max(max_abs(r.grad_alpha_is), max_abs(r.grad_alpha_ic));
  std::printf(
      "%dx%d masks %d layers %d%s: l_is %.4f l_ic %.4f  fd errors: is %.2g (of %.3g) ic %.2g (of %.3g)"
      " alpha %.2g (of %.3g)\n",
      w, h, count, layers, with_alpha ? " alpha" : "", r.l_is, r.l_ic, worst_is, s_is, worst_ic, s_ic, worst_a, s_a);
  EXPECT_LE(worst_is, kFdTol * s_is + 1e-9);
  EXPECT_LE(worst_ic, kFdTol * s_ic + 1e-9);
  EXPECT_LE(worst_a, kFdTol * s_a + 1e-9);
  EXPECT_GT(r.l_ic, 0.0);
}

TEST(MaskLossReference, GradientMatchesFiniteDifferences) {
  check_reference_fd(7, 5, 3, 1, false, 1);
  check_reference_fd(9, 7, 5, 2, false, 2);
  check_reference_fd(8, 6, 4, 2, true, 3);
  check_reference_fd(6, 6, 2, 1, true, 4);
}

// Constant features on each mask: L_is = 0 and no L_is gradient; two masks
// whose constants are d apart (L1) give L_ic = 1 / (d + 1).
TEST(MaskLossReference, Identities) {
  const int w = 10, h = 6;
  ViewMasks m = make_masks(w, h, 2, 1, 5);
  std::vector<double> f(w * h * 3);
  for (int p = 0; p < w * h; ++p)
    for (int c = 0; c < 3; ++c) f[p * 3 + c] = m.labels[p] == 1 ? 0.5 + 0.1 * c : 0.25;
  auto r = ref::mask_loss(f, nullptr, m.labels, 1, 2, w, h, true);
  EXPECT_EQ(r.masks, 2);
  EXPECT_LE(r.l_is, 1e-15);
  EXPECT_NEAR(r.l_ic, 1.0 / (0.25 + 0.35 + 0.45 + 1.0), 1e-14);
  EXPECT_LE(max_abs(r.grad_is), 1e-15);
}

// ---------------------------------------------------------------- device

TEST(MaskLoss, MatchesReference) {
  const int sizes[][2] = {{1, 1}, {7, 5}, {17, 9}, {64, 48}, {160, 120}};
  const int counts[] = {0, 1, 2, 5, 40};
  MaskLoss loss(test::runtime());
  uint32_t seed = 100;
  int variant = 0;
  for (auto& s : sizes)
    for (int count : counts)
      for (int layers = 1; layers <= 2; ++layers, ++variant)
        check_case({s[0], s[1], count, layers, variant % 2 == 1, variant % 3 == 0, seed += 10}, loss);
  std::printf("worst: loss %.2g (relative)  grad %.2g  alpha grad %.2g (of the largest entry)\n", g_worst.loss,
              g_worst.grad, g_worst.grad_alpha);
}

// Another device's configuration: one entry per work-item, 64-wide groups
// (chunks of 64 mask pixels), and a mid configuration.
TEST(MaskLoss, OtherWorkSplits) {
  for (MaskLossOptions opt : {MaskLossOptions{64, 1}, MaskLossOptions{32, 4}}) {
    if (static_cast<size_t>(opt.work_group) > test::runtime().info().max_work_group) continue;
    MaskLoss loss(test::runtime(), opt);
    check_case({64, 48, 40, 2, true, true, 7}, loss);
    check_case({37, 23, 5, 1, false, false, 8}, loss);
  }
}

// A training-size view (many masks, two layers, masks of thousands of
// pixels split over several chunks): the same precision, and the time of one
// call (printed: 23-37 ms on the shared 2-core PoCL machine, split about
// evenly between the two gathers and the gradient pass).
TEST(MaskLoss, TrainingSizeView) {
  MaskLoss loss(test::runtime());
  check_case({640, 480, 150, 2, true, true, 71}, loss);
  const int w = 640, h = 480;
  const size_t npix = static_cast<size_t>(w) * h;
  Runtime& rt = test::runtime();
  DeviceBuffer fb(&rt), ab(&rt), gf(&rt), ga(&rt);
  std::vector<float> f(npix * 3);
  for (size_t i = 0; i < f.size(); ++i) f[i] = 0.001f * static_cast<float>(i % 1009);
  fb.upload(f);
  ab.upload(make_alpha(npix, 72));
  double best = 1e30;
  for (int rep = 0; rep < 5; ++rep) {
    const auto t0 = std::chrono::steady_clock::now();
    loss.forward_backward(fb, &ab, w, h, ImageLayout::kPlanar, 2.5f, 0.25f, &gf, &ga);
    best = std::min(best, std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count());
  }
  std::printf("  640x480, 150 masks, 2 layers: %.2f ms per forward_backward\n", best);
  rt.set_profiling(true);
  rt.take_timings();
  loss.forward_backward(fb, &ab, w, h, ImageLayout::kPlanar, 2.5f, 0.25f, &gf, &ga);
  for (auto& [name, ms] : rt.take_timings()) std::printf("    %-16s %.3f ms\n", name.c_str(), ms);
  rt.set_profiling(false);
}

// The loss weights only scale the two gradients.
TEST(MaskLoss, Weights) {
  MaskLoss loss(test::runtime());
  check_case({33, 20, 6, 2, false, true, 9}, loss, 1.f, 0.f);
  check_case({33, 20, 6, 2, false, true, 9}, loss, 0.f, 1.f);
  check_case({33, 20, 6, 2, true, false, 9}, loss, 0.1f, 3.f);
}

TEST(MaskLoss, ConstantMasksHaveNoInternalLoss) {
  // Constants with short mantissas: the float sums and means are exact, so
  // G - Gbar is exactly 0 and sign(0) = 0 leaves only the L_ic gradient.
  const int w = 50, h = 30;
  ViewMasks m = make_masks(w, h, 6, 1, 11);
  std::vector<float> f(w * h * 3);
  for (int p = 0; p < w * h; ++p)
    for (int c = 0; c < 3; ++c) f[p * 3 + c] = m.labels[p] < 0 ? 0.1f * p : 0.125f * (m.labels[p] + 1) + 0.25f * c;
  MaskLoss loss(test::runtime());
  loss.set_masks(m);
  std::vector<float> g_is, g_ic;
  auto r = loss.forward_backward(f, nullptr, w, h, 1.f, 0.f, &g_is);
  EXPECT_EQ(r.l_is, 0.0);
  EXPECT_GT(r.l_ic, 0.0);
  for (float v : g_is) ASSERT_EQ(v, 0.f);
  loss.forward_backward(f, nullptr, w, h, 0.f, 1.f, &g_ic);
  auto ref = ref::mask_loss(f, nullptr, m.labels, 1, 6, w, h, true);
  auto c = test::compare(g_ic, ref.grad_ic, kGradTol * max_abs(ref.grad_ic), 0.0);
  EXPECT_EQ(c.violations, 0u);
  EXPECT_NEAR(r.l_ic, ref.l_ic, kLossTol * ref.l_ic);
}

TEST(MaskLoss, ContrastDecreasesAsMeansMoveApart) {
  const int w = 24, h = 16;
  ViewMasks m;
  m.width = w;
  m.height = h;
  m.layers = 1;
  m.count = 2;
  m.labels.assign(w * h, -1);
  for (int y = 2; y < 14; ++y)
    for (int x = 1; x < 23; ++x) m.labels[y * w + x] = x < 12 ? 0 : 1;
  MaskLoss loss(test::runtime());
  loss.set_masks(m);
  double last = 2;
  for (int step = 0; step <= 8; ++step) {
    const float t = 0.25f * step;
    std::vector<float> f(w * h * 3, 0.5f);
    for (int p = 0; p < w * h; ++p)
      if (m.labels[p] == 1) f[p * 3] = 0.5f + t;  // mask 1's mean moves away along channel 0
    auto r = loss.forward_backward(f, nullptr, w, h, 1.f, 1.f, nullptr);
    std::printf("  distance %.2f  l_ic %.6f\n", t, r.l_ic);
    EXPECT_NEAR(r.l_ic, 1.0 / (t + 1.0), 1e-6);
    EXPECT_LT(r.l_ic, last);
    last = r.l_ic;
  }
}

// Degenerate views: zero loss and zero gradients, never NaN (the test builds
// fill fresh device buffers with NaN, so unwritten outputs would show).
TEST(MaskLoss, DegenerateViews) {
  const int w = 19, h = 11;
  const size_t npix = static_cast<size_t>(w) * h;
  std::vector<float> f(npix * 3);
  for (size_t i = 0; i < f.size(); ++i) f[i] = 0.01f * static_cast<float>(i % 97);
  MaskLoss loss(test::runtime());
  std::vector<float> gf, ga;
  auto all_zero = [](const std::vector<float>& v) {
    for (float x : v)
      if (x != 0.f) return false;
    return true;
  };
  {  // no masks at all: zero layers, and one layer of -1
    for (int layers : {0, 1}) {
      ViewMasks m;
      m.width = w;
      m.height = h;
      m.layers = layers;
      m.labels.assign(npix * layers, -1);
      loss.set_masks(m);
      auto r = loss.forward_backward(f, nullptr, w, h, 1.f, 1.f, &gf, &ga);
      EXPECT_EQ(r.l_is, 0.0);
      EXPECT_EQ(r.l_ic, 0.0);
      EXPECT_EQ(r.masks, 0);
      EXPECT_TRUE(all_zero(gf));
      EXPECT_TRUE(all_zero(ga));
    }
  }
  {  // one mask: L_ic = 0 with zero gradient; empty masks are ignored
    ViewMasks m = make_masks(w, h, 1, 1, 21);
    m.count = 4;  // masks 1..3 have no pixel
    loss.set_masks(m);
    auto r = loss.forward_backward(f, nullptr, w, h, 0.f, 1.f, &gf);
    EXPECT_EQ(r.masks, 1);
    EXPECT_EQ(r.l_ic, 0.0);
    EXPECT_GT(r.l_is, 0.0);
    EXPECT_TRUE(all_zero(gf));
    auto ref = ref::mask_loss(f, nullptr, m.labels, 1, 4, w, h, false);
    EXPECT_NEAR(r.l_is, ref.l_is, kLossTol * ref.l_is);
  }
  {  // a mask whose pixels all have alpha < 0.1 is absent: 2 masks -> m = 1
    ViewMasks m = make_masks(w, h, 2, 1, 22);
    std::vector<float> alpha(npix, 0.5f);
    for (size_t p = 0; p < npix; ++p)
      if (m.labels[p] == 1) alpha[p] = 0.05f;
    loss.set_masks(m);
    auto r = loss.forward_backward(f, &alpha, w, h, 0.f, 1.f, &gf, &ga);
    EXPECT_EQ(r.masks, 1);
    EXPECT_EQ(r.l_ic, 0.0);
    EXPECT_TRUE(all_zero(gf));
    EXPECT_TRUE(all_zero(ga));
    // Everything excluded: no mask at all.
    std::vector<float> low(npix, 0.f);
    r = loss.forward_backward(f, &low, w, h, 1.f, 1.f, &gf, &ga);
    EXPECT_EQ(r.masks, 0);
    EXPECT_EQ(r.mask_pixels, 0);
    EXPECT_EQ(r.l_is, 0.0);
    EXPECT_TRUE(all_zero(gf));
    EXPECT_TRUE(all_zero(ga));
  }
}

// normalise_by_alpha: alpha = 1 is the plain loss bit for bit; F s with alpha
// s is the loss of F; excluded pixels get no gradient; the alpha gradient
// matches the reference (also in check_case).
TEST(MaskLoss, AlphaNormalisation) {
  const int w = 40, h = 27;
  const size_t npix = static_cast<size_t>(w) * h;
  ViewMasks m = make_masks(w, h, 7, 2, 31);
  const std::vector<double> g = make_g(m, 32);
  std::vector<float> f(g.begin(), g.end());
  MaskLoss loss(test::runtime());
  loss.set_masks(m);
  std::vector<float> g0, g1, ga;
  auto r0 = loss.forward_backward(f, nullptr, w, h, 2.5f, 0.25f, &g0);
  std::vector<float> ones(npix, 1.f);
  auto r1 = loss.forward_backward(f, &ones, w, h, 2.5f, 0.25f, &g1, &ga);
  EXPECT_EQ(r0.l_is, r1.l_is);
  EXPECT_EQ(r0.l_ic, r1.l_ic);
  EXPECT_EQ(test::hash_vec(g0), test::hash_vec(g1));
  // Scaled: F s / s = F up to rounding.
  const std::vector<float> alpha = make_alpha(npix, 33);
  std::vector<float> fs(f.size());
  for (size_t p = 0; p < npix; ++p)
    for (int c = 0; c < 3; ++c) fs[p * 3 + c] = f[p * 3 + c] * std::max(alpha[p], 0.1f);
  std::vector<float> clamped(alpha);
  for (float& a : clamped) a = std::max(a, 0.1f);  // keep every pixel
  auto rs = loss.forward_backward(fs, &clamped, w, h, 2.5f, 0.25f, &g1, &ga);
  EXPECT_NEAR(rs.l_is, r0.l_is, 1e-5 * r0.l_is);
  EXPECT_NEAR(rs.l_ic, r0.l_ic, 1e-5 * r0.l_ic);
  // Excluded pixels: zero gradients.
  loss.forward_backward(fs, &alpha, w, h, 2.5f, 0.25f, &g1, &ga);
  for (size_t p = 0; p < npix; ++p)
    if (alpha[p] < 0.1f) {
      ASSERT_EQ(ga[p], 0.f);
      for (int c = 0; c < 3; ++c) ASSERT_EQ(g1[p * 3 + c], 0.f);
    }
  check_case({40, 27, 7, 2, false, true, 34}, loss);
}

TEST(MaskLoss, Deterministic) {
  const int w = 97, h = 61;
  const size_t npix = static_cast<size_t>(w) * h;
  ViewMasks m = make_masks(w, h, 30, 2, 41);
  const std::vector<float> alpha = make_alpha(npix, 43);
  const std::vector<double> g = make_g(m, 42, &alpha);
  std::vector<float> f(g.begin(), g.end());
  MaskLoss a(test::runtime()), b(test::runtime());
  a.set_masks(m);
  b.set_masks(m);
  std::vector<float> fa, fb, aa, ab;
  auto ra = a.forward_backward(f, &alpha, w, h, 2.5f, 0.25f, &fa, &aa);
  auto rb = b.forward_backward(f, &alpha, w, h, 2.5f, 0.25f, &fb, &ab);
  EXPECT_EQ(ra.l_is, rb.l_is);
  EXPECT_EQ(ra.l_ic, rb.l_ic);
  EXPECT_EQ(test::hash_vec(fa), test::hash_vec(fb));
  EXPECT_EQ(test::hash_vec(aa), test::hash_vec(ab));
  auto rc = a.forward_backward(f, &alpha, w, h, 2.5f, 0.25f, &fb, &ab);
  EXPECT_EQ(ra.l_is, rc.l_is);
  EXPECT_EQ(ra.l_ic, rc.l_ic);
  EXPECT_EQ(test::hash_vec(fa), test::hash_vec(fb));
  EXPECT_EQ(test::hash_vec(aa), test::hash_vec(ab));
}

// The device API with planar buffers, as the trainer calls it, and the
// per-view upload cache.
TEST(MaskLoss, DeviceApiAndMaskCache) {
  const int w = 41, h = 26;
  const size_t npix = static_cast<size_t>(w) * h;
  ViewMasks m = make_masks(w, h, 9, 1, 51);
  const std::vector<double> g = make_g(m, 52);
  std::vector<float> f(g.begin(), g.end());
  const std::vector<float> alpha = make_alpha(npix, 53);
  Runtime& rt = test::runtime();
  DeviceBuffer fb(&rt), ab(&rt), gf(&rt), ga(&rt);
  fb.upload(to_planar(f, npix));
  ab.upload(alpha);
  MaskLoss loss(rt);
  EXPECT_TRUE(loss.set_masks(m, 3));
  EXPECT_FALSE(loss.set_masks(m, 3));
  EXPECT_EQ(loss.masks_key(), 3);
  auto rd = loss.forward_backward(fb, &ab, w, h, ImageLayout::kPlanar, 2.5f, 0.25f, &gf, &ga);
  std::vector<float> gp, gap, gi, gai;
  gf.download(gp, npix * 3);
  ga.download(gap, npix);
  auto rh = loss.forward_backward(f, &alpha, w, h, 2.5f, 0.25f, &gi, &gai);
  EXPECT_EQ(rd.l_is, rh.l_is);
  EXPECT_EQ(rd.l_ic, rh.l_ic);
  EXPECT_EQ(test::hash_vec(gp), test::hash_vec(to_planar(gi, npix)));
  EXPECT_EQ(test::hash_vec(gap), test::hash_vec(gai));
  // Forward only, and an alpha gradient without a feature gradient.
  auto rf = loss.forward_backward(fb, &ab, w, h, ImageLayout::kPlanar, 2.5f, 0.25f, nullptr);
  EXPECT_EQ(rf.l_is, rd.l_is);
  loss.forward_backward(fb, &ab, w, h, ImageLayout::kPlanar, 2.5f, 0.25f, nullptr, &ga);
  ga.download(gap, npix);
  EXPECT_EQ(test::hash_vec(gap), test::hash_vec(gai));
  // enqueue() then result(): the same as forward_backward().
  loss.enqueue(fb, &ab, w, h, ImageLayout::kPlanar, 2.5f, 0.25f, &gf, &ga);
  auto re = loss.result();
  EXPECT_EQ(re.l_is, rd.l_is);
  EXPECT_EQ(re.l_ic, rd.l_ic);
  EXPECT_EQ(re.masks, rd.masks);
  // Another view under another key is uploaded.
  ViewMasks other = make_masks(w, h, 4, 1, 54);
  EXPECT_TRUE(loss.set_masks(other, 4));
  EXPECT_EQ(loss.mask_count(), 4);
  EXPECT_TRUE(loss.set_masks(other));  // key -1: always
}

TEST(MaskLoss, UnmaskedPixelsBecomeOneMoreMask) {
  // 4x2, two layers: pixel 0 in mask 0 (layer 0), pixel 1 in mask 1 (layer 1
  // only), pixels 2..7 uncovered except pixel 5 (mask 0, layer 1).
  ViewMasks m;
  m.width = 4;
  m.height = 2;
  m.layers = 2;
  m.count = 2;
  m.labels = {0,  -1, -1, -1, -1, -1, -1, -1,   // layer 0
              -1, 1,  -1, -1, -1, 0,  -1, -1};  // layer 1
  m.pixels = {2, 1};
  m.feature_dim = 2;
  m.features = {1, 2, 3, 4};
  const ViewMasks u = with_unmasked_group(m);
  EXPECT_EQ(u.count, 3);
  EXPECT_EQ(u.pixels, (std::vector<int64_t>{2, 1, 5}));
  EXPECT_EQ(u.labels, (std::vector<int32_t>{0, -1, 2, 2, 2, -1, 2, 2,  //
                                            -1, 1, -1, -1, -1, 0, -1, -1}));
  EXPECT_EQ(u.features, (std::vector<float>{1, 2, 3, 4, 0, 0}));
  // Every pixel covered: unchanged.
  ViewMasks full = m;
  full.layers = 1;
  full.labels = {0, 1, 0, 1, 0, 1, 0, 1};
  const ViewMasks same = with_unmasked_group(full);
  EXPECT_EQ(same.count, 2);
  EXPECT_EQ(same.labels, full.labels);
  // The loss accepts the result and counts the extra mask.
  MaskLoss loss(test::runtime());
  EXPECT_TRUE(loss.set_masks(u));
  EXPECT_EQ(loss.mask_count(), 3);
}

TEST(MaskLoss, RejectsBadArguments) {
  MaskLoss loss(test::runtime());
  std::vector<float> f(12 * 3), g;
  EXPECT_THROW(loss.forward_backward(f, nullptr, 4, 3, 1.f, 1.f, &g), std::logic_error);  // no masks yet
  ViewMasks m = make_masks(4, 3, 2, 1, 61);
  loss.set_masks(m);
  EXPECT_THROW(loss.forward_backward(f, nullptr, 4, 4, 1.f, 1.f, &g), std::invalid_argument);  // size
  EXPECT_THROW(loss.forward_backward(f, nullptr, 6, 2, 1.f, 1.f, &g), std::invalid_argument);  // not the masks'
  std::vector<float> short_alpha(5);
  EXPECT_THROW(loss.forward_backward(f, &short_alpha, 4, 3, 1.f, 1.f, &g), std::invalid_argument);
  ViewMasks bad = m;
  bad.labels[3] = 2;  // count is 2
  EXPECT_THROW(loss.set_masks(bad), std::invalid_argument);
  bad.labels[3] = -2;
  EXPECT_THROW(loss.set_masks(bad), std::invalid_argument);
  bad = m;
  bad.labels.pop_back();
  EXPECT_THROW(loss.set_masks(bad), std::invalid_argument);
  DeviceBuffer x(&test::runtime());
  x.upload(f);
  EXPECT_THROW(loss.forward_backward(x, nullptr, 4, 3, ImageLayout::kPlanar, 1.f, 1.f, &x), std::invalid_argument);
  EXPECT_THROW(MaskLoss(test::runtime()).result(), std::logic_error);
  EXPECT_THROW(MaskLoss(test::runtime(), MaskLossOptions{3, 0}), std::invalid_argument);
  EXPECT_THROW(MaskLoss(test::runtime(), MaskLossOptions{0, 3}), std::invalid_argument);
}

}  // namespace
}  // namespace ag2gs
