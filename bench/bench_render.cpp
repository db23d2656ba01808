// ag2gs_bench: speed against error of the tile renderer.
// For 10k, 100k and 1M Gaussians (surfaces with a realistic scale mix) at
// 400x300 and 800x600 it prints forward and backward time per kernel
// (median over repeats), Gaussian-pixel evaluations per second, peak device
// memory, and the error of the device result against the double-precision
// reference (tests/reference) at the same settings.
#include <spdlog/spdlog.h>

#include <CLI/CLI.hpp>
#include <Eigen/Geometry>
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <map>
#include <random>

#include "host/device/cl_runtime.h"
#include "host/render/renderer.h"
#include "tests/reference/reference_renderer.h"

using namespace ag2gs;

namespace {

// Gaussians on a few spheres and a ground plane, scales shrinking with the
// count like a trained scene's (surface density ~ N), lognormal spread,
// opacities mostly high with a transparent tail.
GaussianSet surface_scene(size_t n, uint32_t seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(0, 1);
  std::normal_distribution<double> nrm(0, 1);
  GaussianSet g;
  g.sh_degree = 3;
  g.resize(n);
  const double base = 1.6 / std::sqrt(static_cast<double>(n));  // spacing on ~10 units^2 of surface
  const Eigen::Vector3d centres[3] = {{0, 0, 0}, {0.9, 0.3, 0.6}, {-0.8, -0.2, 0.4}};
  const double radii[3] = {0.7, 0.35, 0.45};
  for (size_t i = 0; i < n; ++i) {
    Eigen::Vector3d p;
    double kind = u(rng);
    if (kind < 0.7) {
      int s = static_cast<int>(u(rng) * 3) % 3;
      Eigen::Vector3d d(nrm(rng), nrm(rng), nrm(rng));
      p = centres[s] + radii[s] * d.normalized();
    } else {
      p = Eigen::Vector3d(4 * u(rng) - 2, 0.75 + 0.01 * nrm(rng), 4 * u(rng) - 2);  // ground (y down)
    }
    for (int k = 0; k < 3; ++k) {
      g.means[3 * i + k] = static_cast<float>(p[k]);
      g.scales[3 * i + k] = static_cast<float>(base * std::exp(0.6 * nrm(rng)) * (k == 2 ? 0.3 : 1.0));
      g.features[3 * i + k] = static_cast<float>(u(rng));
    }
    for (int k = 0; k < 4; ++k) g.quats[4 * i + k] = static_cast<float>(nrm(rng));
    double o = u(rng);
    g.opacities[i] = static_cast<float>(o < 0.3 ? 0.02 + 0.3 * u(rng) : 0.6 + 0.39 * u(rng));
    for (int k = 0; k < 16; ++k)
      for (int c = 0; c < 3; ++c) g.sh[(i * 16 + k) * 3 + c] = static_cast<float>((k == 0 ? 0.8 : 0.1) * nrm(rng));
  }
  return g;
}

Camera bench_camera(int w, int h) {
  Camera c;
  c.width = w;
  c.height = h;
  c.fx = c.fy = 0.9 * w;
  c.cx = w / 2.0;
  c.cy = h / 2.0;
  Eigen::AngleAxisd rot(0.35, Eigen::Vector3d(0.1, 1, 0).normalized());
  c.R = rot.toRotationMatrix();
  c.t = Eigen::Vector3d(0, 0, 3.5);
  return c;
}

double median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  return v.empty() ? 0 : v[v.size() / 2];
}

