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
#include <type_traits>
#include <variant>

#include "cli/commands.h"
#include "cli/run_driver.h"
#include "cli/run_guard.h"
#include "cli/viewer/view_server.h"
#include "host/device/cl_runtime.h"
#include "host/io/model_io.h"
#include "host/scene/scene.h"
#include "stages/divergence_guard.h"
#include "stages/language.h"
#include "stages/train_settings.h"
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

// A setting as a flag shows it: "--children 2", "--init-children-random",
// "--far-shell true".
std::string flag_text(const TrainSetting& s, const TrainConfig& c) {
  const nlohmann::json v = s.get(c);
  if (s.is_bool() && !s.takes_value) {
    const std::string name = s.name_for(v.get<bool>());
    return name.empty() ? s.flag_name() + "=" + (v.get<bool>() ? "true" : "false") : name;
  }
  if (s.is_bool()) return s.flag_name() + (v.get<bool>() ? " true" : " false");
  if (v.is_number_float()) return fmt::format("{} {:g}", s.flag_name(), v.get<double>());
  return s.flag_name() + " " + v.dump();
}

// The flag of a setting (stages/train_settings.h), bound to its field of
// `c`, checked as the table says.
void add_setting_option(CLI::App* sub, const TrainSetting& s, TrainConfig& c) {
  std::visit(
      [&](auto field) {
        auto& ref = field(c);
        using T = std::decay_t<decltype(ref)>;
        if constexpr (std::is_same_v<T, bool>) {
          if (!s.takes_value) {
            sub->add_flag(s.flag, ref, s.help);
            return;
          }
        }
        CLI::Option* o = sub->add_option(s.flag, ref, s.help);
        switch (s.check) {
          case TrainSetting::Check::kRange:
            if constexpr (std::is_integral_v<T> && !std::is_same_v<T, bool>) {
              const T hi = s.hi >= static_cast<double>(std::numeric_limits<T>::max()) ? std::numeric_limits<T>::max()
                                                                                      : static_cast<T>(s.hi);
              o->check(CLI::Range(static_cast<T>(s.lo), hi));
            } else {
              o->check(finite_range(s.lo, s.hi));
            }
            break;
          case TrainSetting::Check::kNonNegative:
            o->check(non_negative_number());
            break;
          case TrainSetting::Check::kPositive:
            o->check(positive_number());
            break;
          case TrainSetting::Check::kSeed:
            o->check(seed_number());
            break;
          case TrainSetting::Check::kNone:
            break;
        }
      },
      s.field);
}

// --preset's help, from the table.
std::string preset_help() {
  std::string def, paper;
  const TrainConfig d = TrainConfig::preset("default"), p = TrainConfig::preset("paper");
  for (const TrainSetting& s : train_settings()) {
    if (s.in_default) def += " " + flag_text(s, d);
    if (s.in_paper) paper += " " + flag_text(s, p);
  }
  return "default (= appearance, the measured setting for photographed scenes:" + def +
         ") or paper (the method as published:" + paper +
         ", 5 children inside their voxels, one seeded layer); the library's defaults for the rest; flags given "
         "explicitly win";
}

// Presets (stages/train_settings.cpp names the values). The default (also
// called "appearance") is the measured setting for photographed scenes;
// "paper" is the method as published. A setting the user gives on the
// command line wins. A resumed run takes its settings from the checkpoint,
// so a preset is applied only when given explicitly there.
void apply_preset(const CLI::App& sub, TrainArgs& a, bool log = true) {
  const bool continues = a.resume || std::find(a.stages.begin(), a.stages.end(), 1) == a.stages.end();
  if (continues && sub.count("--preset") == 0) return;
  apply_train_preset(a.config, a.preset, [&sub](const TrainSetting& s) { return sub.count(s.flag_name()) > 0; });
  if (!log) return;
  std::string line;
  for (const TrainSetting& s : train_settings())
    if (s.in_a_preset()) line += " " + flag_text(s, a.config);
  spdlog::info("preset {}:{}", a.preset, line);
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
  for (const TrainSetting& s : train_settings())
    if (s.is_flag()) add_setting_option(sub, s, c);
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
  sub->add_option("--preset", a->preset, preset_help())->check(CLI::IsMember({"default", "appearance", "paper"}));
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
