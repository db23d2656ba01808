// What the files of `ag2gs train` share: its arguments, and the steps
// cmd_train.cpp (the run) takes from train_options.cpp (the flags, the
// presets) and train_setup.cpp (resuming, stage 3 alone, the log of what
// the run will do).
#pragma once

#include <CLI/CLI.hpp>
#include <memory>
#include <nlohmann/json.hpp>
#include <string>
#include <thread>
#include <vector>

#include "cli/commands.h"
#include "cli/run_driver.h"
#include "cli/viewer/view_server.h"
#include "host/scene/scene.h"
#include "train/stage3/stage3.h"
#include "train/train_config.h"
#include "train/train_settings.h"
#include "train/trainer.h"

namespace ag2gs::cli {

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

// The run itself (cmd_train.cpp).
void cmd_train(const GlobalOptions& global, TrainArgs& a);

// train_options.cpp. A setting as a flag shows it ("--children 2",
// "--init-children-random", "--far-shell true").
std::string flag_text(const TrainSetting& s, const TrainConfig& c);
// Presets (train/train_settings.cpp names the values). The default (also
// called "appearance") is the measured setting for photographed scenes;
// "paper" is the method as published. A setting the user gives on the
// command line wins. A resumed run takes its settings from the checkpoint,
// so a preset is applied only when given explicitly there. Logs the
// settings the preset names unless !log.
void apply_preset(const CLI::App& sub, TrainArgs& a, bool log = true);

// train_setup.cpp.
bool has_stage(const TrainArgs& a, int s);
// The checks of the arguments before anything is read: the stages (sorted,
// without repeats), stage 3's settings, the output folder.
void check_train_args(TrainArgs& a);
// Before training: whether the run continues a checkpoint (no stage 1, or
// --resume: its settings then come from it), that no model is replaced by
// accident, the settings' validation, the output folder writable, and the
// scene, opened (without SAM masks stages 2 and 3 are dropped).
std::unique_ptr<Scene> prepare_run(TrainArgs& a);
// The trainer continued from MODEL_DIR's checkpoint; refuses one that has
// not finished stage 1 when the run has no stage 1.
void resume_trainer(Trainer& trainer, const TrainArgs& a);
// After the files are written: with --view, the viewer serves the final
// model until Ctrl-C; a signal seen during the last stage sets the exit
// status (the files are complete).
void end_run(const TrainArgs& a, std::unique_ptr<LiveView>& view);
// The stage-3 summary line, after training or for --stages 3 alone.
void log_stage3(const Stage3Summary& s, const Stage3Config& config);
// --stages 3 alone: stage 3 on MODEL_DIR/model.ag2gs, at the resolution and
// split it was trained with.
void stage3_only(const GlobalOptions& global, TrainArgs& a);
// The settings outside TrainConfig that shape a run's files: the stages and
// stage 3's. They go into the checkpoint (Trainer::set_run_record), so that
// `--resume` alone finishes the run as it was started.
nlohmann::json run_record(const TrainArgs& a);
// --resume: the run's config comes from the checkpoint; a setting given on
// the command line (one that differs from the default) must agree with it.
void adopt_checkpoint_config(TrainArgs& a);
// The log lines that say what the run will do: the anchors, the schedule,
// coarse to fine, growing and pruning, the budgets, the mask losses.
void log_training_plan(const Trainer& trainer, const Scene& scene);
// The anchor trainer's own loss terms since the last progress line.
struct StepTerms {
  double distortion_sum = 0, intersection_sum = 0, is_sum = 0, ic_sum = 0, prop_sum = 0;
  int steps = 0, with_masks = 0, with_prop = 0;
  void add(const StepStats& st);
  double distortion() const { return steps ? distortion_sum / steps : 0; }
  double intersections() const { return steps ? intersection_sum / steps : 0; }
  // ", L_is 0.0143, L_ic 0.9886, L_prop 5.8e-04": the means of the terms the steps had.
  std::string mask_terms() const;
};
// What a step did besides the progress line: stage 2's graph on its first
// step, an opacity reset, a growing round's counts.
void log_step_events(const StepStats& st, const Trainer& trainer, bool first_of_stage2);
// The progress line of step `st` (losses, PSNR, counts, speed, an ETA from
// the recent steps and the growth still to come); resets `terms` and
// returns the ETA in seconds.
double log_progress(RunDriver& run, const Trainer& trainer, const StepStats& st, int it_end, StepTerms& terms,
                    size_t gaussians_at_start, int rounds_done);
// After training: the stage times (training time without evaluations;
// stage 1 ended at stage1_end_s, or < 0 when the run did not cross it) and
// stage 3 when asked for, which runs on the written model; returns
// metrics.json's "stages".
nlohmann::json final_stages(Runtime& rt, Scene& scene, const TrainArgs& a, double seconds, double stage1_end_s,
                            int it_start);

}  // namespace ag2gs::cli
