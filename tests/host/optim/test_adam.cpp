// Device Adam (host/optim/adam.h) against the double-precision reference of
// torch.optim.Adam's documented update (tests/reference/adam_reference.h), its
// sparse (visible-rows) variant, the non-finite gradient count, and the row
// gather/resize used when rows are added or removed.
//
// Tolerances, measured on PoCL: after 25 steps with learning rates up to
// 0.05, |dev - ref| <= kParamTol for parameters of magnitude <= 1 (worst
// measured 5.4e-7: float rounding of the parameter and of the update, a few
// ulp per step); exp_avg within kMomentTol of the element's gradient scale
// |m| + sqrt(vhat) (worst 6.4e-8; m is a signed sum and may cancel), exp_avg_sq
// within kMomentTol relative (worst 8e-7).
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>
#include <random>
#include <vector>

#include "host/optim/adam.h"
#include "tests/reference/adam_reference.h"
#include "tests/test_util.h"

namespace ag2gs {
namespace {

constexpr double kParamTol = 2e-6;
constexpr double kMomentTol = 2e-6;

std::vector<float> random_params(size_t n, uint32_t seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<float> u(-1.f, 1.f);
  std::vector<float> p(n);
  for (auto& v : p) v = u(rng);
  return p;
}

// Gradients over many magnitudes (1e-7 .. 10), both signs, some exact zeros.
std::vector<float> random_grads(size_t n, uint32_t seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(0, 1);
  std::normal_distribution<double> nrm(0, 1);
  std::vector<float> g(n);
  for (auto& v : g) v = u(rng) < 0.05 ? 0.f : static_cast<float>(nrm(rng) * std::pow(10.0, -7 + 8 * u(rng)));
  return g;
}

std::vector<double> to_double(const std::vector<float>& v) {
  return std::vector<double>(v.begin(), v.end());
}

void expect_close(const char* what, const std::vector<float>& dev, const std::vector<double>& ref, double abs_tol,
                  double rel_tol) {
  auto c = test::compare(dev, ref, abs_tol, rel_tol);
  std::printf("  %-10s max abs %.3g  max rel %.3g  violations %zu/%zu\n", what, c.max_abs, c.max_rel, c.violations,
              c.n);
  EXPECT_EQ(c.violations, 0u) << what;
  EXPECT_EQ(c.nan_mismatch, 0u) << what;
}

// One parameter group on the device and its reference twin.
struct Twin {
  Twin(Runtime& rt, const char* name, size_t rows, int row_size, uint32_t seed)
      : group(rt, name, rows, row_size), param(&rt), grad(&rt) {
    host = random_params(rows * row_size, seed);
    param.upload(host);
    ref_param = to_double(host);
  }
  void step(Adam& adam, double lr, uint32_t seed, const std::vector<int>* visible = nullptr,
            DeviceBuffer* visible_buf = nullptr) {
    auto g = random_grads(group.size(), seed);
    grad.upload(g);
    if (visible)
      adam.step_visible(group, param, grad, lr, *visible_buf);
    else
      adam.step(group, param, grad, lr);
    ref::adam_step(ref_param, to_double(g), ref_state, lr, 0.9, 0.999, 1e-15, visible, group.row_size());
  }
  void check() {
    std::vector<float> p, m, v;
    param.download(p, group.size());
    group.exp_avg().download(m, group.size());
    group.exp_avg_sq().download(v, group.size());
    std::printf(" group %s, step %lld\n", group.name().c_str(), static_cast<long long>(group.steps()));
    expect_close("param", p, ref_param, kParamTol, 0);
    // m is a signed sum and can cancel: its error is measured against the
    // element's gradient scale sqrt(vhat), v's against itself.
    const double bc2 = 1 - std::pow(0.999, static_cast<double>(ref_state.step));
    double worst_m = 0;
    for (size_t i = 0; i < m.size(); ++i) {
      const double scale = std::abs(ref_state.m[i]) + std::sqrt(ref_state.v[i] / bc2);
      if (scale > 0) worst_m = std::max(worst_m, std::abs(m[i] - ref_state.m[i]) / scale);
    }
    std::printf("  %-10s max error %.3g of the gradient scale\n", "exp_avg", worst_m);
    EXPECT_LE(worst_m, kMomentTol);
    expect_close("exp_avg_sq", v, ref_state.v, 1e-30, kMomentTol);
    EXPECT_EQ(group.steps(), ref_state.step);
  }
  AdamGroup group;
  DeviceBuffer param, grad;
  std::vector<float> host;
  std::vector<double> ref_param;
  ref::RefAdamState ref_state;
};

TEST(Adam, MatchesReferenceWithChangingLearningRates) {
  Runtime& rt = test::runtime();
  Adam adam(rt);
  // Two groups stepped in lockstep with their own schedules, sizes not
  // multiples of any work-group size.
  Twin offsets(rt, "offsets", 3337, 3, 1), opacity(rt, "opacity", 1001, 1, 2);
  for (int it = 0; it < 25; ++it) {
    const double lr_off = 1e-2 * std::pow(0.01, it / 24.0);  // exponential decay 1e-2 -> 1e-4
    const double lr_op = it < 10 ? 0.05 : 0.02;
    offsets.step(adam, lr_off, 100 + it);
    opacity.step(adam, lr_op, 200 + it);
  }
  offsets.check();
  opacity.check();
}

// torch's update in closed form: with a constant gradient, mhat = g and
// vhat = g^2 at every step, so each step moves a parameter by lr sign(g)
// (eps = 1e-15 is below float resolution here).
TEST(Adam, ConstantGradientMovesByLearningRate) {
  Runtime& rt = test::runtime();
  Adam adam(rt);
  AdamGroup group(rt, "p", 4, 1);
  DeviceBuffer param(&rt), grad(&rt);
  param.upload(std::vector<float>{1.f, 1.f, -2.f, 0.5f});
  grad.upload(std::vector<float>{0.5f, -3e-4f, 7.f, 0.f});
  const double lrs[3] = {0.1, 0.05, 0.025};
  for (double lr : lrs) adam.step(group, param, grad, lr);
  std::vector<float> p;
  param.download(p, 4);
  EXPECT_NEAR(p[0], 1.0 - 0.175, 1e-6);
  EXPECT_NEAR(p[1], 1.0 + 0.175, 1e-6);
  EXPECT_NEAR(p[2], -2.0 - 0.175, 1e-6);
  EXPECT_EQ(p[3], 0.5f);  // zero gradient: m = 0, no move
  EXPECT_EQ(group.steps(), 3);
}

TEST(Adam, VisibleRowsOnly) {
  Runtime& rt = test::runtime();
  Adam adam(rt);
  const size_t rows = 777;
  Twin scales(rt, "scales", rows, 3, 3);
  std::vector<int> visible(rows);
  DeviceBuffer vis(&rt);
  for (int it = 0; it < 6; ++it) {
    std::mt19937 rng(50 + it);
    for (auto& v : visible) v = rng() % 3 == 0 ? 0 : static_cast<int>(rng() % 40) + 1;  // radii-like
    vis.upload(visible);
    scales.step(adam, 5e-3, 300 + it, &visible, &vis);
  }
  scales.check();
  // A row never visible keeps its initial value bit for bit.
  std::vector<int> none(rows, 0);
  vis.upload(none);
  std::vector<float> before, after;
  scales.param.download(before, rows * 3);
  adam.step_visible(scales.group, scales.param, scales.grad, 1e-2, vis);
  scales.param.download(after, rows * 3);
  EXPECT_EQ(test::hash_vec(before), test::hash_vec(after));
}

// The trainer's SH rest group steps only the coefficients of the degrees
// switched on so far. Against full steps of the same gradients, where the
// columns past the prefix are zero until they switch on, every bit agrees:
// parameters, both moments and the step count.
TEST(Adam, ColumnPrefixStepsKeepTheBitsOfFullSteps) {
  Runtime& rt = test::runtime();
  Adam adam(rt);
  const size_t rows = 1237;
  const int row_size = 45;
  AdamGroup full(rt, "full", rows, row_size), cols(rt, "cols", rows, row_size);
  DeviceBuffer p_full(&rt), p_cols(&rt), grad(&rt);
  const std::vector<float> init = random_params(rows * row_size, 11);
  p_full.upload(init);
  p_cols.upload(init);
  const int prefixes[] = {0, 0, 9, 9, 24, 24, 45, 45};  // degrees 0, 1, 2, 3 (3 channels each)
  int it = 0;
  for (int prefix : prefixes) {
    std::vector<float> g = random_grads(rows * row_size, 400 + it++);
    for (size_t r = 0; r < rows; ++r)
      for (int c = prefix; c < row_size; ++c) g[r * row_size + c] = 0.f;
    grad.upload(g);
    adam.step(full, p_full, grad, 2.5e-3);
    adam.step_cols(cols, p_cols, grad, 2.5e-3, prefix);
  }
  std::vector<float> a, b;
  p_full.download(a, rows * row_size);
  p_cols.download(b, rows * row_size);
  EXPECT_EQ(test::hash_vec(a), test::hash_vec(b));
  EXPECT_NE(test::hash_vec(a), test::hash_vec(init));
  full.exp_avg().download(a, rows * row_size);
  cols.exp_avg().download(b, rows * row_size);
  EXPECT_EQ(test::hash_vec(a), test::hash_vec(b));
  full.exp_avg_sq().download(a, rows * row_size);
  cols.exp_avg_sq().download(b, rows * row_size);
  EXPECT_EQ(test::hash_vec(a), test::hash_vec(b));
  EXPECT_EQ(cols.steps(), 8);
  // Columns past the prefix are left alone even with a gradient there.
  std::vector<float> before, after;
  p_cols.download(before, rows * row_size);
  grad.upload(std::vector<float>(rows * row_size, 1.f));
  adam.step_cols(cols, p_cols, grad, 1e-2, 3);
  p_cols.download(after, rows * row_size);
  size_t moved = 0, moved_outside = 0;
  for (size_t i = 0; i < before.size(); ++i)
    if (before[i] != after[i]) (static_cast<int>(i % row_size) < 3 ? moved : moved_outside)++;
  EXPECT_EQ(moved, rows * 3);
  EXPECT_EQ(moved_outside, 0u);
  // The non-finite count over a prefix sees only the prefix.
  std::vector<float> bad(rows * row_size, 0.f);
  bad[5 * row_size + 2] = std::numeric_limits<float>::quiet_NaN();  // inside a 3-column prefix
  bad[7 * row_size + 30] = std::numeric_limits<float>::infinity();  // outside it
  grad.upload(bad);
  adam.clear_nonfinite();
  adam.accumulate_nonfinite_cols(grad, rows, row_size, 3);
  EXPECT_EQ(adam.read_nonfinite(), 1u);
  adam.clear_nonfinite();
  adam.accumulate_nonfinite_cols(grad, rows, row_size, row_size);
  EXPECT_EQ(adam.read_nonfinite(), 2u);
  // Every value of a 9-column prefix (the last rows and columns of the
  // rounded-up range included) is counted once.
  grad.upload(std::vector<float>(rows * row_size, std::numeric_limits<float>::quiet_NaN()));
  adam.clear_nonfinite();
  adam.accumulate_nonfinite_cols(grad, rows, row_size, 9);
  EXPECT_EQ(adam.read_nonfinite(), rows * 9);
  EXPECT_THROW(adam.step_cols(cols, p_cols, grad, 1e-2, 46), std::invalid_argument);
  EXPECT_THROW(adam.step_cols(cols, p_cols, grad, 1e-2, -1), std::invalid_argument);
}

TEST(Adam, CountsNonFiniteValues) {
  Runtime& rt = test::runtime();
  Adam adam(rt);
  const size_t n = 100003;
  std::vector<float> g = random_grads(n + 10, 7);
  const float inf = std::numeric_limits<float>::infinity();
  g[0] = std::numeric_limits<float>::quiet_NaN();
  g[12345] = inf;
  g[54321] = -inf;
  g[n - 1] = -std::numeric_limits<float>::quiet_NaN();
  g[n + 3] = inf;  // beyond n: not counted
  g[17] = std::numeric_limits<float>::max();
  g[18] = std::numeric_limits<float>::denorm_min();
  g[19] = -0.f;
  DeviceBuffer buf(&rt);
  buf.upload(g);
  EXPECT_EQ(adam.count_nonfinite(buf, n), 4u);
  EXPECT_EQ(adam.count_nonfinite(buf, n + 10), 5u);
  EXPECT_EQ(adam.count_nonfinite(buf, 0), 0u);
  EXPECT_EQ(adam.count_nonfinite(buf, 1), 1u);
  // Several buffers, one read; everything NaN counts every element.
  DeviceBuffer all_nan(&rt);
  all_nan.upload(std::vector<float>(5000, std::numeric_limits<float>::quiet_NaN()));
  adam.clear_nonfinite();
  adam.accumulate_nonfinite(buf, n);
  adam.accumulate_nonfinite(all_nan, 5000);
  EXPECT_EQ(adam.read_nonfinite(), 5004u);
  DeviceBuffer clean(&rt);
  clean.upload(random_grads(4096, 8));
  EXPECT_EQ(adam.count_nonfinite(clean, 4096), 0u);
}

std::vector<float> host_gather(const std::vector<float>& src, const std::vector<int>& index, int row_size) {
  std::vector<float> out;
  for (int s : index)
    for (int c = 0; c < row_size; ++c) out.push_back(s < 0 ? 0.f : src[static_cast<size_t>(s) * row_size + c]);
  return out;
}

TEST(Adam, GatherRows) {
  Runtime& rt = test::runtime();
  const int C = 7;
  const size_t rows = 501;
  auto src_host = random_params(rows * C, 9);
  DeviceBuffer src(&rt), dst(&rt);
  src.upload(src_host);
  std::vector<int> index;  // prune every third row, then append 20 new ones
  for (size_t r = 0; r < rows; ++r)
    if (r % 3 != 1) index.push_back(static_cast<int>(rows - 1 - r));
  for (int k = 0; k < 20; ++k) index.push_back(-1);
  gather_rows(rt, src, rows, dst, index, C);
  std::vector<float> out;
  dst.download(out, index.size() * C);
  EXPECT_EQ(test::hash_vec(out), test::hash_vec(host_gather(src_host, index, C)));
  // Bad indices: rejected from the host, NaN rows from a device list.
  EXPECT_THROW(gather_rows(rt, src, rows, dst, std::vector<int>{0, static_cast<int>(rows)}, C), std::invalid_argument);
  EXPECT_THROW(gather_rows(rt, src, rows, dst, std::vector<int>{-2}, C), std::invalid_argument);
  DeviceBuffer idx(&rt);
  idx.upload(std::vector<int>{3, 9999, -1});
  gather_rows(rt, src, rows, dst, idx, 3, C);
  dst.download(out, 3 * C);
  EXPECT_EQ(out[0], src_host[3 * C]);
  EXPECT_TRUE(std::isnan(out[C]));
  EXPECT_EQ(out[2 * C], 0.f);
  EXPECT_THROW(gather_rows(rt, src, rows, src, idx, 3, C), std::invalid_argument);
}

// Densify/prune in the middle of training: the moments follow their rows, new
// rows start from zero moments, and later steps still match the reference.
TEST(Adam, MomentsFollowGatherAndResize) {
  Runtime& rt = test::runtime();
  Adam adam(rt);
  const int C = 3;
  Twin t(rt, "means", 400, C, 11);
  for (int it = 0; it < 4; ++it) t.step(adam, 1e-3, 400 + it);

  std::vector<int> index;
  for (int r = 0; r < 400; r += 2) index.push_back(r);
  for (int k = 0; k < 37; ++k) index.push_back(k % 5 == 0 ? -1 : 399 - k);  // clones and new rows
  t.group.gather(index);
  DeviceBuffer new_param(&rt);
  gather_rows(rt, t.param, 400, new_param, index, C);
  std::vector<float> p;
  new_param.download(p, index.size() * C);
  t.param.upload(p);
  std::vector<double> gp(index.size() * C), gm(index.size() * C), gv(index.size() * C);
  for (size_t r = 0; r < index.size(); ++r)
    for (int c = 0; c < C; ++c) {
      const size_t i = r * C + c, s = static_cast<size_t>(index[r]) * C + c;
      gp[i] = p[i];  // continue from the device's parameters
      gm[i] = index[r] < 0 ? 0.0 : t.ref_state.m[s];
      gv[i] = index[r] < 0 ? 0.0 : t.ref_state.v[s];
    }
  t.ref_param = gp;
  t.ref_state.m = gm;
  t.ref_state.v = gv;
  EXPECT_EQ(t.group.rows(), index.size());
  EXPECT_EQ(t.group.steps(), 4);
  t.check();

  for (int it = 0; it < 3; ++it) t.step(adam, 1e-3, 500 + it);
  t.check();

  // Resize: grow keeps rows and zeroes the new ones; shrink keeps the prefix.
  std::vector<float> m_before;
  t.group.exp_avg().download(m_before, t.group.size());
  const size_t rows = t.group.rows();
  t.group.resize(rows + 5000);  // beyond the capacity: reallocates
  std::vector<float> m_after;
  t.group.exp_avg().download(m_after, t.group.size());
  ASSERT_EQ(m_after.size(), (rows + 5000) * C);
  for (size_t i = 0; i < m_after.size(); ++i) ASSERT_EQ(m_after[i], i < m_before.size() ? m_before[i] : 0.f) << i;
  t.group.resize(10);
  t.group.resize(12);  // within the capacity: rows 10, 11 are zeroed again
  t.group.exp_avg_sq().download(m_after, t.group.size());
  for (size_t i = 30; i < 36; ++i) EXPECT_EQ(m_after[i], 0.f);
  t.group.exp_avg().download(m_after, t.group.size());
  for (size_t i = 0; i < 30; ++i) EXPECT_EQ(m_after[i], m_before[i]);

  t.group.zero_moments();
  t.group.exp_avg_sq().download(m_after, t.group.size());
  for (float v : m_after) EXPECT_EQ(v, 0.f);
  EXPECT_EQ(t.group.steps(), 7);  // the step count survives a moment reset
}

// Parking (the importance sweep's, on simulators): the moments leave the
// device and come back with the same bits, so the steps after it equal the
// steps of a group that never parked, bit for bit.
TEST(Adam, ParkedMomentsReturnBitForBit) {
  Runtime& rt = test::runtime();
  Adam adam(rt);
  Twin a(rt, "parked", 300, 3, 21), b(rt, "kept", 300, 3, 21);
  for (int it = 0; it < 3; ++it) {
    a.step(adam, 1e-3, 600 + it);
    b.step(adam, 1e-3, 600 + it);
  }
  const uint64_t held = rt.allocated_bytes();
  const size_t moments = a.group.exp_avg().capacity() + a.group.exp_avg_sq().capacity();
  a.group.park();
  EXPECT_TRUE(a.group.parked());
  EXPECT_EQ(rt.allocated_bytes(), held - moments) << "park frees both moments";
  EXPECT_EQ(a.group.exp_avg().capacity(), 0u);
  EXPECT_EQ(a.group.exp_avg_sq().capacity(), 0u);
  a.group.park();  // twice is once
  a.group.unpark();
  EXPECT_FALSE(a.group.parked());
  a.group.unpark();  // nothing parked: no change
  for (int it = 0; it < 2; ++it) {
    a.step(adam, 1e-3, 700 + it);
    b.step(adam, 1e-3, 700 + it);
  }
  std::vector<float> pa, pb, ma, mb, va, vb;
  a.param.download(pa, a.group.size());
  b.param.download(pb, b.group.size());
  a.group.exp_avg().download(ma, a.group.size());
  b.group.exp_avg().download(mb, b.group.size());
  a.group.exp_avg_sq().download(va, a.group.size());
  b.group.exp_avg_sq().download(vb, b.group.size());
  EXPECT_EQ(test::hash_vec(pa), test::hash_vec(pb));
  EXPECT_EQ(test::hash_vec(ma), test::hash_vec(mb));
  EXPECT_EQ(test::hash_vec(va), test::hash_vec(vb));
  EXPECT_EQ(a.group.steps(), 5);
}

TEST(Adam, RejectsBadArguments) {
  Runtime& rt = test::runtime();
  Adam adam(rt);
  // Sizes above DeviceBuffer's 256-byte minimum, so capacities are exact.
  AdamGroup group(rt, "g", 1000, 2);
  DeviceBuffer param(&rt), grad(&rt), small(&rt), visible(&rt);
  param.upload(std::vector<float>(2000, 0.f));
  grad.upload(std::vector<float>(2000, 0.f));
  small.upload(std::vector<float>(1999, 0.f));
  visible.upload(std::vector<int>(999, 1));
  EXPECT_THROW(adam.step(group, param, grad, -1.0), std::invalid_argument);
  EXPECT_THROW(adam.step(group, param, grad, std::nan("")), std::invalid_argument);
  EXPECT_THROW(adam.step(group, param, param, 1e-3), std::invalid_argument);
  EXPECT_THROW(adam.step(group, small, grad, 1e-3), std::invalid_argument);
  EXPECT_THROW(adam.step(group, param, small, 1e-3), std::invalid_argument);
  EXPECT_THROW(adam.step_visible(group, param, grad, 1e-3, visible), std::invalid_argument);
  EXPECT_EQ(group.steps(), 0);  // nothing ran
  EXPECT_THROW(AdamGroup(rt, "bad", 3, 0), std::invalid_argument);
  EXPECT_THROW(Adam(rt, AdamSettings{1.0, 0.999, 1e-15}), std::invalid_argument);
}

}  // namespace
}  // namespace ag2gs
