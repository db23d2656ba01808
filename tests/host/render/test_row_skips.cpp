// The blend walks skip a Gaussian at pixels where it cannot blend before
// computing its exponential (kernels/common.cl): row_beyond and
// tile_rows_reached for a tile row, tile_cols_reached for a tile column
// (the GPU layout's lists, tile_reached), row_reach for every row past a bound on
// |dy|, out_of_reach for one pixel's sigma. A skip changes no bit only if
// the alpha test (sigma >= 0 and min(0.99, o exp(-sigma)) >= 1/255, as the
// kernels compute it) fails wherever a skip is taken. This test runs the
// device's own helpers on Gaussians from round to needle-thin, opacities
// from 1/255 to 1, and checks every pixel a skip covers, densest just past
// each bound.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <random>
#include <string>
#include <vector>

#include "kernels/layout.h"
#include "tests/io_test_util.h"
#include "tests/test_util.h"

namespace ag2gs {
namespace {

namespace fs = std::filesystem;

// For record i (u, v relative to a 16x16 tile at the origin): bad[i] gets
// 1 when a pixel blends although a skip covers it.
const char* kCheckKernel = R"CL(
inline int blends(__global const float* q, float dx, float dy) {
  const float sigma = blend_sigma(q[REC_CA], q[REC_CB], q[REC_CC], dx, dy);
  const float alpha = fmin(q[REC_OPACITY] * blend_falloff(sigma), ALPHA_MAX);
  return sigma >= 0.f && alpha >= ALPHA_MIN;
}

__kernel void row_skip_check(int n, __global const float* records, __global int* bad) {
  const int i = get_global_id(0);
  if (i >= n) return;
  __global const float* q = records + (size_t)i * REC_SIZE;
  int b = 0;
  // Every pixel of the tile: the row bit, the row test and the pixel test.
  const float u = q[REC_U], v = q[REC_V];
  for (int y = 0; y < TILE; ++y) {
    const float py = (float)y + 0.5f;
    for (int x = 0; x < TILE; ++x) {
      const float px = (float)x + 0.5f;
      if (!blends(q, u - px, v - py)) continue;
      const float sigma = blend_sigma(q[REC_CA], q[REC_CB], q[REC_CC], u - px, v - py);
      if (out_of_reach(sigma, q[REC_THR])) b |= 1;
      if (row_beyond(q[REC_CA], q[REC_CB], q[REC_CC], q[REC_CM], q[REC_THR], v - py, u - 0.5f, u - ((float)TILE - 0.5f)))
        b |= 2;
    }
  }
  // Rows past row_reach, for pixel centres up to dxm across: at the bound
  // and just past it in steps of a few ulps, then further out.
  const float dxm = fmax(fabs(u - 0.5f), fabs(u - ((float)TILE - 0.5f)));
  const float reach = row_reach(q[REC_CA], q[REC_CB], q[REC_CC], q[REC_CM], q[REC_THR], dxm);
  if (isfinite(reach)) {
    for (int k = 0; k < 48; ++k) {
      const float off = k < 24 ? (float)k * 1e-6f * fmax(reach, 1.f) : (float)(k - 23) * 0.25f * fmax(reach, 1.f);
      for (int side = -1; side <= 1; side += 2) {
        const float dy = (float)side * (reach + off);
        for (int m = 0; m <= 64; ++m) {
          const float dx = -dxm + 2.f * dxm * (float)m / 64.f;
          if (blends(q, dx, dy)) b |= 4;
        }
      }
    }
  }
  bad[i] = b;
}

// The GPU layout's masks (tile_reached: rows, then columns), read from local
// memory as the walks read them.
__kernel void tile_rows_check(int n, __global const float* records, __global uint* masks) {
  __local float rec[REC_SIZE];
  const int i = get_group_id(0);
  if (get_local_id(0) == 0) {
    for (int c = 0; c < REC_SIZE; ++c) rec[c] = records[(size_t)i * REC_SIZE + c];
  }
  barrier(CLK_LOCAL_MEM_FENCE);
  if (get_local_id(0) == 0 && i < n) masks[i] = tile_reached(rec, 0, 1);
}
)CL";

struct Rec {
  float f[REC_SIZE];
};

// A record as project_fwd writes it (kernels/project.cl): conic from a 2D
// covariance, thr = ln(255 o), cm = cC - cB^2 / cA.
Rec make_record(std::mt19937& rng) {
  std::uniform_real_distribution<float> unit(0.f, 1.f);
  const float angle = 6.2831853f * unit(rng);
  // Standard deviations from a tenth of a pixel to 30 pixels, either axis.
  const float s1 = 0.1f * std::pow(300.f, unit(rng)), s2 = 0.1f * std::pow(300.f, unit(rng));
  const float c = std::cos(angle), s = std::sin(angle);
  const float a = c * c * s1 * s1 + s * s * s2 * s2 + 0.3f, cc = s * s * s1 * s1 + c * c * s2 * s2 + 0.3f;
  const float b = c * s * (s1 * s1 - s2 * s2);
  const float det = a * cc - b * b;
  Rec r{};
  r.f[REC_U] = -24.f + 64.f * unit(rng);  // u: inside the tile and well outside it
  r.f[REC_V] = -24.f + 64.f * unit(rng);  // v
  r.f[REC_CA] = cc / det;
  r.f[REC_CB] = -b / det;
  r.f[REC_CC] = a / det;
  const float o = unit(rng) < 0.1f ? 1.f / 255.f + 1e-6f : std::pow(255.f, -unit(rng));
  r.f[REC_OPACITY] = o;
  r.f[REC_THR] = std::log(255.f * o);
  r.f[REC_CM] = r.f[REC_CC] - r.f[REC_CB] * r.f[REC_CB] / r.f[REC_CA];
  return r;
}

TEST(RowSkips, NoSkipCoversAPixelThatBlends) {
  const char* src = std::getenv("AG2GS_SOURCE_DIR");
  const fs::path kernels = fs::path(src ? src : ".") / "kernels";
  test::ScratchDir dir("row_skips");
  const fs::path kdir = dir.file("kernels");
  fs::create_directories(kdir);
  for (const char* f : {"layout.h", "common.cl"}) fs::copy_file(kernels / f, kdir / f);
  std::ofstream(kdir / "row_skip_check.cl") << kCheckKernel;
  setenv("AG2GS_KERNEL_DIR", kdir.c_str(), 1);

  Runtime& rt = test::runtime();
  std::mt19937 rng(7);
  const int n = 20000;
  std::vector<float> recs(static_cast<size_t>(n) * REC_SIZE);
  for (int i = 0; i < n; ++i) {
    const Rec r = make_record(rng);
    std::copy(r.f, r.f + REC_SIZE, recs.begin() + static_cast<size_t>(i) * REC_SIZE);
  }
  DeviceBuffer in(&rt), bad(&rt), masks(&rt);
  in.upload(recs);
  bad.reserve(static_cast<size_t>(n) * 4);
  masks.reserve(static_cast<size_t>(n) * 4);
  const std::map<std::string, std::string> defs{{"VW", "1"}};
  cl::Kernel check = rt.kernel("row_skip_check.cl", "row_skip_check", defs);
  set_kernel_args(check, n, in, bad);
  rt.launch("test", check, cl::NDRange(n));
  cl::Kernel rows = rt.kernel("row_skip_check.cl", "tile_rows_check", defs);
  set_kernel_args(rows, n, in, masks);
  rt.launch("test", rows, cl::NDRange(static_cast<size_t>(n) * 16), cl::NDRange(16));  // one group per record
  unsetenv("AG2GS_KERNEL_DIR");

  std::vector<int> b;
  bad.download(b, n);
  std::vector<uint32_t> m;
  masks.download(m, n);
  int skipped_rows = 0, skipped_cols = 0;
  for (int i = 0; i < n; ++i) {
    const float* q = recs.data() + static_cast<size_t>(i) * REC_SIZE;
    EXPECT_EQ(b[i], 0) << "record " << i << " (conic " << q[REC_CA] << " " << q[REC_CB] << " " << q[REC_CC]
                       << ", opacity " << q[REC_OPACITY] << "): " << ((b[i] & 1) ? "out_of_reach " : "")
                       << ((b[i] & 2) ? "row_beyond " : "") << ((b[i] & 4) ? "row_reach " : "")
                       << "skipped a pixel that blends";
    // The masks: a row or a column without its bit has no pixel that blends
    // (the pixel test in double, with a margin float rounding cannot cross).
    for (int y = 0; y < TILE; ++y) {
      for (int x = 0; x < TILE; ++x) {
        const bool row_bit = (m[i] >> y) & 1u, col_bit = (m[i] >> (TILE + x)) & 1u;
        if (x == 0 && !row_bit) ++skipped_rows;
        if (y == 0 && !col_bit) ++skipped_cols;
        if (row_bit && col_bit) continue;
        const double dx = q[REC_U] - (x + 0.5), dy = q[REC_V] - (y + 0.5);
        const double sigma = 0.5 * (q[REC_CA] * dx * dx + q[REC_CC] * dy * dy) + q[REC_CB] * dx * dy;
        EXPECT_FALSE(sigma < std::log(255.0 * q[REC_OPACITY]) - 1e-3)
            << "record " << i << ": " << (row_bit ? "column " : "row ") << (row_bit ? x : y)
            << " has no bit, yet pixel (" << x << ", " << y << ") blends";
      }
    }
  }
  // The skips do skip: most rows and columns of most records are out of reach.
  EXPECT_GT(skipped_rows, n * TILE / 2);
  EXPECT_GT(skipped_cols, n * TILE / 2);
}

}  // namespace
}  // namespace ag2gs
