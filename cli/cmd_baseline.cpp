// baseline: vanilla 3DGS (free Gaussians, no anchors) on a scene directory
// (stages/free_trainer.h), through the same kernels as `ag2gs train`, writing
// MODEL_DIR/point_cloud.ply and, with --eval, MODEL_DIR/metrics.json in the
// trainer's layout.
#include <spdlog/spdlog.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <memory>
#include <nlohmann/json.hpp>
#include <string>

#include "cli/commands.h"
#include "cli/run_guard.h"
#include "host/cl_runtime.h"
#include "host/scene.h"
#include "stages/free_trainer.h"
#include "stages/trainer.h"

namespace fs = std::filesystem;

namespace ag2gs::cli {
namespace {

struct BaselineArgs {
  std::string scene, out;
  std::string sparse;  // --sparse; empty = the scene-folder rule (host/scene.h)
  int resolution = 1;
  bool eval = false;
  int log_every = 100;
  int test_every = 0;
  std::vector<int> test_at;              // --test-at: evaluate at these iterations too
  std::vector<std::string> test_images;  // --test-views: held out instead of every 8th
  bool profile = false;
  bool force = false;  // --force: replace the model MODEL_DIR holds
  FreeTrainConfig config;
};

std::string duration_text(double s) {
  if (!std::isfinite(s) || s < 0) return "?";
  char buf[32];
  if (s >= 3600)
    std::snprintf(buf, sizeof buf, "%dh%02dm", static_cast<int>(s / 3600), static_cast<int>(s / 60) % 60);
  else if (s >= 60)
    std::snprintf(buf, sizeof buf, "%dm%02ds", static_cast<int>(s / 60), static_cast<int>(s) % 60);
  else
    std::snprintf(buf, sizeof buf, "%.1fs", s);
  return buf;
}

void cmd_baseline(const GlobalOptions& global, BaselineArgs& a) {
  a.config.validate();
  if (a.resolution < 1) throw std::invalid_argument("-r must be >= 1 (it divides the camera resolution)");
  refuse_model_overwrite(a.out, a.force, "--force to replace it");
  check_model_dir_writable(a.out);
  SceneOptions so;
  so.resolution = a.resolution;
  so.eval = a.eval || !a.test_images.empty();
  so.test_images = a.test_images;
  so.sparse = a.sparse;
  a.eval = so.eval;
  std::unique_ptr<Scene> scene = Scene::open(a.scene, so);
  scene->require_points();

  Runtime rt(global.device);
  rt.set_profiling(a.profile);
  FreeTrainer trainer(rt, *scene, a.config);
  const FreeTrainConfig& c = trainer.config();
  const std::vector<int> test_views = scene->test_views();
  spdlog::info("device [{}] {}", rt.info().index, rt.info().name);
  spdlog::info("scene {}: {} training views, {} test views, {}x{} (-r {}), {} SfM points", scene->dir(),
               scene->train_views().size(), test_views.size(), scene->views()[0].camera.width,
               scene->views()[0].camera.height, a.resolution, scene->points().size());
  spdlog::info("free Gaussians (3DGS baseline): {} from the SfM points, extent {:.4g}", trainer.gaussians(),
               trainer.extent());
  spdlog::info("{} iterations, seed {}, SH degree up to {} (+1 every {} iterations), background {}", c.iterations,
               c.seed, c.sh_degree, c.effective_sh_interval(), c.white_background ? "white" : "black");
  if (c.densify_every > 0 && c.densify_from <= c.effective_densify_until())
    spdlog::info(
        "densification every {} iterations from {} to {} (gradient {:.3g}, clone up to {:.3g} x extent, else split); "
        "prune opacity < {:.3g}; opacity reset {}",
        c.densify_every, c.densify_from, c.effective_densify_until(), c.grad_threshold, c.percent_dense,
        c.prune_opacity, c.opacity_reset_every > 0 ? "every " + std::to_string(c.opacity_reset_every) : "off");
  else
    spdlog::info("densification off");

  nlohmann::json metrics = {{"scene", scene->dir()},
                            {"resolution", a.resolution},
                            {"seed", c.seed},
                            {"iterations", c.iterations},
                            {"train_views", scene->train_views().size()},
                            {"test_views", test_views.size()},
                            {"model", "baseline"},
                            {"test", nlohmann::json::array()}};
  const fs::path metrics_path = fs::path(a.out) / "metrics.json";
  auto run_eval = [&](int iteration) {
    auto t = std::chrono::steady_clock::now();
    EvalStats ev = trainer.evaluate(test_views);
    double s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t).count();
    spdlog::info("[test] iteration {}: PSNR {:.3f} dB, SSIM {:.4f}, L1 {:.5f} over {} views ({:.2f} s)", iteration,
                 ev.psnr, ev.ssim, ev.l1, ev.views, s);
    metrics["test"].push_back({{"iteration", iteration}, {"psnr", ev.psnr}, {"ssim", ev.ssim}, {"l1", ev.l1}});
    write_json_atomic(metrics_path.string(), metrics);
    return ev;
  };

