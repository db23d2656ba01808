// baseline: vanilla 3DGS (free Gaussians, no anchors) on a scene directory
// (train/baseline/free_trainer.h), through the same kernels as `ag2gs train`, writing
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
#include "cli/run_driver.h"
#include "cli/run_guard.h"
#include "cli/setting_options.h"
#include "host/device/cl_runtime.h"
#include "host/scene/scene.h"
#include "train/baseline/free_train_settings.h"
#include "train/baseline/free_trainer.h"
#include "train/trainer.h"

namespace fs = std::filesystem;

namespace ag2gs::cli {
namespace {

struct BaselineArgs : RunArgs {
  FreeTrainConfig config;
};

void cmd_baseline(const GlobalOptions& global, BaselineArgs& a) {
  if (a.config.position_lr_init > 0 && !(a.config.position_lr_final > 0))
    throw std::invalid_argument(
        "--lr-position-final must be > 0 when --lr-position is (the rate decays "
        "exponentially from one to the other)");
  a.config.validate();
  if (a.resolution < 1) throw std::invalid_argument("-r must be >= 1 (it divides the camera resolution)");
  refuse_file_as_output_folder(a.out, "-o");
  refuse_output_in_inputs(a.out, a.scene, {}, "-o");
  refuse_model_overwrite(a.out, a.force, "--force to replace it");
  check_model_dir_writable(a.out);
  std::unique_ptr<Scene> scene = open_run_scene(a);

  Runtime rt(global.device);
  rt.set_profiling(a.profile);
  FreeTrainer trainer(rt, *scene, a.config);
  const FreeTrainConfig& c = trainer.config();
  const std::vector<int> test_views = scene->test_views();
  log_run_scene(*scene, rt, a.resolution);
  spdlog::info("free Gaussians (3DGS baseline): {} from the SfM points, extent {:.4g}", trainer.gaussians(),
               trainer.extent());
  spdlog::info("{} iterations, seed {}, SH degree up to {} (+1 every {} iterations), background {}", c.iterations,
               c.seed, c.sh_degree, c.effective_sh_interval(), c.white_background ? "white" : "black");
  const bool densifying = c.densify_every > 0 && c.densify_from <= c.effective_densify_until();
  if (densifying)
    spdlog::info(
        "densification every {} iterations from {} to {} (gradient {:.3g}, clone up to {:.3g} x extent, else split); "
        "prune opacity < {:.3g}; opacity reset {}",
        c.densify_every, c.densify_from, c.effective_densify_until(), c.grad_threshold, c.percent_dense,
        c.prune_opacity, c.opacity_reset_every > 0 ? "every " + std::to_string(c.opacity_reset_every) : "off");
  else
    spdlog::info("densification off");

  RunDriver run(a, *scene, "baseline", c.seed, c.iterations);
  auto evaluate = [&] { return trainer.evaluate(test_views); };
  auto counts = [&] { return nlohmann::json{{"gaussians", trainer.gaussians()}}; };

  // Ctrl-C, SIGTERM and SIGHUP finish the iteration and save the model so far.
  InterruptGuard interrupts;
  run.start(0);
  int skipped = 0;
  double psnr0 = NAN;
  size_t last_added = 0;  // the last densification's net gain (for the ETA)
  const int densify_until = densifying ? std::min(c.effective_densify_until(), c.iterations) : 0;
  for (int it = 0; it < c.iterations; ++it) {
    const int iteration = it + 1;
    const bool log_now = run.log_due(iteration, 0, c.iterations);
    // Tests run inside the step, before its densification and opacity
    // reset, as in `train`.
    const bool test_now = run.test_due(iteration, c.iterations);
    const size_t count_before = trainer.gaussians();
    const auto t_step = std::chrono::steady_clock::now();
    FreeStepStats st = test_now ? trainer.step([&] { run.evaluate(iteration, evaluate, counts()); }) : trainer.step();
    if (!test_now)
      run.record_step_ms(std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t_step).count(),
                         iteration > densify_until);
    if (st.skipped) ++skipped;
    if (st.densified) {
      last_added = trainer.gaussians() > count_before ? trainer.gaussians() - count_before : 0;
      spdlog::info("iteration {}: cloned {}, split {}, pruned {} -> {} Gaussians", st.iteration, st.cloned, st.split,
                   st.pruned, trainer.gaussians());
    }
    if (st.opacity_reset) spdlog::info("iteration {}: opacity reset", st.iteration);
    if (std::isnan(psnr0)) psnr0 = st.psnr;
    run.add_sample(st.loss, st.psnr, st.l1, st.ssim);
    if (log_now) {
      const RunDriver::Means m = run.take_means(st.iteration);
      // The ETA from the recent steps' time and the densification still to come.
      const int growing = std::max(0, densify_until - st.iteration);
      const int rounds_left = c.densify_every > 0 ? growing / c.densify_every : 0;
      const double eta = run.eta_seconds(c.iterations - st.iteration, trainer.gaussians(), growing,
                                         growth_end_tapering(trainer.gaussians(), last_added, rounds_left));
      spdlog::info(
          "it {:>6}/{}  loss {:.5f} (L1 {:.5f}, SSIM {:.4f})  PSNR {:.2f} dB  SH {}  Gaussians {}  {:.1f} it/s  "
          "ETA {}{}",
          st.iteration, c.iterations, m.loss, m.l1, m.ssim, m.psnr, st.sh_degree, trainer.gaussians(), m.its,
          fmt_duration(eta), growing > 0 ? fmt::format(" (densifying until {})", densify_until) : std::string());
    }
    if (InterruptGuard::interrupted() && st.iteration != c.iterations) {
      // The baseline has no checkpoint to resume from: what it keeps is
      // the model so far.
      trainer.save(a.out);
      spdlog::warn(
          "{}: stopped at iteration {} of {}; the model so far is in {} (the baseline cannot resume: "
          "run it again with --force for the full schedule)",
          InterruptGuard::signal_name(), st.iteration, c.iterations, (fs::path(a.out) / "point_cloud.ply").string());
      InterruptGuard::exit_after_saving();
    }
  }
  run.finish_training(rt, c.iterations, skipped, trainer.gaussians(), psnr0, "densification");
  trainer.save(a.out);
  spdlog::info("wrote {} ({} Gaussians, SH degree {})", (fs::path(a.out) / "point_cloud.ply").string(),
               trainer.gaussians(), trainer.active_sh_degree());
  run.metrics()["config"] = c.to_json();
  run.final_test(c.iterations, evaluate, counts());
}

}  // namespace

void register_baseline(CLI::App& app, GlobalOptions& global) {
  auto a = std::make_shared<BaselineArgs>();
  FreeTrainConfig& c = a->config;
  auto* sub = app.add_subcommand("baseline",
                                 "Train the free-Gaussian baseline (vanilla 3DGS densification, no anchors) on a scene "
                                 "directory: writes MODEL_DIR/point_cloud.ply");
  add_scene_options(sub, *a);
  sub->add_flag("--force", a->force, "Replace the model MODEL_DIR holds (refused otherwise)");
  add_setting_options(sub, free_train_settings(), c);
  add_progress_options(sub, *a);
  auto print_config = add_print_config_flag(sub, "train with");
  set_action(sub, [&global, a, print_config] {
    if (*print_config) return print_config_json(a->config);
    cmd_baseline(global, *a);
  });
}

}  // namespace ag2gs::cli
