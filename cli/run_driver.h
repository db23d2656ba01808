// One driver for the training subcommands (`train` and `baseline`): the
// flags they share, the scene preamble, the test schedule, evaluation timed
// apart from training, step times and the ETA, the progress meter's running
// means, the kernel profile print and one metrics.json schema
// (docs/formats.md). What a trainer does per step stays in its command.
#pragma once

#include <CLI/CLI.hpp>
#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "host/core/timing.h"  // fmt_duration
#include "host/device/cl_runtime.h"
#include "host/scene/scene.h"
#include "train/eta.h"
#include "train/train_common.h"

namespace ag2gs::cli {

// The flags every training subcommand takes.
struct RunArgs {
  std::string scene, out;
  std::string sparse;  // --sparse; empty = the scene-folder rule (host/scene/scene.h)
  int resolution = 1;
  bool eval = false;
  int log_every = 100;
  int test_every = 0;
  std::vector<int> test_at;              // --test-at: evaluate at these iterations too
  std::vector<std::string> test_images;  // --test-views: held out instead of every 8th
  bool profile = false;
  bool force = false;  // --force: replace the model MODEL_DIR holds
};

// scene_dir, -o, --sparse, -r, --eval (the positional and the model folder first).
void add_scene_options(CLI::App* sub, RunArgs& a);
// --log-every, --test-at, --test-views, --test-every, --profile.
void add_progress_options(CLI::App* sub, RunArgs& a);

// Opens the scene as the flags say (-r, the split, --sparse), requires SfM
// points, and sets a.eval when test views were named.
std::unique_ptr<Scene> open_run_scene(RunArgs& a);
// The device and scene lines every run prints first.
void log_run_scene(const Scene& scene, const Runtime& rt, int resolution);

class RunDriver {
 public:
  // The metrics start with the run's fixed fields: the scene, `model`
  // ("anchors" or "baseline"), -r, the seed, the iterations and the view
  // counts.
  RunDriver(const RunArgs& args, const Scene& scene, const std::string& model, uint64_t seed, int iterations);

  // Whether step `iteration` (1-based) prints a progress line / runs a test
  // (the last step's test is the final one, run after saving).
  bool log_due(int iteration, int first, int last) const;
  bool test_due(int iteration, int last) const;

  // Starts the clock at step `first` (0-based: the first step to train;
  // training time = wall time since, evaluations left out).
  void start(int first);
  double train_seconds() const;
  // Evaluates through `eval`, timed apart from training; appends a "test"
  // entry (with the training time so far and `counts`, e.g. Gaussians),
  // prints it and rewrites metrics.json.
  EvalStats evaluate(int iteration, const std::function<EvalStats()>& eval, const nlohmann::json& counts);

  // Wall time of one step without an evaluation in it; `fixed`: the model's
  // count no longer changes (after growing or densifying: `count_changes`
  // in the summary names which).
  void record_step_ms(double ms, bool fixed);
  double recent_step_ms() const;  // median of the last 100
  // estimate_seconds_left (train/eta.h) at the recent step time.
  double eta_seconds(int remaining, size_t now, int growing, double end_count) const;

  // Running means of the progress line.
  void add_sample(double loss, double psnr, double l1, double ssim);
  struct Means {
    double loss = 0, psnr = 0, l1 = 0, ssim = 0;
    double its = 0;  // iterations per second since the last line
  };
  // The means since the last line (and resets them).
  Means take_means(int iteration);

  // A warning printed and kept in metrics.json.
  void warn(const std::string& text);

  // After the last step: the summary lines (time, step-time percentiles,
  // kernel profile) and the metrics fields every run has; returns the
  // training time in seconds.
  double finish_training(Runtime& rt, int trained, int skipped, size_t gaussians, double first_train_psnr,
                         const char* count_changes = "growing");
  // The final test (with --eval) under "final", then metrics.json.
  void final_test(int iteration, const std::function<EvalStats()>& eval, const nlohmann::json& counts);

  nlohmann::json& metrics() { return metrics_; }
  void write_metrics() const;
  std::string metrics_path() const;

 private:
  using Clock = std::chrono::steady_clock;
  const RunArgs& args_;
  nlohmann::json metrics_;
  Clock::time_point t0_ = Clock::now(), t_last_ = Clock::now();
  int it_last_ = 0;
  double eval_seconds_ = 0;
  std::vector<double> step_ms_, step_ms_fixed_;
  double sum_loss_ = 0, sum_psnr_ = 0, sum_l1_ = 0, sum_ssim_ = 0;
  int count_ = 0;
};

}  // namespace ag2gs::cli