  // Ctrl-C, SIGTERM and SIGHUP finish the iteration and save the model so far.
  InterruptGuard interrupts;
  const auto t0 = std::chrono::steady_clock::now();
  auto t_last = t0;
  int it_last = 0, skipped = 0;
  double psnr0 = NAN;
  double sum_loss = 0, sum_psnr = 0, sum_l1 = 0, sum_ssim = 0;
  int count = 0;
  for (int it = 0; it < c.iterations; ++it) {
    const bool log_now = a.log_every > 0 && ((it + 1) % a.log_every == 0 || it + 1 == c.iterations || it == 0);
    FreeStepStats st = trainer.step();
    if (st.skipped) ++skipped;
    if (st.densified)
      spdlog::info("iteration {}: cloned {}, split {}, pruned {} -> {} Gaussians", st.iteration, st.cloned, st.split,
                   st.pruned, trainer.gaussians());
    if (st.opacity_reset) spdlog::info("iteration {}: opacity reset", st.iteration);
    if (std::isnan(psnr0)) psnr0 = st.psnr;
    sum_loss += st.loss;
    sum_psnr += st.psnr;
    sum_l1 += st.l1;
    sum_ssim += st.ssim;
    ++count;
    if (log_now) {
      auto now = std::chrono::steady_clock::now();
      const double dt = std::chrono::duration<double>(now - t_last).count();
      const double its = (st.iteration - it_last) / std::max(dt, 1e-9);
      const double elapsed = std::chrono::duration<double>(now - t0).count();
      const double eta = (c.iterations - st.iteration) * elapsed / st.iteration;
      spdlog::info(
          "it {:>6}/{}  loss {:.5f} (L1 {:.5f}, SSIM {:.4f})  PSNR {:.2f} dB  SH {}  Gaussians {}  {:.1f} it/s  "
          "ETA {}",
          st.iteration, c.iterations, sum_loss / count, sum_l1 / count, sum_ssim / count, sum_psnr / count,
          st.sh_degree, trainer.gaussians(), its, duration_text(eta));
      t_last = now;
      it_last = st.iteration;
      sum_loss = sum_psnr = sum_l1 = sum_ssim = 0;
      count = 0;
    }
    const bool test_now = (a.test_every > 0 && st.iteration % a.test_every == 0) ||
                          std::find(a.test_at.begin(), a.test_at.end(), st.iteration) != a.test_at.end();
    if (a.eval && test_now && st.iteration != c.iterations) run_eval(st.iteration);
    if (InterruptGuard::interrupted() && st.iteration != c.iterations) {
      // The baseline has no checkpoint to resume from: what it keeps is
      // the model so far.
      trainer.save(a.out);
      spdlog::warn("{}: stopped at iteration {} of {}; the model so far is in {} (the baseline cannot resume: "
                   "run it again with --force for the full schedule)",
                   InterruptGuard::signal_name(), st.iteration, c.iterations,
                   (fs::path(a.out) / "point_cloud.ply").string());
      InterruptGuard::exit_after_saving();
    }
  }
  const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  spdlog::info("trained {} iterations in {:.1f} s ({:.2f} ms/iteration){}", c.iterations, seconds,
               1000 * seconds / c.iterations, skipped ? fmt::format(", {} steps skipped", skipped) : "");
  if (a.profile) {
    auto timings = rt.take_timings();
    double total = 0;
    for (auto& [k, ms] : timings) total += ms;
    spdlog::info("kernel time per iteration: {:.3f} ms in total", total / c.iterations);
    for (auto& [k, ms] : timings)
      spdlog::info("  {:<17} {:8.3f} ms ({:4.1f}%)", k, ms / c.iterations, total > 0 ? 100 * ms / total : 0.0);
  }
  trainer.save(a.out);
  spdlog::info("wrote {} ({} Gaussians, SH degree {})", (fs::path(a.out) / "point_cloud.ply").string(),
               trainer.gaussians(), trainer.active_sh_degree());
  metrics["train_seconds"] = seconds;
  metrics["ms_per_iteration"] = 1000 * seconds / c.iterations;
  metrics["skipped_steps"] = skipped;
  metrics["gaussians"] = trainer.gaussians();
  metrics["first_train_psnr"] = psnr0;
  metrics["config"] = c.to_json();
  if (a.eval) {
    EvalStats ev = run_eval(c.iterations);
    metrics["final"] = {{"iteration", c.iterations}, {"psnr", ev.psnr}, {"ssim", ev.ssim}, {"l1", ev.l1}};
    write_json_atomic(metrics_path.string(), metrics);
  }
}

}  // namespace

