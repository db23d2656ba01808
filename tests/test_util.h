// Shared helpers for the device tests: one OpenCL runtime per process, random
// scenes, and element-wise comparison with measured tolerances.
#pragma once

#include <gtest/gtest.h>
#include <unistd.h>

#include <Eigen/Geometry>
#include <array>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <random>
#include <string>
#include <vector>

#include "host/core/gaussians.h"
#include "host/device/cl_runtime.h"
#include "host/render/renderer.h"

namespace ag2gs::test {

// One runtime per test program, never destroyed: static destructors run in an
// order the OpenCL implementation does not know about, and releasing a context
// after the implementation's own statics are gone corrupts its heap (Oclgrind
// aborts at exit that way). The process exit frees it.
inline Runtime& runtime() {
  static Runtime* rt = new Runtime(-1);
  return *rt;
}

inline std::string source_dir() {
  const char* s = std::getenv("AG2GS_SOURCE_DIR");
  return s ? s : ".";
}

// A camera at distance `dist` on the -z side of the origin looking at it.
inline Camera look_at_origin(int w, int h, double dist = 4.0, double fov_scale = 1.0) {
  Camera c;
  c.width = w;
  c.height = h;
  c.fx = c.fy = fov_scale * 0.9 * std::max(w, h);
  c.cx = 0.5 * w + 0.13;  // slightly off-centre: catches cx/cy mix-ups
  c.cy = 0.5 * h - 0.21;
  Eigen::AngleAxisd rot(0.3, Eigen::Vector3d(0.2, 1, 0.1).normalized());
  c.R = rot.toRotationMatrix();
  c.t = Eigen::Vector3d(0.05, -0.03, dist);
  return c;
}

// A camera at `eye` looking at `target` with world +z up (x right, y down),
// principal point at the image centre.
inline Camera look_at(const Eigen::Vector3d& eye, const Eigen::Vector3d& target, int w, int h, double focal) {
  Camera c;
  c.width = w;
  c.height = h;
  c.fx = c.fy = focal;
  c.cx = 0.5 * w;
  c.cy = 0.5 * h;
  const Eigen::Vector3d fwd = (target - eye).normalized();
  const Eigen::Vector3d right = fwd.cross(Eigen::Vector3d::UnitZ()).normalized();
  c.R.row(0) = right;
  c.R.row(1) = fwd.cross(right);
  c.R.row(2) = fwd;
  c.t = -c.R * eye;
  return c;
}

struct SceneSpec {
  size_t n = 100;
  int sh_degree = 1;
  double extent = 1.0;  // means in [-extent, extent]^3
  double log_scale_lo = -4.0, log_scale_hi = -1.5;
  double opacity_lo = 0.05, opacity_hi = 1.0;
};

inline GaussianSet random_scene(const SceneSpec& s, uint32_t seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u01(0, 1);
  std::normal_distribution<double> nrm(0, 1);
  GaussianSet g;
  g.sh_degree = s.sh_degree;
  g.resize(s.n);
  const int K = g.sh_coeffs();
  for (size_t i = 0; i < s.n; ++i) {
    for (int k = 0; k < 3; ++k) {
      g.means[3 * i + k] = static_cast<float>((2 * u01(rng) - 1) * s.extent);
      g.scales[3 * i + k] = static_cast<float>(std::exp(s.log_scale_lo + (s.log_scale_hi - s.log_scale_lo) * u01(rng)));
      g.features[3 * i + k] = static_cast<float>(u01(rng));
    }
    for (int k = 0; k < 4; ++k) g.quats[4 * i + k] = static_cast<float>(nrm(rng));
    g.opacities[i] = static_cast<float>(s.opacity_lo + (s.opacity_hi - s.opacity_lo) * u01(rng));
    for (int k = 0; k < K; ++k)
      for (int c = 0; c < 3; ++c)
        g.sh[(i * K + k) * 3 + c] = static_cast<float>(k == 0 ? nrm(rng) * 0.8 : nrm(rng) * 0.2);
  }
  return g;
}

// Element-wise comparison: |a - b| <= abs_tol + rel_tol * |b|. Elements whose
// error exceeds that are "violations"; up to `allowed_fraction` of them are
// accepted when below `flip_tol` (pixels where a 1/255 or 1e-4 threshold
// decision went the other way in float than in double).
struct CompareResult {
  double max_abs = 0, max_rel = 0;
  size_t violations = 0, big_violations = 0, nan_mismatch = 0, n = 0;
};

template <typename A, typename B>
CompareResult compare(const std::vector<A>& dev, const std::vector<B>& ref, double abs_tol, double rel_tol,
                      double flip_tol = 0) {
  CompareResult r;
  r.n = ref.size();
  EXPECT_EQ(dev.size(), ref.size());
  for (size_t i = 0; i < std::min(dev.size(), ref.size()); ++i) {
    double a = dev[i], b = ref[i];
    if (std::isnan(a) || std::isnan(b)) {
      if (std::isnan(a) != std::isnan(b)) ++r.nan_mismatch;
      continue;
    }
    double e = std::abs(a - b);
    r.max_abs = std::max(r.max_abs, e);
    if (std::abs(b) > 1e-3) r.max_rel = std::max(r.max_rel, e / std::abs(b));
    if (e > abs_tol + rel_tol * std::abs(b)) {
      ++r.violations;
      if (e > flip_tol) ++r.big_violations;
    }
  }
  return r;
}

inline void expect_close(const char* what, const CompareResult& r, double allowed_fraction = 0) {
  std::printf("  %-12s max abs %.3g  max rel %.3g  violations %zu/%zu\n", what, r.max_abs, r.max_rel, r.violations,
              r.n);
  EXPECT_EQ(r.nan_mismatch, 0u) << what;
  EXPECT_EQ(r.big_violations, 0u) << what;
  EXPECT_LE(static_cast<double>(r.violations), allowed_fraction * r.n) << what;
}

inline bool all_finite(const std::vector<float>& v) {
  for (float x : v)
    if (!std::isfinite(x)) return false;
  return true;
}

inline uint64_t hash_bytes(const void* data, size_t bytes, uint64_t h = 1469598103934665603ull) {
  auto* p = static_cast<const unsigned char*>(data);
  for (size_t i = 0; i < bytes; ++i) {
    h ^= p[i];
    h *= 1099511628211ull;
  }
  return h;
}
template <typename T>
uint64_t hash_vec(const std::vector<T>& v, uint64_t h = 1469598103934665603ull) {
  return hash_bytes(v.data(), v.size() * sizeof(T), h);
}

// Runs this test program's `worker` test (--gtest_filter) in a child process
// with 1 and then 2 PoCL threads; the worker writes one line to the file
// named by $AG2GS_HASH_OUT (and skips when that is unset). Returns the two
// lines. The pid keeps tests that ctest runs in parallel (the layout
// variants) from reading each other's files.
inline std::array<std::string, 2> lines_by_thread_count(const std::string& worker) {
  std::array<std::string, 2> lines;
  char exe[4096];
  const ssize_t len = readlink("/proc/self/exe", exe, sizeof exe - 1);
  EXPECT_GT(len, 0);
  if (len <= 0) return lines;
  exe[len] = 0;
  for (int threads = 1; threads <= 2; ++threads) {
    const std::string file =
        testing::TempDir() + "ag2gs_hash_" + std::to_string(getpid()) + "_" + worker + "_" + std::to_string(threads);
    const std::string cmd = "POCL_MAX_PTHREAD_COUNT=" + std::to_string(threads) + " AG2GS_HASH_OUT=" + file + " " +
                            exe + " --gtest_filter=" + worker + " > /dev/null 2>&1";
    EXPECT_EQ(std::system(cmd.c_str()), 0) << cmd;
    std::ifstream f(file);
    std::getline(f, lines[threads - 1]);
    EXPECT_FALSE(lines[threads - 1].empty()) << cmd;
    std::remove(file.c_str());
  }
  return lines;
}

}  // namespace ag2gs::test
