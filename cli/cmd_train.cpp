// train: stages 1 (appearance + mask losses), 2 (propagation loss over the
// anchor graph) and 3 (clusters and their language features) of the anchor
// model on a scene directory (train/trainer.h), writing MODEL_DIR/model.ag2gs,
// checkpoint.ag2gs and point_cloud.ply. --stages picks a subset; without
// stage 1 the run continues from MODEL_DIR's checkpoint / model.
#include <spdlog/spdlog.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <memory>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>

#include "cli/run_guard.h"
#include "cli/train_command.h"
#include "host/device/cl_runtime.h"
#include "host/io/model_io.h"
#include "train/divergence_guard.h"
#include "train/eta.h"

namespace fs = std::filesystem;

namespace ag2gs::cli {

void cmd_train(const GlobalOptions& global, TrainArgs& a) {
  // Ctrl-C, SIGTERM and SIGHUP from here on: before training nothing is
  // written and the run stops there; during training the iteration finishes
  // and a checkpoint is saved; during stage 3 it finishes (its model file is
  // replaced whole) and the run exits with the signal's status.
  InterruptGuard interrupts;
  check_train_args(a);
  if (a.stages == std::vector<int>{3}) {
    if (a.view)
      throw std::invalid_argument(
          "--view shows a model while it trains; --stages 3 alone trains none: look at the "
          "result with `ag2gs view " +
          a.out + "`");
    return stage3_only(global, a);
  }
  std::unique_ptr<Scene> scene = prepare_run(a);

  Runtime rt(global.device);
  rt.set_profiling(a.profile);
  // Stage 3 reads the saved model: the trainer's device buffers (parameters,
  // optimiser moments, losses, the graph) go before it.
  auto trainer_owner = std::make_unique<Trainer>(rt, *scene, a.config);
  Trainer& trainer = *trainer_owner;
  const TrainConfig& c = trainer.config();
  if (a.resume) resume_trainer(trainer, a);
  // The last iteration this run trains to.
  const int it_end = has_stage(a, 2) ? c.total_iterations() : std::min(c.iterations, c.total_iterations());
  if (has_stage(a, 2) && c.effective_prop_iters() > 0)
    spdlog::info("stage 2: {} iterations after stage 1 with {} L_prop (tau {}) over the anchor graph",
                 c.effective_prop_iters(), c.w_prop, c.prop_tau);
  const std::vector<int> test_views = scene->test_views();
  log_run_scene(*scene, rt, a.resolution);
  log_training_plan(trainer, *scene);

  RunDriver run(a, *scene, "anchors", c.seed, c.iterations);
  auto evaluate = [&] { return trainer.evaluate(test_views); };
  auto counts = [&] { return nlohmann::json{{"anchors", trainer.anchors()}, {"gaussians", trainer.gaussians()}}; };

  if (a.resume) run.metrics()["resumed_at"] = trainer.iteration();
  const int it_start = trainer.iteration();
  trainer.set_run_record(run_record(a));
  if (InterruptGuard::interrupted()) {
    spdlog::warn("{} before training started: stopped before writing anything to {}", InterruptGuard::signal_name(),
                 a.out);
    InterruptGuard::exit_after_saving();
  }
  // A save before the end replaces the model files; a metrics.json already in
  // MODEL_DIR then describes a model that is gone (a run started with
  // --force, or one resumed past its end), so it goes with the first save.
  bool stale_metrics_checked = false;
  auto save_mid_run = [&] {
    trainer.save(a.out);
    if (stale_metrics_checked) return;
    stale_metrics_checked = true;
    const fs::path metrics = fs::path(a.out) / "metrics.json";
    std::error_code ec;
    if (fs::remove(metrics, ec))
      spdlog::info("removed {}: it described the model these files replace (a new one is written at the end)",
                   metrics.string());
  };
  double eta_s = -1;  // the last progress line's ETA, for the viewer
  auto live_status = [&](int iteration, bool stage2, double psnr) {
    return nlohmann::json{{"iteration", iteration}, {"iterations", it_end},         {"stage", stage2 ? 2 : 1},
                          {"psnr", psnr},           {"anchors", trainer.anchors()}, {"gaussians", trainer.gaussians()},
                          {"eta_s", eta_s}};
  };
  std::unique_ptr<LiveView> view;
  if (a.view) view = std::make_unique<LiveView>(global, a, trainer, live_status(it_start, it_start >= c.iterations, 0));
  run.start(it_start);
  int skipped = 0;
  double psnr0 = NAN;
  StepTerms terms;  // since the last progress line
  double stage1_end_s = -1;
  // Divergence warnings (train/divergence_guard.h), also in metrics.json.
  DivergenceGuard guard;
  auto warn = [&](const std::optional<std::string>& w) {
    if (w) run.warn(*w);
  };
  const GrowthConfig growth_schedule = c.growth_config(scene->train_views().size());
  const size_t gaussians_at_start = trainer.gaussians();
  int rounds_done = 0;
  size_t gaussians_before_round = trainer.gaussians();
  for (int it = it_start; it < it_end; ++it) {
    const int iteration = it + 1;
    const bool log_now = run.log_due(iteration, it_start, it_end);
    if (it == c.iterations) {
      stage1_end_s = run.train_seconds();
      spdlog::info("stage 2 from iteration {}: {} anchors", it + 1, trainer.anchors());
    }
    // Tests run inside the step, before its growing round and opacity
    // reset (as 3DGS does), so a test at a reset iteration is meaningful.
    const bool test_now = run.test_due(iteration, it_end);
    const auto t_step = std::chrono::steady_clock::now();
    StepStats st =
        test_now ? trainer.step(log_now, [&] { run.evaluate(iteration, evaluate, counts()); }) : trainer.step(log_now);
    if (!test_now)
      run.record_step_ms(std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t_step).count(),
                         iteration > c.effective_grow_until() && iteration <= c.iterations);
    if (st.skipped) ++skipped;
    log_step_events(st, trainer, it == c.iterations);
    if (!st.stage2) {
      warn(guard.step(st.iteration, st.psnr, st.loss - (st.with_offset_loss ? c.w_offset * st.offset_reg : 0)));
      if (growth_schedule.every > 0 && growth_schedule.due(st.iteration)) {
        warn(guard.round(st.iteration, gaussians_before_round, trainer.gaussians()));
        ++rounds_done;
      }
      gaussians_before_round = trainer.gaussians();
    }
    if (std::isnan(psnr0)) psnr0 = st.psnr;
    if (view) {
      view->live.set_status(live_status(st.iteration, st.stage2, st.psnr));
      if (view->live.snapshot_wanted() && st.iteration != it_end) view->live.publish(trainer.model_archive(), false);
      view->live.wait_while_paused();
    }
    run.add_sample(st.loss - (st.with_offset_loss ? c.w_offset * st.offset_reg : 0), st.psnr, st.l1, st.ssim);
    if (const TrainProgressHook& hook = train_progress_hook()) {
      nlohmann::json progress = live_status(st.iteration, st.stage2, st.psnr);
      progress["loss"] = st.loss;
      progress["l1"] = st.l1;
      progress["ssim"] = st.ssim;
      if (!hook(progress)) InterruptGuard::request_stop();
    }
    terms.add(st);
    if (log_now) eta_s = log_progress(run, trainer, st, it_end, terms, gaussians_at_start, rounds_done);
    if (InterruptGuard::interrupted() && st.iteration != it_end) {
      save_mid_run();
      // The checkpoint holds every setting (stages included): the command
      // needs only what locates the scene and the device.
      spdlog::warn("{}: checkpoint at iteration {} of {} in {}; continue with\n  ag2gs {}train {} -o {}{} --resume",
                   InterruptGuard::signal_name(), st.iteration, it_end, a.out,
                   global.device >= 0 ? fmt::format("--device {} ", global.device) : "", a.scene, a.out,
                   a.sparse.empty() ? "" : " --sparse " + a.sparse);
      view.reset();
      InterruptGuard::exit_after_saving();
    }
    if (a.save_every > 0 && st.iteration % a.save_every == 0 && st.iteration != it_end) {
      save_mid_run();
      spdlog::info("checkpoint at iteration {} in {}", st.iteration, a.out);
    }
  }
  const double seconds = run.finish_training(rt, it_end - it_start, skipped, trainer.gaussians(), psnr0);
  trainer.save(a.out);
  spdlog::info("wrote {} and {} ({} anchors, {} Gaussians, SH degree {})", (fs::path(a.out) / "model.ag2gs").string(),
               (fs::path(a.out) / "point_cloud.ply").string(), trainer.anchors(), trainer.gaussians(),
               trainer.active_sh_degree());
  spdlog::info("{}", trainer.last_ply().describe());
  run.metrics()["anchors"] = trainer.anchors();
  run.final_test(it_end, evaluate, counts());
  trainer_owner.reset();
  run.metrics()["stages"] = final_stages(rt, *scene, a, seconds, stage1_end_s, it_start);
  run.write_metrics();
  end_run(a, view);
}

}  // namespace ag2gs::cli