void register_baseline(CLI::App& app, GlobalOptions& global) {
  auto a = std::make_shared<BaselineArgs>();
  FreeTrainConfig& c = a->config;
  auto* sub = app.add_subcommand("baseline",
                                 "Train the free-Gaussian baseline (vanilla 3DGS densification, no anchors) on a scene "
                                 "directory: writes MODEL_DIR/point_cloud.ply");
  sub->add_option("scene_dir", a->scene, "Scene directory (images/, sparse/0/)")->required();
  sub->add_option("-o,--out", a->out, "Model directory to write (created)")->required();
  sub->add_flag("--force", a->force, "Replace the model MODEL_DIR holds (refused otherwise)");
  sub->add_option("--iters", c.iterations, "Training iterations (default 30000)")->check(CLI::Range(1, 100000000));
  sub->add_option("--seed", c.seed, "Random seed: view order and split samples (default 0)")
      ->check(seed_number());
  sub->add_option("--sparse", a->sparse,
                  "COLMAP model folder inside the scene (default: sparse/0/, else sparse/ when it holds the model)");
  sub->add_option("-r,--resolution", a->resolution, "Divide the camera resolution by R (default 1)")
      ->check(CLI::Range(1, 64));
  sub->add_flag("--eval", a->eval, "Hold out every 8th view; test PSNR/SSIM to MODEL_DIR/metrics.json");
  sub->add_flag("--white-bg", c.white_background, "White background instead of black");
  sub->add_option("--sh-degree", c.sh_degree, "Highest SH degree (default 3)")->check(CLI::Range(0, 3));
  sub->add_option("--sh-interval", c.sh_interval,
                  "Iterations per SH degree step (default 0 = min(1000, iters / (sh-degree + 1)), as `train`)")
      ->check(non_negative_number());
  sub->add_option("--lambda-ssim", c.lambda_ssim, "Weight of 1 - SSIM in the loss (default 0.2)")
      ->check(CLI::Range(0.0, 1.0));
  sub->add_option("--lr-position", c.position_lr_init,
                  "Position learning rate at the start, x extent (default 1.6e-4)");
  sub->add_option("--lr-position-final", c.position_lr_final, "Position learning rate at the end, x extent (1.6e-6)");
  sub->add_option("--lr-sh", c.sh_dc_lr, "SH DC learning rate (default 0.0025)");
  sub->add_option("--lr-sh-rest", c.sh_rest_lr, "Higher SH learning rate (default 0.0025 / 20)");
  sub->add_option("--lr-opacity", c.opacity_lr, "Opacity logit learning rate (default 0.05)");
  sub->add_option("--lr-scaling", c.scaling_lr, "Log-scale learning rate (default 0.005)");
  sub->add_option("--lr-rotation", c.rotation_lr, "Rotation learning rate (default 0.001)");
  sub->add_option("--densify-from", c.densify_from, "First densification iteration (default 500)")
      ->check(non_negative_number());
  sub->add_option("--densify-until", c.densify_until, "Last densification iteration (default 0 = half of --iters)")
      ->check(non_negative_number());
  sub->add_option("--densify-every", c.densify_every, "Iterations between densifications (default 100; 0 = off)")
      ->check(non_negative_number());
  sub->add_option("--densify-threshold", c.grad_threshold,
                  "Mean view-space positional gradient (NDC units) above which a Gaussian is cloned or split "
                  "(default 2e-4)");
  sub->add_option("--percent-dense", c.percent_dense,
                  "Clone when the largest scale is at most this x extent, split otherwise (default 0.01)")
      ->check(non_negative_number());
  sub->add_option("--prune-opacity", c.prune_opacity, "Remove Gaussians with opacity below this (default 0.005)")
      ->check(CLI::Range(0.0, 0.999));
  sub->add_option("--opacity-reset-every", c.opacity_reset_every,
                  "Clamp every opacity to 0.01 every N iterations until --densify-until (default 3000; 0 = off)")
      ->check(non_negative_number());
  sub->add_option("--max-screen-size", c.max_screen_size,
                  "After the first opacity reset, remove Gaussians with a radius above this many pixels (default 20; 0 "
                  "= off)")
      ->check(non_negative_number());
  sub->add_option("--max-world-size", c.max_world_size,
                  "After the first opacity reset, remove Gaussians larger than this x extent (default 0.1; 0 = off)")
      ->check(non_negative_number());
  sub->add_option("--log-every", a->log_every, "Progress line every N iterations (default 100; 0 = none)")
      ->check(non_negative_number());
  sub->add_option("--test-at", a->test_at, "With --eval: also test at these iterations (comma-separated)")
      ->delimiter(',');
  sub->add_option("--test-views", a->test_images,
                  "Hold out these images (comma-separated names or stems, e.g. 6.jpg) instead of every 8th; implies "
                  "--eval")
      ->delimiter(',');
  sub->add_option("--test-every", a->test_every, "With --eval: test metrics every N iterations (default 0 = end only)")
      ->check(non_negative_number());
  sub->add_flag("--profile", a->profile, "Time every kernel and print the per-iteration breakdown");
  set_action(sub, [&global, a] { cmd_baseline(global, *a); });
}

}  // namespace ag2gs::cli
