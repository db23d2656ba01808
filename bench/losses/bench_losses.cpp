// ag2gs_bench_losses: speed of the image loss (L1 + SSIM, forward and
// backward) at 400x300 and 800x600 and of Adam steps on 1M and 10M
// parameters, median over repeats, with the error against the double
// references (tests/reference) at one size each.
#include <CLI/CLI.hpp>
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <random>
#include <vector>

#include "host/device/cl_runtime.h"
#include "host/losses/image_loss.h"
#include "host/optim/adam.h"
#include "tests/reference/adam_reference.h"
#include "tests/reference/image_loss_reference.h"

using namespace ag2gs;

namespace {

double median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  return v.empty() ? 0.0 : v[v.size() / 2];
}

template <typename F>
double time_ms(Runtime& rt, int repeats, F&& run) {
  run();  // warm-up: kernel builds, buffer growth
  rt.queue().finish();
  std::vector<double> ms;
  for (int r = 0; r < repeats; ++r) {
    auto t0 = std::chrono::steady_clock::now();
    run();
    rt.queue().finish();
    ms.push_back(std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count());
  }
  return median(ms);
}

// A photograph-like image pair: smooth structure plus noise, the rendering
// off by a smooth bias and noise.
void image_pair(int w, int h, uint32_t seed, std::vector<float>& rendered, std::vector<float>& target) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<float> u(0.f, 1.f);
  const size_t n = static_cast<size_t>(w) * h * 3;
  rendered.resize(n);
  target.resize(n);
  for (int y = 0; y < h; ++y)
    for (int x = 0; x < w; ++x)
      for (int c = 0; c < 3; ++c) {
        const size_t i = (static_cast<size_t>(y) * w + x) * 3 + c;
        const float base = 0.5f + 0.3f * std::sin(0.05f * x + 0.07f * y + c) * std::cos(0.03f * x - 0.02f * y);
        target[i] = std::clamp(base + 0.05f * (u(rng) - 0.5f), 0.f, 1.f);
        rendered[i] = std::clamp(target[i] + 0.05f * std::sin(0.01f * x + c) + 0.04f * (u(rng) - 0.5f), 0.f, 1.f);
      }
}

void bench_image_loss(Runtime& rt, int repeats, bool with_error) {
  ImageLoss loss(rt);
  std::printf("image loss (work-group %d, %d pixels per work-item)\n", loss.work_group(), loss.lanes());
  std::printf("  %-9s %12s %14s %22s\n", "size", "forward ms", "fwd+bwd ms", "fwd+bwd planar ms");
  const int sizes[][2] = {{400, 300}, {800, 600}};
  for (auto& s : sizes) {
    const int w = s[0], h = s[1];
    std::vector<float> x, y;
    image_pair(w, h, 1, x, y);
    DeviceBuffer dx(&rt), dy(&rt), grad(&rt);
    dx.upload(x);
    dy.upload(y);
    const double fwd = time_ms(rt, repeats, [&] { loss.enqueue(dx, dy, w, h, kSsimLambda); });
    const double both = time_ms(rt, repeats, [&] { loss.enqueue(dx, dy, w, h, kSsimLambda, &grad); });
    // [3,H,W] images, as the renderer keeps them on the device (the trainer's
    // path; the pixel values do not matter for the timing).
    const double planar =
        time_ms(rt, repeats, [&] { loss.enqueue(dx, dy, w, h, kSsimLambda, &grad, nullptr, ImageLayout::kPlanar); });
    std::printf("  %4dx%-4d %12.2f %14.2f %22.2f\n", w, h, fwd, both, planar);
    if (with_error && w == 400) {
      const ImageLossResult d = loss.forward_backward(dx, dy, w, h, kSsimLambda, &grad);
      std::vector<float> g;
      grad.download(g, static_cast<size_t>(w) * h * 3);
      const ref::RefImageLoss r = ref::image_loss(x, y, w, h, kSsimLambda, true);
      double scale = 0, err = 0;
      for (size_t i = 0; i < g.size(); ++i) {
        scale = std::max(scale, std::abs(r.grad[i]));
        err = std::max(err, std::abs(g[i] - r.grad[i]));
      }
      std::printf(
          "  error vs reference at %dx%d: loss %.3g (loss %.6f, ssim %.6f), gradient max %.3g = %.2g of "
          "max |grad|\n",
          w, h, std::abs(d.loss - r.loss), r.loss, r.ssim, err, err / scale);
    }
  }
}

