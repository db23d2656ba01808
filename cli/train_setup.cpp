// `ag2gs train`: resuming a run (its settings from the checkpoint), stage 3
// alone, and the log of what a run will do (cli/train_command.h).
#include <spdlog/spdlog.h>

#include <algorithm>
#include <filesystem>
#include <memory>
#include <string>

#include "cli/run_guard.h"
#include "cli/train_command.h"
#include "host/core/timing.h"
#include "host/device/cl_runtime.h"
#include "host/io/model_io.h"
#include "train/eta.h"
#include "train/stage3/language.h"
#include "train/stage3/stage3_settings.h"

namespace fs = std::filesystem;

namespace ag2gs::cli {

bool has_stage(const TrainArgs& a, int s) {
  return std::find(a.stages.begin(), a.stages.end(), s) != a.stages.end();
}

void log_stage3(const Stage3Summary& s, const Stage3Config& config) {
  spdlog::info(
      "stage 3: {} clusters of {} anchors ({} components, {} anchors in clusters under {} skipped), {} with "
      "a language feature{}",
      s.clusters, s.anchors, s.components, s.skipped_anchors, config.cluster.min_cluster_size, s.with_language,
      s.language ? "" : " (scene without CLIP features: none attached)");
}

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

nlohmann::json run_record(const TrainArgs& a) {
  return {{"stages", a.stages}, {"stage3", stage3_to_json(a.stage3)}};
}

namespace {

// Takes the stages (unless --stages was given) and the stage-3 settings
// (unless one was given) from a checkpoint's run record.
void adopt_run_record(const nlohmann::json& run, TrainArgs& a) {
  if (!run.is_object()) return;  // a checkpoint from before the record
  if (!a.stages_given && run.contains("stages")) a.stages = run["stages"].get<std::vector<int>>();
  const nlohmann::json given = run_record(a)["stage3"];
  const nlohmann::json defaults = run_record(TrainArgs{})["stage3"];
  if (given != defaults || !run.contains("stage3")) return;
  stage3_from_json(run["stage3"], a.stage3);
}

}  // namespace

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

void log_training_plan(const Trainer& trainer, const Scene& scene) {
  const TrainConfig& c = trainer.config();
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
        scene.semantics() != SemanticsKind::none ? "; mask-loss iterations always full" : "");
  if (c.grow_every > 0 && c.grow_from <= c.effective_grow_until()) {
    const GrowthConfig g = c.growth_config(scene.train_views().size());
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
  if (scene.semantics() != SemanticsKind::none && (c.w_is > 0 || c.w_ic > 0))
    spdlog::info("mask losses from iteration {}: {} L_is + {} L_ic on the rendered features{}, training {}",
                 c.effective_mask_from(), c.w_is, c.w_ic, c.mask_alpha_normalise ? " / alpha" : "",
                 c.mask_geometry ? "every parameter" : "the semantic features only");
}

void check_train_args(TrainArgs& a) {
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
}

void StepTerms::add(const StepStats& st) {
  distortion_sum += st.distortion;
  intersection_sum += static_cast<double>(st.intersections);
  if (st.with_masks) {
    is_sum += st.l_is;
    ic_sum += st.l_ic;
    ++with_masks;
  }
  if (st.stage2) {
    prop_sum += st.l_prop;
    ++with_prop;
  }
  ++steps;
}

std::string StepTerms::mask_terms() const {
  std::string t =
      with_masks > 0 ? fmt::format(", L_is {:.4f}, L_ic {:.4f}", is_sum / with_masks, ic_sum / with_masks) : "";
  if (with_prop > 0) t += fmt::format(", L_prop {:.3e}", prop_sum / with_prop);
  return t;
}

double log_progress(RunDriver& run, const Trainer& trainer, const StepStats& st, int it_end, StepTerms& terms,
                    size_t gaussians_at_start, int rounds_done) {
  const TrainConfig& c = trainer.config();
  const RunDriver::Means m = run.take_means(st.iteration);
  // The ETA from the recent steps' time (evaluations left out) and the
  // growth still to come.
  const int grow_until = c.grow_every > 0 ? std::min(c.effective_grow_until(), c.iterations) : 0;
  const int growing = std::max(0, grow_until - st.iteration);
  const int rounds_left = c.grow_every > 0 ? growing / c.grow_every : 0;
  const double eta = run.eta_seconds(it_end - st.iteration, trainer.gaussians(), growing,
                                     growth_end_geometric(trainer.gaussians(), gaussians_at_start, rounds_done,
                                                          rounds_left, trainer.max_gaussians()));
  const std::string eta_text =
      fmt_duration(eta) + (growing > 0 ? fmt::format(" (growing until {})", grow_until) : std::string());
  spdlog::info(
      "it {:>6}/{}  loss {:.5f} (L1 {:.5f}, SSIM {:.4f}, dist {:.3e}, L_in {:.4f}{})  PSNR {:.2f} dB  SH {}  "
      "anchors {}  Gaussians {}  {:.1f} it/s  ETA {}",
      st.iteration, it_end, m.loss + c.w_offset * st.offset_reg, m.l1, m.ssim, terms.distortion(), st.offset_reg,
      terms.mask_terms(), m.psnr, st.sh_degree, trainer.anchors(), trainer.gaussians(), m.its, eta_text);
  spdlog::debug("  {:.0f} tile intersections per iteration", terms.intersections());
  terms = StepTerms{};
  return eta;
}

nlohmann::json final_stages(Runtime& rt, Scene& scene, const TrainArgs& a, double seconds, double stage1_end_s,
                            int it_start) {
  const TrainConfig& c = a.config;
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
    const Stage3Summary s3 = run_stage3_on_model(rt, scene, a.out, scene.train_views(), a.stage3);
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
  return stages;
}

std::unique_ptr<Scene> prepare_run(TrainArgs& a) {
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
  return scene;
}

void resume_trainer(Trainer& trainer, const TrainArgs& a) {
  const TrainConfig& c = trainer.config();
  trainer.resume(a.out);
  spdlog::info("resuming {} at iteration {} of {}", Trainer::checkpoint_path(a.out), trainer.iteration(),
               c.total_iterations());
  if (!has_stage(a, 1) && trainer.iteration() < c.iterations)
    throw std::runtime_error("--stages without 1: the checkpoint " + Trainer::checkpoint_path(a.out) +
                             " is at iteration " + std::to_string(trainer.iteration()) + ", stage 1 ends at " +
                             std::to_string(c.iterations) + "; finish it with --resume");
}

void end_run(const TrainArgs& a, std::unique_ptr<LiveView>& view) {
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

void log_step_events(const StepStats& st, const Trainer& trainer, bool first_of_stage2) {
  if (st.stage2 && first_of_stage2)
    spdlog::info("stage 2: anchor graph with {} edges (mean degree {:.2f})", trainer.graph().edges(),
                 trainer.anchors() ? 2.0 * trainer.graph().edges() / trainer.anchors() : 0.0);
  if (st.opacity_reset) spdlog::info("iteration {}: opacities reset to at most 0.01", st.iteration);
  if (st.grown > 0 || st.pruned > 0)
    spdlog::info("iteration {}: grew {} anchors{}, pruned {} -> {} anchors, {} Gaussians", st.iteration, st.grown,
                 st.over_budget > 0 ? fmt::format(" ({} more asked, over the budget)", st.over_budget) : "", st.pruned,
                 trainer.anchors(), trainer.gaussians());
}

}  // namespace ag2gs::cli
