// train: stages 1 (appearance + mask losses), 2 (propagation loss over the
// anchor graph) and 3 (clusters and their language features) of the anchor
// model on a scene directory (stages/trainer.h), writing MODEL_DIR/model.ag2gs,
// checkpoint.ag2gs and point_cloud.ply. --stages picks a subset; without
// stage 1 the run continues from MODEL_DIR's checkpoint / model.
#include <spdlog/spdlog.h>
#include <sys/resource.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <csignal>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <limits>
#include <memory>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <thread>

#include "cli/commands.h"
#include "cli/run_driver.h"
#include "cli/run_guard.h"
#include "cli/viewer/view_server.h"
#include "host/device/cl_runtime.h"
#include "host/io/model_io.h"
#include "host/scene/scene.h"
#include "stages/divergence_guard.h"
#include "stages/language.h"
#include "stages/trainer.h"

namespace fs = std::filesystem;

namespace ag2gs::cli {
namespace {

struct TrainArgs : RunArgs {
  int save_every = 0;
  bool resume = false;
  std::vector<int> stages{1, 2, 3};  // --stages
  bool stages_given = false;         // --stages was on the command line
  std::string preset = "default";    // --preset
  Stage3Config stage3;
  TrainConfig config;
  bool view = false;  // --view: serve the viewer while training
  ServeOptions serve;
};

// `train --view`: the viewer's server on its own runtime and thread, showing
// snapshots of the model as it trains (cli/viewer/view_server.h). Stopped
// and joined when it goes out of scope, however the run ends.
struct LiveView {
  LiveView(const GlobalOptions& global, const TrainArgs& a, Trainer& trainer, const nlohmann::json& status)
      : rt(global.device),
        live(rt, options(a)),
        server([this]() -> ViewSession& { return live.session(); }, &live, a.serve) {
    live.set_status(status);  // before the first request can come
    live.publish(trainer.model_archive(), false);
    url_port = server.bind(a.out + " while it trains");
    thread = std::thread([this] { server.run(); });
  }
  ~LiveView() {
    server.stop();
    if (thread.joinable()) thread.join();
  }
  static ViewOptions options(const TrainArgs& a) {
    ViewOptions o;
    o.model = a.out;
    o.scene = a.scene;
    o.sparse = a.sparse;
    o.resolution = a.resolution;
    return o;
  }
  Runtime rt;
  LiveTraining live;
  ViewServer server;
  int url_port = 0;
  std::thread thread;
};

// Presets. The default (also called "appearance") is the measured setting
// for photographed scenes: children that may outgrow their voxel (scale cap
// 64), 2 per anchor placed on the SfM points, the points seeding the top
// layer and the next (so thin objects get anchors of their own), growth of
// at most 10% of the anchors per round, recycling of transparent children,
// faster offset and scale rates; with the library's defaults for the rest
// (the voxel chosen from the scene, the Gaussian budget). "paper" is the
// method as published: 200 top-layer cells, 5 children inside their voxels,
// one seeded layer, no growth budget. A setting the user gives on the
// command line wins. A resumed run takes its settings from the checkpoint, so
// a preset is applied only when given explicitly there.
void apply_preset(const CLI::App& sub, TrainArgs& a, bool log = true) {
  const bool continues = a.resume || std::find(a.stages.begin(), a.stages.end(), 1) == a.stages.end();
  if (continues && sub.count("--preset") == 0) return;
  TrainConfig& c = a.config;
  // The values live in the library (TrainConfig::preset); a flag given on
  // the command line wins over them.
  const TrainConfig p = TrainConfig::preset(a.preset);
  auto unless_given = [&sub](const char* flag, auto& field, auto value) {
    if (sub.count(flag) == 0) field = value;
  };
  unless_given("--top-cells", c.anchors.top_cells, p.anchors.top_cells);
  unless_given("--max-gaussians", c.max_gaussians, p.max_gaussians);
  unless_given("--downscales", c.downscales, p.downscales);
  unless_given("--sky-degree", c.sky_degree, p.sky_degree);
  unless_given("--scale-cap", c.anchors.scale_cap, p.anchors.scale_cap);
  unless_given("--children", c.anchors.children, p.anchors.children);
  unless_given("--init-layers", c.anchors.init_layers, p.anchors.init_layers);
  unless_given("--grow-budget", c.grow_budget, p.grow_budget);
  unless_given("--init-children-at-points", c.anchors.init_children_at_points, p.anchors.init_children_at_points);
  unless_given("--recycle-opacity", c.recycle_opacity, p.recycle_opacity);
  unless_given("--final-prune-opacity", c.final_prune_opacity, p.final_prune_opacity);
  unless_given("--prune-importance", c.prune_importance, p.prune_importance);
  unless_given("--lr-offset", c.offset_lr_init, p.offset_lr_init);
  unless_given("--lr-scaling", c.scaling_lr, p.scaling_lr);
  unless_given("--grow-min-seen", c.grow_min_seen, p.grow_min_seen);
  unless_given("--grow-split", c.grow_split, p.grow_split);
  unless_given("--far-shell", c.far_shell, p.far_shell);
  if (!log) return;
  if (a.preset == "paper") {
    spdlog::info(
        "preset paper: --top-cells {} --children {} --init-layers {} --scale-cap {} --grow-budget {} --max-gaussians "
        "{} --sky-degree {}",
        c.anchors.top_cells, c.anchors.children, c.anchors.init_layers, c.anchors.scale_cap, c.grow_budget,
        c.max_gaussians, c.sky_degree);
    return;
  }
  spdlog::info(
      "preset {}: --scale-cap {} --children {} --init-layers {} --{} --grow-budget {} --grow-min-seen {} "
      "--grow-split {} --far-shell {} --recycle-opacity {} --final-prune-opacity {} --prune-importance {} "
      "--lr-offset {} --lr-scaling {}",
      a.preset, c.anchors.scale_cap, c.anchors.children, c.anchors.init_layers,
      c.anchors.init_children_at_points ? "init-children-at-points" : "init-children-random", c.grow_budget,
      c.grow_min_seen, c.grow_split, c.far_shell, c.recycle_opacity, c.final_prune_opacity, c.prune_importance,
      c.offset_lr_init, c.scaling_lr);
}

bool has_stage(const TrainArgs& a, int s) {
  return std::find(a.stages.begin(), a.stages.end(), s) != a.stages.end();
}

// The stage-3 summary line, after training or for --stages 3 alone.
void log_stage3(const Stage3Summary& s, const Stage3Config& config) {
  spdlog::info(
      "stage 3: {} clusters of {} anchors ({} components, {} anchors in clusters under {} skipped), {} with "
      "a language feature{}",
      s.clusters, s.anchors, s.components, s.skipped_anchors, config.cluster.min_cluster_size, s.with_language,
      s.language ? "" : " (scene without CLIP features: none attached)");
}

// --stages 3 alone: stage 3 on MODEL_DIR/model.ag2gs, at the resolution and
// split it was trained with.
void stage3_only(const GlobalOptions& global, TrainArgs& a) {
  const std::string path = (fs::path(a.out) / "model.ag2gs").string();
  if (!fs::exists(path))
    throw std::runtime_error("--stages 3: no model " + path + "; train stages 1 and 2 into " + a.out + " first");
  const ModelArchive archive = read_model_archive(path);
  check_model_archive(archive);  // before the scene is read: a damaged model is named first
  const nlohmann::json tr = archive.meta.value("train", nlohmann::json::object());
  SceneOptions so;
  so.resolution = a.resolution != 1 ? a.resolution : recorded_resolution(tr, path);
  so.eval = a.eval || tr.value("eval_split", false);
  so.test_images = a.test_images;
  so.sparse = a.sparse;
  std::unique_ptr<Scene> scene = Scene::open(a.scene, so);
  Runtime rt(global.device);
  const Stage3Summary s = run_stage3_on_model(rt, *scene, a.out, scene->train_views(), a.stage3);
  log_stage3(s, a.stage3);
  spdlog::info("stage 3: {:.1f} s; wrote {}", s.total_ms / 1000, path);
  if (InterruptGuard::interrupted()) {
    spdlog::warn("{} during stage 3: it finished and {} is complete; exiting with status {}",
                 InterruptGuard::signal_name(), path, InterruptGuard::exit_code());
    InterruptGuard::exit_after_saving();
  }
}

// The settings outside TrainConfig that shape a run's files: the stages and
// stage 3's. They go into the checkpoint (Trainer::set_run_record), so that
// `--resume` alone finishes the run as it was started.
nlohmann::json run_record(const TrainArgs& a) {
  const Stage3Config& s = a.stage3;
  return {{"stages", a.stages},
          {"stage3",
           {{"cluster_distance", s.cluster.max_distance},
            {"min_cluster_size", s.cluster.min_cluster_size},
            {"match_score", s.language.min_score},
            {"match_softmax", s.language.softmax_scale},
            {"instance_fraction", s.language.instance_fraction}}}};
}

// Takes the stages (unless --stages was given) and the stage-3 settings
// (unless one was given) from a checkpoint's run record.
void adopt_run_record(const nlohmann::json& run, TrainArgs& a) {
  if (!run.is_object()) return;  // a checkpoint from before the record
  if (!a.stages_given && run.contains("stages")) a.stages = run["stages"].get<std::vector<int>>();
  const nlohmann::json given = run_record(a)["stage3"];
  const nlohmann::json defaults = run_record(TrainArgs{})["stage3"];
  if (given != defaults || !run.contains("stage3")) return;
  const nlohmann::json& s3 = run["stage3"];
  Stage3Config& s = a.stage3;
  s.cluster.max_distance = s3.value("cluster_distance", s.cluster.max_distance);
  s.cluster.min_cluster_size = s3.value("min_cluster_size", s.cluster.min_cluster_size);
  s.language.min_score = s3.value("match_score", s.language.min_score);
  s.language.softmax_scale = s3.value("match_softmax", s.language.softmax_scale);
  s.language.instance_fraction = s3.value("instance_fraction", s.language.instance_fraction);
}

// --resume: the run's config comes from the checkpoint; a setting given on
// the command line (one that differs from the default) must agree with it.
void adopt_checkpoint_config(TrainArgs& a) {
  const std::string path = Trainer::checkpoint_path(a.out);
  if (!fs::exists(path))
    throw std::runtime_error("--resume: no checkpoint " + path + "; train without --resume to start afresh");
  const ModelArchive archive = read_model_archive(path);
  if (!archive.meta.contains("checkpoint") || !archive.meta["checkpoint"].contains("config"))
    throw std::runtime_error("--resume: " + path + " holds no training state (not written by ag2gs train)");
  const nlohmann::json& ck = archive.meta["checkpoint"];
  const TrainConfig saved = TrainConfig::from_json(ck["config"]);
  const std::vector<std::string> given = config_differences(a.config.to_json(), TrainConfig{}.to_json());
  std::string clash;
  for (const std::string& d : config_differences(a.config.to_json(), saved.to_json()))
    for (const std::string& g : given)
      if (d.substr(0, d.find(' ')) == g.substr(0, g.find(' '))) clash += "\n  " + d;
  const nlohmann::json& sc = ck.value("scene", nlohmann::json::object());
  if (a.resolution != 1 && sc.value("resolution", 1) != a.resolution)
    clash += "\n  -r (" + std::to_string(a.resolution) + " vs " + std::to_string(sc.value("resolution", 1)) + ")";
  if (clash.size())
    throw std::runtime_error("--resume: these settings differ from the checkpoint " + path +
                             " (command line vs checkpoint); drop them or start a new model folder:" + clash);
  a.config = saved;
  adopt_run_record(ck.value("run", nlohmann::json()), a);
  a.resolution = sc.value("resolution", a.resolution);
  a.eval = a.eval || sc.value("eval_split", false);
}

void cmd_train(const GlobalOptions& global, TrainArgs& a) {
  // Ctrl-C, SIGTERM and SIGHUP from here on: before training nothing is
  // written and the run stops there; during training the iteration finishes
  // and a checkpoint is saved; during stage 3 it finishes (its model file is
  // replaced whole) and the run exits with the signal's status.
  InterruptGuard interrupts;
  std::sort(a.stages.begin(), a.stages.end());
  a.stages.erase(std::unique(a.stages.begin(), a.stages.end()), a.stages.end());
  if (a.stages.empty()) throw std::invalid_argument("--stages needs at least one of 1, 2, 3");
  if (has_stage(a, 1) && has_stage(a, 3) && !has_stage(a, 2) && a.config.prop_iters != 0)
    throw std::invalid_argument("--stages 1,3 skips stage 2; give --prop-iters 0 for a model without stage 2");
  a.stage3.cluster.validate();
  a.stage3.language.validate();
  refuse_file_as_output_folder(a.out, "-o");
  refuse_output_in_inputs(a.out, a.scene, {}, "-o");
  if (a.config.offset_lr_init > 0 && !(a.config.offset_lr_final > 0))
    throw std::invalid_argument(
        "--lr-offset-final must be > 0 when --lr-offset is (the rate decays "
        "exponentially from one to the other)");
  if (a.stages == std::vector<int>{3}) {
    if (a.view)
      throw std::invalid_argument(
          "--view shows a model while it trains; --stages 3 alone trains none: look at the "
          "result with `ag2gs view " +
          a.out + "`");
    return stage3_only(global, a);
  }
  // Without stage 1 the run continues from the checkpoint.
  if (!has_stage(a, 1)) a.resume = true;
  // A new model never replaces one by accident.
  if (!a.resume)
    refuse_model_overwrite(a.out, a.force, "--resume to continue it from its checkpoint, --force to start over");
  if (a.resume) adopt_checkpoint_config(a);
  a.config.validate();
  if (a.resolution < 1) throw std::invalid_argument("-r must be >= 1 (it divides the camera resolution)");
  // Before anything slow: a run must not fail at its end for want of a place to write.
  check_model_dir_writable(a.out);
  std::unique_ptr<Scene> scene = open_run_scene(a);
  // Without SAM masks the features never train: nothing to propagate or cluster.
  const bool semantics = scene->semantics() != SemanticsKind::none;
  if (!semantics && !a.resume && (has_stage(a, 2) || has_stage(a, 3)) &&
      (a.config.effective_prop_iters() > 0 || has_stage(a, 3))) {
    spdlog::info("scene {} has no SAM masks: stages 2 and 3 skipped (no semantic features to propagate or cluster)",
                 scene->dir());
    a.config.prop_iters = 0;
    a.stages.erase(std::remove_if(a.stages.begin(), a.stages.end(), [](int s) { return s != 1; }), a.stages.end());
  }

  Runtime rt(global.device);
  rt.set_profiling(a.profile);
  Trainer trainer(rt, *scene, a.config);
  const TrainConfig& c = trainer.config();
  if (a.resume) {
    trainer.resume(a.out);
    spdlog::info("resuming {} at iteration {} of {}", Trainer::checkpoint_path(a.out), trainer.iteration(),
                 c.total_iterations());
    if (!has_stage(a, 1) && trainer.iteration() < c.iterations)
      throw std::runtime_error("--stages without 1: the checkpoint " + Trainer::checkpoint_path(a.out) +
                               " is at iteration " + std::to_string(trainer.iteration()) + ", stage 1 ends at " +
                               std::to_string(c.iterations) + "; finish it with --resume");
  }
  // The last iteration this run trains to.
  const int it_end = has_stage(a, 2) ? c.total_iterations() : std::min(c.iterations, c.total_iterations());
  if (has_stage(a, 2) && c.effective_prop_iters() > 0)
    spdlog::info("stage 2: {} iterations after stage 1 with {} L_prop (tau {}) over the anchor graph",
                 c.effective_prop_iters(), c.w_prop, c.prop_tau);
  const std::vector<int> test_views = scene->test_views();
  log_run_scene(*scene, rt, a.resolution);
  {
    std::string per_layer;
    for (size_t l = 0; l < trainer.init_stats().anchors_per_layer.size(); ++l)
      per_layer += (l ? "/" : "") + std::to_string(trainer.init_stats().anchors_per_layer[l]);
    spdlog::info("anchors: {} (per layer {}), {} Gaussians ({} children each); {}", trainer.anchors(), per_layer,
                 trainer.gaussians(), c.anchors.children,
                 trainer.voxel_choice().describe(c.anchors.layers, c.anchors.layer_ratio));
  }
  spdlog::info("{} iterations, seed {}, SH degree up to {} (+1 every {} iterations), background {}{}", c.iterations,
               c.seed, c.anchors.sh_degree, c.effective_sh_interval(), c.white_background ? "white" : "black",
               c.sky_degree >= 0 ? fmt::format(" (the start of a learned sky of SH degree {})", c.sky_degree)
               : c.sky_degree == TrainConfig::kSkyAuto ? " (or a learned sky, chosen from the scene below)"
                                                       : "");
  if (c.downscales > 0)
    spdlog::info(
        "coarse to fine: images / {} at first, resolution doubled every {} iterations (full from iteration {}; "
        "low-pass {:.3g} px^2 at the coarsest level{})",
        1 << c.downscales, c.res_schedule, c.downscales * c.res_schedule, c.lowpass_at_level(c.downscales),
        scene->semantics() != SemanticsKind::none ? "; mask-loss iterations always full" : "");
  if (c.grow_every > 0 && c.grow_from <= c.effective_grow_until()) {
    const GrowthConfig g = c.growth_config(scene->train_views().size());
    spdlog::info(
        "anchor growing{} every {} iterations from {} to {} (threshold {:.3g}, for children seen in at least {:.0f}% "
        "of a round's views; {}); pruning: opacity < {:.3g}{}, unseen {}{}",
        c.anchors.layers > 1 ? "" : " (one layer: pruning only)", c.grow_every, c.grow_from, c.effective_grow_until(),
        c.grow_threshold, 100 * c.grow_min_seen,
        c.grow_split > 0 ? fmt::format("split: children {:g} finer voxels wide also ask at +-1 sigma, and their "
                                       "anchors start at their scale / 1.6",
                                       c.grow_split)
                         : std::string("no split: one finer anchor at a child's mean, grown children start small"),
        c.prune_opacity, c.prune_opacity > 0 ? "" : " (off)",
        g.prune_unseen ? "in the last " + std::to_string(g.unseen_window) + " views" : std::string("off"),
        (c.prune_importance > 0
             ? fmt::format("; at iteration {}: the anchors drawing least, up to {:.3g}% of the training views' "
                           "blending weight",
                           c.effective_prune_importance_at(), 100 * c.prune_importance)
             : std::string()) +
            (c.final_prune_opacity > 0
                 ? fmt::format("; after iteration {}: mean opacity < {:.3g}", c.iterations, c.final_prune_opacity)
                 : std::string()));
    spdlog::info("growth budget: {} per round{}, at most {} Gaussians{}",
                 c.grow_budget > 0 ? fmt::format("{:.0f}% of the anchors", 100 * c.grow_budget) : "no limit",
                 c.grow_budget > 0 ? " (at least 64)" : "",
                 trainer.max_gaussians() > 0 ? std::to_string(trainer.max_gaussians()) : "no limit",
                 c.max_gaussians == -1 ? " (the pixels of a training view, at least 2x the initial count; "
                                         "--max-gaussians)"
                                       : "");
  } else {
    spdlog::info("anchor growing off");
  }
  if (scene->semantics() != SemanticsKind::none && (c.w_is > 0 || c.w_ic > 0))
    spdlog::info("mask losses from iteration {}: {} L_is + {} L_ic on the rendered features{}, training {}",
                 c.effective_mask_from(), c.w_is, c.w_ic, c.mask_alpha_normalise ? " / alpha" : "",
                 c.mask_geometry ? "every parameter" : "the semantic features only");

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
  // Running means of the anchor trainer's own terms since the last progress line.
  double sum_dist = 0, sum_is = 0, sum_ic = 0, sum_isect = 0, sum_prop = 0;
  int count = 0, count_masks = 0, count_prop = 0;
  double stage1_end_s = -1;
  // Divergence warnings (stages/divergence_guard.h), also in metrics.json.
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
    if (st.stage2 && it == c.iterations)
      spdlog::info("stage 2: anchor graph with {} edges (mean degree {:.2f})", trainer.graph().edges(),
                   trainer.anchors() ? 2.0 * trainer.graph().edges() / trainer.anchors() : 0.0);
    if (st.stage2) {
      sum_prop += st.l_prop;
      ++count_prop;
    }
    if (st.skipped) ++skipped;
    if (st.opacity_reset) spdlog::info("iteration {}: opacities reset to at most 0.01", st.iteration);
    if (st.grown > 0 || st.pruned > 0)
      spdlog::info("iteration {}: grew {} anchors{}, pruned {} -> {} anchors, {} Gaussians", st.iteration, st.grown,
                   st.over_budget > 0 ? fmt::format(" ({} more asked, over the budget)", st.over_budget) : "",
                   st.pruned, trainer.anchors(), trainer.gaussians());
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
    sum_dist += st.distortion;
    sum_isect += static_cast<double>(st.intersections);
    if (st.with_masks) {
      sum_is += st.l_is;
      sum_ic += st.l_ic;
      ++count_masks;
    }
    ++count;
    if (log_now) {
      const RunDriver::Means m = run.take_means(st.iteration);
      // The ETA from the recent steps' time (evaluations left out) and the
      // growth still to come.
      const int grow_until = c.grow_every > 0 ? std::min(c.effective_grow_until(), c.iterations) : 0;
      const int growing = std::max(0, grow_until - st.iteration);
      const int rounds_left = c.grow_every > 0 ? growing / c.grow_every : 0;
      const double eta = run.eta_seconds(it_end - st.iteration, trainer.gaussians(), growing,
                                         growth_end_geometric(trainer.gaussians(), gaussians_at_start, rounds_done,
                                                              rounds_left, trainer.max_gaussians()));
      eta_s = eta;
      const std::string eta_text =
          fmt_duration(eta) + (growing > 0 ? fmt::format(" (growing until {})", grow_until) : std::string());
      std::string mask_terms =
          count_masks > 0 ? fmt::format(", L_is {:.4f}, L_ic {:.4f}", sum_is / count_masks, sum_ic / count_masks)
                          : std::string();
      if (count_prop > 0) mask_terms += fmt::format(", L_prop {:.3e}", sum_prop / count_prop);
      spdlog::info(
          "it {:>6}/{}  loss {:.5f} (L1 {:.5f}, SSIM {:.4f}, dist {:.3e}, L_in {:.4f}{})  PSNR {:.2f} dB  SH {}  "
          "anchors {}  Gaussians {}  {:.1f} it/s  ETA {}",
          st.iteration, it_end, m.loss + c.w_offset * st.offset_reg, m.l1, m.ssim, sum_dist / count, st.offset_reg,
          mask_terms, m.psnr, st.sh_degree, trainer.anchors(), trainer.gaussians(), m.its, eta_text);
      spdlog::debug("  {:.0f} tile intersections per iteration", sum_isect / count);
      sum_dist = sum_is = sum_ic = sum_isect = sum_prop = 0;
      count = count_masks = count_prop = 0;
    }
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
  // Stage times of this run (training time without evaluations).
  double s1 = seconds, s2 = 0;
  if (stage1_end_s >= 0) {
    s1 = stage1_end_s;
    s2 = seconds - stage1_end_s;
  } else if (it_start >= c.iterations) {
    s1 = 0;
    s2 = seconds;
  }
  nlohmann::json stages = {{"stage1_seconds", s1}, {"stage2_seconds", s2}};
  if (has_stage(a, 3)) {
    const Stage3Summary s3 = run_stage3_on_model(rt, *scene, a.out, scene->train_views(), a.stage3);
    log_stage3(s3, a.stage3);
    stages["stage3_seconds"] = s3.total_ms / 1000;
    stages["clusters"] = s3.clusters;
    stages["clusters_with_language"] = s3.with_language;
    stages["skipped_anchors"] = s3.skipped_anchors;
    spdlog::info("stage times: stage 1 {:.1f} s, stage 2 {:.1f} s, stage 3 {:.1f} s (cluster {:.1f} ms)", s1, s2,
                 s3.total_ms / 1000, s3.cluster_ms);
  } else {
    spdlog::info("stage times: stage 1 {:.1f} s, stage 2 {:.1f} s", s1, s2);
  }
  run.metrics()["stages"] = stages;
  run.write_metrics();
  if (view && !InterruptGuard::interrupted()) {
    // The final model (with stage 3's clusters): selection works again.
    InterruptGuard::set_stop_message("\nstopping the viewer (training is done and saved)\n");
    view->live.publish(read_model_archive((fs::path(a.out) / "model.ag2gs").string()), true);
    spdlog::info("training done; the viewer keeps serving the final model at port {} until Ctrl-C", view->url_port);
    view->thread.join();
    spdlog::info("stopped ({})", InterruptGuard::signal_name());
    return;  // training completed: status 0
  }
  // A stop the caller asked for at the last iteration came after the work
  // was done: the run ends as a finished one. A signal still sets the status.
  if (InterruptGuard::signalled()) {
    spdlog::warn("{} during the last stage: it finished and its files are complete; exiting with status {}",
                 InterruptGuard::signal_name(), InterruptGuard::exit_code());
    view.reset();  // the viewer's thread joined before the process exits
    InterruptGuard::exit_after_saving();
  }
}

}  // namespace

void register_train(CLI::App& app, GlobalOptions& global) {
  auto a = std::make_shared<TrainArgs>();
  TrainConfig& c = a->config;
  auto* sub = app.add_subcommand("train",
                                 "Train the anchor model on a scene directory: stage 1 (appearance, masks), stage 2 "
                                 "(propagation loss), stage 3 (clusters, language features); writes "
                                 "MODEL_DIR/model.ag2gs and MODEL_DIR/point_cloud.ply");
  add_scene_options(sub, *a);
  sub->add_option("--iters", c.iterations, "Training iterations (default 30000)")->check(CLI::Range(1, 100000000));
  sub->add_option("--seed", c.seed, "Random seed: anchor init and view order (default 0)")->check(seed_number());
  sub->add_option("--sh-degree", c.anchors.sh_degree, "Highest SH degree (default 3)")->check(CLI::Range(0, 3));
  sub->add_option("--sh-interval", c.sh_interval,
                  "Iterations per SH degree step (default 0 = min(1000, iters / (sh-degree + 1)))")
      ->check(non_negative_number());
  sub->add_flag("--white-bg", c.white_background, "White background instead of black (with a sky: its start)");
  sub->add_option("--sky-degree", c.sky_degree,
                  "The sky behind the Gaussians: a colour per viewing direction, spherical harmonics of this degree "
                  "(0 = one learned colour; -1 = none, a fixed black or white background, as --preset paper; default "
                  "-2 = from the scene: 3 when at least 5% of the training pixels have no SfM point near them, else "
                  "-1)")
      ->check(CLI::Range(-2, 3));
  sub->add_option("--far-shell", c.far_shell,
                  "Where the pixels without SfM points show surfaces rather than an open sky (a degree-3 sky fits "
                  "them with an RMS error above 0.04, as a room's far walls), seed anchors from them on a sphere "
                  "around the cameras (default true; false: --preset paper and the official code)");
  sub->add_option("--lr-sky", c.sky_lr, "Learning rate of the sky's coefficients (default 0.01)")
      ->check(finite_range(0, 100));
  sub->add_option("--lambda-ssim", c.lambda_ssim, "Weight of 1 - SSIM in L_rgb (default 0.2)")
      ->check(finite_range(0.0, 1.0));
  sub->add_option("--w-offset", c.w_offset, "Weight of the offset regulariser L_in (default 0.5)")
      ->check(finite_range(0, 1e+06));
  sub->add_option("--w-dist", c.w_distortion, "Weight of the depth distortion L_d (default 50)")
      ->check(finite_range(0, 1e+06));
  sub->add_option("--dist-from", c.distortion_from, "First iteration with the distortion term (default 0)")
      ->check(non_negative_number());
  sub->add_option("--downscales", c.downscales,
                  "Coarse-to-fine: start at the images divided by 2^N, doubling the resolution every --res-schedule "
                  "iterations (default -1: as many halvings, at most 3, as keep the shorter side >= 64 px; 0 = off, "
                  "as --preset paper; mask-loss iterations and stage 2 always at full resolution)")
      ->check(CLI::Range(-1, 6));
  sub->add_option("--res-schedule", c.res_schedule,
                  "Iterations per resolution doubling with --downscales (default 0: 0.85 x iters / levels, at most "
                  "3000, so full resolution for the last 15% of the run)")
      ->check(CLI::Range(0, 100000000));
  sub->add_option("--coarse-lowpass", c.coarse_lowpass,
                  "At the coarse levels of --downscales, the screen-space low-pass is 0.3 px^2 x F^level of the "
                  "downscaled image (default 0.5; 1 = 0.3 coarse px at every level, 0.25 = 0.3 full-resolution px)")
      ->check(finite_range(1e-6, 1.0));
  sub->add_option("--w-is", c.w_is,
                  "Weight of the mask-internal loss L_is on the rendered features (default 0.1; scenes with masks)")
      ->check(finite_range(0, 1e+06));
  sub->add_option("--w-ic", c.w_ic, "Weight of the mask-contrast loss L_ic (default 0.1)")
      ->check(finite_range(0, 1e+06));
  sub->add_option("--mask-from", c.mask_from,
                  "First iteration with the mask losses (default -1 = iters / 6, the official 5k of 30k)")
      ->check(CLI::Range(-1, std::numeric_limits<int>::max()));
  sub->add_flag("!--no-mask-alpha-norm", c.mask_alpha_normalise,
                "Mask losses on the raw rendered feature instead of the feature divided by alpha (default: divided, "
                "pixels with alpha < 0.1 left out)");
  sub->add_flag("--mask-geometry,!--mask-features-only", c.mask_geometry,
                "--mask-geometry (default): the mask losses' gradient reaches every Gaussian parameter (the "
                "paper's joint loss); --mask-features-only: it trains the semantic features alone, so appearance "
                "and geometry train as without masks");
  sub->add_flag("!--no-unmasked-group", c.mask_unmasked_group,
                "Leave pixels without a SAM mask out of the mask losses (default: they form one more mask, so "
                "object features are pushed away from the unmasked surroundings)");
  sub->add_flag("!--no-grow-same-layer", c.grow_same_layer,
                "Grow only finer anchors (default: also anchors of a child's own layer where its mean left its "
                "voxel, so the model spreads into regions without SfM points)");
  sub->add_option("--recycle-opacity", c.recycle_opacity,
                  "In growing rounds, children of a kept anchor below this opacity become copies of its most opaque "
                  "child, the two sharing its opacity (default 0.02; --preset paper 0 = off)")
      ->check(finite_range(0.0, 0.999));
  sub->add_flag("!--no-feature-ball", c.feature_ball,
                "Let the semantic features grow without bound (default: projected into the unit ball after each "
                "step, so the graph stages' absolute thresholds keep their meaning)");
  sub->add_option("--lr-feature", c.feature_lr, "Semantic feature learning rate (default 0.05)")
      ->check(finite_range(0, 100));
  sub->add_option("--lr-offset", c.offset_lr_init,
                  "Offset learning rate at the start (default 1e-2; --preset paper 1e-3; voxel units)")
      ->check(finite_range(0, 100));
  sub->add_option("--lr-offset-final", c.offset_lr_final, "Offset learning rate at the end (default 1e-4)")
      ->check(finite_range(0, 100));
  sub->add_flag("--lr-offset-extent,!--no-lr-offset-extent", c.offset_lr_extent,
                "Multiply the offset rates by the camera radius (default on, as the official code; "
                "--no-lr-offset-extent for voxel units alone)");
  sub->add_option("--lr-sh", c.sh_dc_lr, "SH DC learning rate (default 0.0025)")->check(finite_range(0, 100));
  sub->add_option("--lr-sh-rest", c.sh_rest_lr, "Higher SH learning rate (default 0.0025 / 20)")
      ->check(finite_range(0, 100));
  sub->add_option("--lr-opacity", c.opacity_lr, "Opacity logit learning rate (default 0.05)")
      ->check(finite_range(0, 100));
  sub->add_option("--lr-scaling", c.scaling_lr, "Scale logit learning rate (default 0.01; --preset paper 0.005)")
      ->check(finite_range(0, 100));
  sub->add_option("--lr-rotation", c.rotation_lr, "Rotation learning rate (default 0.001)")
      ->check(finite_range(0, 100));
  sub->add_option("--top-cells", c.anchors.top_cells,
                  "Top-layer voxels along the longest robust extent of the SfM points (default: the voxel is "
                  "chosen from the scene, a finest-layer voxel of about a pixel at the points' median depth; "
                  "--preset paper: 200)")
      ->check(positive_number());
  sub->add_option("--voxel-size", c.anchors.voxel_size,
                  "Top-layer voxel edge in world units (overrides --top-cells and the scene's choice)")
      ->check([](const std::string& v) -> std::string {
        char* end = nullptr;
        const double x = std::strtod(v.c_str(), &end);
        if (end == v.c_str() || *end != 0 || !(x > 0) || !std::isfinite(x))
          return "--voxel-size must be a finite number > 0 (world units), not '" + v + "'";
        return {};
      });
  sub->add_option("--max-gaussians", c.max_gaussians,
                  "Growth never takes the model past this many Gaussians (default: the pixels of a training view, "
                  "at least twice the initial count; 0 = no limit; below the initial count is an error)")
      ->check(CLI::Range(int64_t{0}, std::numeric_limits<int64_t>::max()));
  sub->add_option("--grow-budget", c.grow_budget,
                  "A growing round adds at most this fraction of the anchors (at least 64; default 0.1, the "
                  "library's 0.25; 0 = no limit); the children asking hardest win")
      ->check(finite_range(0.0, 1e6));
  sub->add_option("--children", c.anchors.children, "Gaussians per anchor (default 2; --preset paper 5)")
      ->check(CLI::Range(1, 64));
  sub->add_option("--init-layer", c.anchors.init_layer,
                  "First voxel layer the SfM points initialise anchors on (default 0 = the top layer, as the "
                  "official code; -1 = every layer, as the paper says)")
      ->check(CLI::Range(-1, 15));
  sub->add_option("--init-layers", c.anchors.init_layers,
                  "Layers the SfM points initialise anchors on, from --init-layer down (default 2: the top layer "
                  "and the next, so thin objects start with anchors of their own; --preset paper 1, the official "
                  "code)")
      ->check(CLI::Range(1, 16));
  sub->add_option("--init-scale", c.anchors.init_scale,
                  "Scale of a fresh child as a fraction of its voxel edge (default 0.5; below --scale-cap)")
      ->check(finite_range(1e-4, 1023.0));
  sub->add_option("--scale-cap", c.anchors.scale_cap,
                  "A child's scale is at most this many voxel edges (default 64; --preset paper 1: a child "
                  "never outgrows its voxel)")
      ->check(finite_range(1.0, 1024.0));
  sub->add_option("--scale-cap-layers", c.anchors.scale_cap_layers,
                  "--scale-cap holds on this many of the coarsest layers (1 = the top layer only); finer layers keep "
                  "their children inside their voxels (default: every layer)")
      ->check(CLI::Range(1, 16));
  sub->add_option("--init-opacity", c.anchors.init_opacity, "Opacity of a fresh child (default 0.1)")
      ->check(finite_range(1e-4, 0.9999));
  sub->add_flag("--init-children-at-points,!--init-children-random", c.anchors.init_children_at_points,
                "Seeded anchors put their children on the SfM points of their voxel, with those points' colours "
                "(default; --init-children-random, as the official code and --preset paper: random offsets and "
                "the voxel's mean colour)");
  sub->add_option("--grow-from", c.grow_from, "First iteration of anchor growing (default 500)")
      ->check(non_negative_number());
  sub->add_option("--grow-until", c.grow_until, "Last iteration of anchor growing (default 0 = 2/3 of --iters)")
      ->check(non_negative_number());
  sub->add_option("--grow-every", c.grow_every, "Iterations between growing rounds (default 100; 0 = no growing)")
      ->check(non_negative_number());
  sub->add_option("--grow-threshold", c.grow_threshold,
                  "Mean screen-space gradient (NDC units) above which a child grows a finer anchor (default 1.5e-4, "
                  "x2 per layer)")
      ->check(finite_range(1e-12, 1000));
  sub->add_option("--grow-min-seen", c.grow_min_seen,
                  "Fraction of a round's iterations a child must be visible in to grow (default 0.1, so the far "
                  "background that a circling capture sees in a few views grows too; --preset paper and the "
                  "official code 0.4)")
      ->check(finite_range(0.0, 1.0));
  sub->add_option("--grow-split", c.grow_split,
                  "Split growth, as 3DGS splits a large Gaussian: a growing child at least this many voxels of the "
                  "layer it grows into wide along one of its two longest axes also asks for anchors at +-1 "
                  "standard deviation along it, and the anchors it grows start at its scale / 1.6 "
                  "(default 4; 0 = off: one anchor at the child's mean whose children start at --init-scale, "
                  "--preset paper and the official code)")
      ->check(finite_range(0.0, 1e6));
  sub->add_option("--prune-opacity", c.prune_opacity,
                  "In growing rounds, remove anchors whose children's mean opacity is below this (default 0.01; 0 = "
                  "off)")
      ->check(finite_range(0.0, 0.999));
  sub->add_option("--final-prune-opacity", c.final_prune_opacity,
                  "After the last stage-1 iteration, remove anchors whose children's mean opacity is below this "
                  "(default 0.015; --preset paper: 0 = off)")
      ->check(finite_range(0.0, 0.999));
  sub->add_option("--prune-importance", c.prune_importance,
                  "Once, at --prune-importance-at, remove the anchors that draw least (their Gaussians' blending "
                  "weights summed over every pixel of the training views) while together they draw at most this "
                  "share of the pictures (default 0.01; --preset paper: 0 = off)")
      ->check(finite_range(0.0, 0.999));
  sub->add_option("--prune-importance-at", c.prune_importance_at,
                  "The iteration of the importance prune (default 0: halfway between the end of growing and --iters)")
      ->check(CLI::Range(0, std::numeric_limits<int>::max()));
  sub->add_option("--prune-unseen-window", c.prune_unseen_window,
                  "In growing rounds, remove anchors none of whose children was visible in the last N training views "
                  "(default 0 = 2 x training views; -1 = off)")
      ->check(CLI::Range(-1, std::numeric_limits<int>::max()));
  sub->add_option("--opacity-reset-every", c.opacity_reset_every,
                  "Reset every opacity to at most 0.01 every N iterations while growing runs (default 3000; 0 = off)")
      ->check(non_negative_number());
  sub->add_option("--opacity-reset-pause", c.opacity_reset_pause,
                  "Growing rounds this many iterations after a reset do not prune by opacity (default 500)")
      ->check(non_negative_number());
  add_progress_options(sub, *a);
  sub->add_flag("--view", a->view,
                "Serve the viewer while training (as `ag2gs view`): the picture follows the model, with its progress "
                "and a pause button; after training it shows the final model until Ctrl-C");
  sub->add_option("--port", a->serve.port, "With --view: TCP port (default 8080; 0 = any free port, printed)")
      ->check(CLI::Range(0, 65535));
  sub->add_option("--host", a->serve.host, "With --view: address to listen on (default 127.0.0.1)");
  sub->add_option("--save-every", a->save_every, "Checkpoint every N iterations (default 0 = end only)")
      ->check(non_negative_number());
  sub->add_flag("--resume", a->resume,
                "Continue from MODEL_DIR/checkpoint.ag2gs (its settings, stages included; flags given must agree "
                "with them)");
  sub->add_flag("--force", a->force,
                "Start a new model even though MODEL_DIR holds one (its files are replaced when training ends)");
  sub->add_option("--stages", a->stages,
                  "Stages to run (comma-separated, default 1,2,3); without 1 they run on MODEL_DIR's checkpoint / "
                  "model (e.g. --stages 3 re-clusters a trained model)")
      ->delimiter(',')
      ->check(CLI::Range(1, 3));
  sub->add_option("--prop-iters", c.prop_iters,
                  "Stage-2 iterations after stage 1 (default -1 = iters / 6, the official 5000 after 30000; 0 = no "
                  "stage 2)")
      ->check(CLI::Range(-1, std::numeric_limits<int>::max()));
  sub->add_option("--w-prop", c.w_prop,
                  "Weight of the propagation loss L_prop (a mean over edges) in stage 2 (default 10; the paper's 0.01 "
                  "is on a sum)")
      ->check(finite_range(0, 1e+06));
  sub->add_option("--prop-tau", c.prop_tau, "Bilateral bandwidth tau of L_prop (default 0.05)")
      ->check(finite_range(1e-09, 1e+06));
  Stage3Config& s3 = a->stage3;
  sub->add_option("--cluster-distance", s3.cluster.max_distance,
                  "Stage 3: join graph neighbours whose feature distance is below this (default 0.01)")
      ->check(finite_range(1e-9, 1e6));
  sub->add_option("--min-cluster-size", s3.cluster.min_cluster_size,
                  "Stage 3: clusters with fewer anchors are skipped (default 5)")
      ->check(CLI::Range(1, std::numeric_limits<int>::max()));
  sub->add_option("--match-score", s3.language.min_score,
                  "Stage 3: a cluster takes a mask's CLIP feature when their score S exceeds this (default 0.3)")
      ->check(finite_range(-1, 1));
  sub->add_option("--match-softmax", s3.language.softmax_scale,
                  "Stage 3: the matches' weights are softmax(scale * S) (default 10)")
      ->check(finite_range(0.001, 80.0));
  sub->add_option("--instance-fraction", s3.language.instance_fraction,
                  "Stage 3: a pixel belongs to a cluster holding at least this share of its weight (default 0.5)")
      ->check(finite_range(0.5, 0.999));
  sub->add_option("--preset", a->preset,
                  "default (= appearance: --scale-cap 64 --children 2 --init-layers 2 --init-children-at-points "
                  "--grow-budget 0.1 --grow-min-seen 0.1 --grow-split 4 --far-shell true --recycle-opacity 0.02 "
                  "--final-prune-opacity 0.015 --prune-importance 0.01 --lr-offset 1e-2 "
                  "--lr-scaling 0.01, "
                  "the voxel from the "
                  "scene) or paper (the method as published: --top-cells 200, 5 children inside their voxels, "
                  "--scale-cap 1, one seeded layer, no growth budget); flags given explicitly win")
      ->check(CLI::IsMember({"default", "appearance", "paper"}));
  auto print_config = std::make_shared<bool>(false);
  sub->add_flag("--print-config", *print_config,
                "Print the settings this command would train with (the preset, then the flags given; JSON, the "
                "`config` of model.ag2gs) and exit without reading the scene or writing anything");
  set_action(sub, [&global, a, sub, print_config] {
    a->stages_given = sub->count("--stages") > 0;
    apply_preset(*sub, *a, !*print_config);
    if (*print_config) {
      a->config.validate();
      std::printf("%s\n", a->config.to_json().dump(2).c_str());
      return;
    }
    cmd_train(global, *a);
  });
}

}  // namespace ag2gs::cli