void bench_adam(Runtime& rt, int repeats, bool with_error) {
  Adam adam(rt);
  std::printf("adam (work-group %d)\n", adam.work_group());
  std::printf("  %-10s %10s %12s %14s %16s\n", "params", "step ms", "GB/s", "nonfinite ms", "gather rows ms");
  for (size_t n : {size_t(1) << 20, size_t(10) << 20}) {
    std::mt19937 rng(2);
    std::normal_distribution<float> nrm(0.f, 1.f);
    std::vector<float> p(n), g(n);
    for (size_t i = 0; i < n; ++i) {
      p[i] = nrm(rng);
      g[i] = 1e-3f * nrm(rng);
    }
    DeviceBuffer dp(&rt), dg(&rt), dst(&rt);
    dp.upload(p);
    dg.upload(g);
    AdamGroup group(rt, "params", n / 4, 4);  // [N, 4] rows, like rotations
    const double step = time_ms(rt, repeats, [&] { adam.step(group, dp, dg, 1e-3); });
    const double check = time_ms(rt, repeats, [&] { adam.count_nonfinite(dg, n); });
    std::vector<int> index(n / 4);
    for (size_t r = 0; r < index.size(); ++r) index[r] = static_cast<int>(r % 10 == 0 ? -1 : index.size() - 1 - r);
    DeviceBuffer didx(&rt);
    didx.upload(index);
    const double gather = time_ms(rt, repeats, [&] { gather_rows(rt, dp, n / 4, dst, didx, n / 4, 4); });
    // 7 float streams per element: read p, g, m, v; write p, m, v.
    const double gbs = 7.0 * 4 * n / (step * 1e-3) / 1e9;
    std::printf("  %-10zu %10.2f %12.1f %14.2f %16.2f\n", n, step, gbs, check, gather);
    if (with_error && n == (size_t(1) << 20)) {
      AdamGroup fresh(rt, "check", n, 1);
      dp.upload(p);
      ref::RefAdamState st;
      std::vector<double> rp(p.begin(), p.end()), rg(g.begin(), g.end());
      for (int it = 0; it < 10; ++it) {
        const double lr = 1e-3 * std::pow(0.5, it);
        adam.step(fresh, dp, dg, lr);
        ref::adam_step(rp, rg, st, lr);
      }
      std::vector<float> out;
      dp.download(out, n);
      double err = 0;
      for (size_t i = 0; i < n; ++i) err = std::max(err, std::abs(out[i] - rp[i]));
      std::printf("  error vs reference after 10 steps on %zu params: max |p - p_ref| %.3g\n", n, err);
    }
  }
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"ag2gs_bench_losses: image loss and Adam speed against error"};
  int repeats = 5, device = -1;
  bool no_error = false;
  app.add_option("--repeats", repeats, "timed repeats per configuration (median reported)");
  app.add_option("--device", device, "OpenCL device index");
  app.add_flag("--no-error", no_error, "skip the comparison with the double references");
  CLI11_PARSE(app, argc, argv);
  try {
    Runtime rt(device);
    std::printf("device: %s (%s)\n", rt.info().name.c_str(), rt.info().platform.c_str());
    bench_image_loss(rt, repeats, !no_error);
    bench_adam(rt, repeats, !no_error);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "error: %s\n", e.what());
    return 1;
  }
  return 0;
}