struct Errors {
  double fwd_abs = 0, fwd_rel = 0;
};

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"ag2gs_bench: renderer speed against error"};
  bool quick = false;
  int repeats = 5, device = -1, sample_pixels = 3000;
  app.add_flag("--quick", quick, "10k Gaussians only");
  app.add_option("--repeats", repeats, "timed repeats per configuration (median reported)");
  app.add_option("--device", device, "OpenCL device index");
  app.add_option("--sample-pixels", sample_pixels, "pixels compared with the double reference");
  std::vector<size_t> only;
  app.add_option("--counts", only, "Gaussian counts to run (default 10000 100000 1000000)");
  std::vector<std::string> size_args;
  app.add_option("--sizes", size_args, "image sizes WxH to run (default 400x300 800x600)");
  bool by_kernel = false;
  app.add_flag("--kernels", by_kernel, "after each row, every kernel's median time");
  CLI11_PARSE(app, argc, argv);
  spdlog::set_level(spdlog::level::warn);

  Runtime rt(device);
  rt.set_profiling(true, by_kernel);
  std::printf("device: %s (%s), vector width %d, sort %s, blend backward %s\n", rt.info().name.c_str(),
              rt.info().platform.c_str(), rt.vector_width(), radix_sort_plan_for(rt.info()).describe().c_str(),
              Renderer(rt).blend_bwd_plan().c_str());
  std::vector<size_t> counts = quick ? std::vector<size_t>{10000} : std::vector<size_t>{10000, 100000, 1000000};
  if (!only.empty()) counts = only;
  std::vector<std::pair<int, int>> sizes = {{400, 300}, {800, 600}};
  if (!size_args.empty()) {
    sizes.clear();
    for (const std::string& a : size_args) {
      int w = 0, h = 0;
      char x = 0;
      if (std::sscanf(a.c_str(), "%d%c%d", &w, &x, &h) != 3 || x != 'x' || w < 1 || h < 1) {
        std::fprintf(stderr, "--sizes: '%s' is not WxH (e.g. 400x300)\n", a.c_str());
        return 2;
      }
      sizes.emplace_back(w, h);
    }
  }
  std::printf(
      "\n| Gaussians | image | isect | fwd ms (project/sort/bin/blend) | bwd ms (blend/project) | fwd+bwd ms "
      "| blend G evals/s | peak MiB | fwd max abs / rel err | bwd max err / scale |\n");
  std::printf("|---|---|---|---|---|---|---|---|---|---|\n");
  for (size_t n : counts) {
    GaussianSet g = surface_scene(n, 7);
    for (auto [w, h] : sizes) {
      Camera cam = bench_camera(w, h);
      Renderer r(rt);
      DeviceGaussians dg(rt);
      dg.upload(g);
      std::mt19937 rng(3);
      std::uniform_real_distribution<float> ud(-1, 1);
      const size_t npix = static_cast<size_t>(w) * h;
      OutputGrads og;
      og.rgb.resize(npix * 3);
      og.alpha.resize(npix);
      og.distortion.resize(npix);
      for (auto& x : og.rgb) x = ud(rng);
      for (auto& x : og.alpha) x = ud(rng);
      for (auto& x : og.distortion) x = ud(rng);
      // The upstream gradients on the device, planar, as a trainer's losses
      // leave them (Renderer::DeviceOutputGrads): the timed backward is the
      // device's work, not the host's conversion and upload of 5 planes.
      std::vector<float> rgb_planar(npix * 3);
      for (size_t p = 0; p < npix; ++p)
        for (int c = 0; c < 3; ++c) rgb_planar[c * npix + p] = og.rgb[3 * p + c];
      DeviceBuffer g_rgb(&rt), g_alpha(&rt), g_dist(&rt);
      g_rgb.upload(rgb_planar);
      g_alpha.upload(og.alpha);
      g_dist.upload(og.distortion);
      Renderer::DeviceOutputGrads dog;
      dog.rgb = &g_rgb;
      dog.alpha = &g_alpha;
      dog.distortion = &g_dist;
      // Warm-up (kernel builds, buffer growth), then timed repeats.
      r.forward(dg, cam, {});
      r.backward(dog);
      rt.take_timings();
      rt.reset_peak();
      std::map<std::string, std::vector<double>> t;
      std::vector<double> wall_f, wall_fb;
      for (int i = 0; i < repeats; ++i) {
        auto t0 = std::chrono::steady_clock::now();
        r.forward(dg, cam, {});
        rt.queue().finish();
        auto t1 = std::chrono::steady_clock::now();
        r.backward(dog);
        rt.queue().finish();
        auto t2 = std::chrono::steady_clock::now();
        wall_f.push_back(std::chrono::duration<double, std::milli>(t1 - t0).count());
        wall_fb.push_back(std::chrono::duration<double, std::milli>(t2 - t0).count());
        for (auto& [k, v] : rt.take_timings()) t[k].push_back(v);
      }
      size_t M = r.stats().n_intersections;
      double blend = median(t["blend_fwd"]);
      double evals = static_cast<double>(M) * 256.0 / (blend * 1e-3) / 1e9;

      // Error against the double reference on a sample of pixels.
      Errors e;
      RenderOutput out = r.download_output();
      std::vector<int> pix;
      for (int i = 0; i < sample_pixels; ++i) pix.push_back(static_cast<int>(rng() % npix));
      ref::RefImages ref_img = ref::render_pixels(g, cam, {}, pix);
      for (size_t i = 0; i < pix.size(); ++i)
        for (int c = 0; c < 3; ++c) {
          double a = out.rgb[3 * pix[i] + c], b = ref_img.rgb[3 * i + c];
          e.fwd_abs = std::max(e.fwd_abs, std::abs(a - b));
          if (std::abs(b) > 1e-2) e.fwd_rel = std::max(e.fwd_rel, std::abs(a - b) / std::abs(b));
        }
      char bwd_err[64] = "n/a (reference too slow)";
      if (n <= 10000) {
        r.backward(og);
        GaussianGrads dgr = r.download_grads();
        ref::RefGrads rg = ref::render_backward(g, cam, {}, og);
        double scale = 0, err = 0;
        for (double x : rg.means) scale = std::max(scale, std::abs(x));
        for (size_t i = 0; i < rg.means.size(); ++i) err = std::max(err, std::abs(dgr.means[i] - rg.means[i]));
        std::snprintf(bwd_err, sizeof bwd_err, "means %.2g", scale > 0 ? err / scale : 0.0);
      }
      std::printf(
          "| %zu | %dx%d | %zu | %.1f (%.1f/%.1f/%.1f/%.1f) | %.1f (%.1f/%.1f) | %.1f | %.2f | %.0f | %.2g / %.2g | %s "
          "|\n",
          n, w, h, M, median(wall_f), median(t["project"]), median(t["sort"]), median(t["bin"]), blend,
          median(wall_fb) - median(wall_f), median(t["blend_bwd"]), median(t["project_bwd"]), median(wall_fb), evals,
          rt.peak_bytes() / double(1 << 20), e.fwd_abs, e.fwd_rel, bwd_err);
      if (by_kernel) {
        std::printf("  kernels (median ms per forward + backward):");
        for (auto& [k, v] : t)
          if (k.rfind("kernel:", 0) == 0) std::printf(" %s %.3f", k.c_str() + 7, median(v));
        std::printf("\n");
      }
      std::fflush(stdout);
    }
  }
  std::printf("\nG evals/s = intersections x 256 pixels / blend_fwd time (the work handed to the blend kernel).\n");
  return 0;
}
