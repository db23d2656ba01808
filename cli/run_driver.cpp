#include "cli/run_driver.h"

#include <spdlog/spdlog.h>
#include <sys/resource.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>

#include "cli/commands.h"
#include "cli/run_guard.h"
#include "host/core/quantile.h"
#include "host/core/timing.h"
#include "train/checkpoint.h"

namespace fs = std::filesystem;

namespace ag2gs::cli {

void add_scene_options(CLI::App* sub, RunArgs& a) {
  sub->add_option("scene_dir", a.scene, "Scene directory (images/, sparse/0/)")->required();
  sub->add_option("-o,--out", a.out, "Model directory to write (created)")->check(output_path())->required();
  sub->add_option("--sparse", a.sparse,
                  "COLMAP model folder inside the scene (default: sparse/0/, else sparse/ when it holds the model)");
  sub->add_option("-r,--resolution", a.resolution, "Divide the camera resolution by R (default 1)")
      ->check(CLI::Range(1, 64));
  sub->add_flag("--eval", a.eval, "Hold out every 8th view; test PSNR/SSIM to MODEL_DIR/metrics.json");
}

void add_progress_options(CLI::App* sub, RunArgs& a) {
  sub->add_option("--log-every", a.log_every, "Progress line every N iterations (default 100; 0 = none)")
      ->check(non_negative_number());
  sub->add_option("--test-at", a.test_at,
                  "With --eval: also test at these iterations (comma-separated, e.g. 1000,3000,7000)")
      ->delimiter(',')
      ->check(positive_number());
  sub->add_option("--test-views", a.test_images,
                  "Hold out these images (comma-separated names or stems, e.g. 6.jpg) instead of every 8th; implies "
                  "--eval")
      ->delimiter(',');
  sub->add_option("--test-every", a.test_every, "With --eval: test metrics every N iterations (default 0 = end only)")
      ->check(non_negative_number());
  sub->add_flag("--profile", a.profile, "Time every kernel and print the per-iteration breakdown");
}

std::unique_ptr<Scene> open_run_scene(RunArgs& a) {
  if (a.resolution < 1) throw std::invalid_argument("-r must be >= 1 (it divides the camera resolution)");
  SceneOptions so;
  so.resolution = a.resolution;
  so.eval = a.eval || !a.test_images.empty();
  so.test_images = a.test_images;
  so.sparse = a.sparse;
  a.eval = so.eval;
  std::unique_ptr<Scene> scene = Scene::open(a.scene, so);
  scene->require_points();
  // Every image and mask decoded once now (they stay in the cache): a corrupt
  // file stops the run before it starts, not at the iteration that needs it.
  // A signal here (train's guard is up) stops the run at once, not after the
  // last photo of a large capture.
  const auto t0 = std::chrono::steady_clock::now();
  scene->check_all([] {
    if (!InterruptGuard::interrupted()) return;
    spdlog::warn("{} while checking the images: stopped before writing anything", InterruptGuard::signal_name());
    InterruptGuard::exit_after_saving();
  });
  spdlog::info("checked the {} views' images{} ({:.1f} s)", scene->views().size(),
               scene->semantics() != SemanticsKind::none ? " and masks" : "", ms_since(t0) / 1000);
  return scene;
}

void log_run_scene(const Scene& scene, const Runtime& rt, int resolution) {
  spdlog::info("device [{}] {}", rt.info().index, rt.info().name);
  spdlog::info("scene {}: {} training views, {} test views, {}x{} (-r {}), {} SfM points", scene.dir(),
               scene.train_views().size(), scene.test_views().size(), scene.views()[0].camera.width,
               scene.views()[0].camera.height, resolution, scene.points().size());
}

RunDriver::RunDriver(const RunArgs& args, const Scene& scene, const std::string& model, uint64_t seed, int iterations)
    : args_(args),
      metrics_({{"scene", scene.dir()},
                {"model", model},
                {"resolution", args.resolution},
                {"seed", seed},
                {"iterations", iterations},
                {"train_views", scene.train_views().size()},
                {"test_views", scene.test_views().size()}}) {
  metrics_["test"] = nlohmann::json::array();
  metrics_["warnings"] = nlohmann::json::array();
}

bool RunDriver::log_due(int iteration, int first, int last) const {
  return args_.log_every > 0 && (iteration % args_.log_every == 0 || iteration == last || iteration == first + 1);
}

bool RunDriver::test_due(int iteration, int last) const {
  return args_.eval && iteration != last &&
         ((args_.test_every > 0 && iteration % args_.test_every == 0) ||
          std::find(args_.test_at.begin(), args_.test_at.end(), iteration) != args_.test_at.end());
}

void RunDriver::start(int first) {
  t0_ = t_last_ = Clock::now();
  it_last_ = first;
  eval_seconds_ = 0;
}

double RunDriver::train_seconds() const {
  return std::chrono::duration<double>(Clock::now() - t0_).count() - eval_seconds_;
}

std::string RunDriver::metrics_path() const {
  return (fs::path(args_.out) / "metrics.json").string();
}

void RunDriver::write_metrics() const {
  write_json_atomic(metrics_path(), metrics_);
}

EvalStats RunDriver::evaluate(int iteration, const std::function<EvalStats()>& eval, const nlohmann::json& counts) {
  const auto t = Clock::now();
  const double trained_s = train_seconds();
  const EvalStats ev = eval();
  const double s = std::chrono::duration<double>(Clock::now() - t).count();
  spdlog::info("[test] iteration {}: PSNR {:.3f} dB, SSIM {:.4f}, L1 {:.5f} over {} views ({:.2f} s)", iteration,
               ev.psnr, ev.ssim, ev.l1, ev.views, s);
  eval_seconds_ += s;
  nlohmann::json entry = {{"iteration", iteration},     {"psnr", ev.psnr},  {"ssim", ev.ssim}, {"l1", ev.l1},
                          {"train_seconds", trained_s}, {"eval_seconds", s}};
  for (auto it = counts.begin(); it != counts.end(); ++it) entry[it.key()] = it.value();
  metrics_["test"].push_back(entry);
  write_metrics();
  return ev;
}

void RunDriver::record_step_ms(double ms, bool fixed) {
  step_ms_.push_back(ms);
  if (fixed) step_ms_fixed_.push_back(ms);
}

double RunDriver::recent_step_ms() const {
  const size_t recent = std::min<size_t>(step_ms_.size(), 100);
  return recent
             ? quantile(std::vector<double>(step_ms_.end() - static_cast<std::ptrdiff_t>(recent), step_ms_.end()), 0.5)
             : 0.0;
}

double RunDriver::eta_seconds(int remaining, size_t now, int growing, double end_count) const {
  return estimate_seconds_left(remaining, recent_step_ms(), now, growing, end_count);
}

void RunDriver::add_sample(double loss, double psnr, double l1, double ssim) {
  sum_loss_ += loss;
  sum_psnr_ += psnr;
  sum_l1_ += l1;
  sum_ssim_ += ssim;
  ++count_;
}

RunDriver::Means RunDriver::take_means(int iteration) {
  const auto now = Clock::now();
  const double dt = std::chrono::duration<double>(now - t_last_).count();
  Means m;
  const double n = std::max(count_, 1);
  m.loss = sum_loss_ / n;
  m.psnr = sum_psnr_ / n;
  m.l1 = sum_l1_ / n;
  m.ssim = sum_ssim_ / n;
  m.its = (iteration - it_last_) / std::max(dt, 1e-9);
  t_last_ = now;
  it_last_ = iteration;
  sum_loss_ = sum_psnr_ = sum_l1_ = sum_ssim_ = 0;
  count_ = 0;
  return m;
}

void RunDriver::warn(const std::string& text) {
  spdlog::warn("{}", text);
  metrics_["warnings"].push_back(text);
}

double RunDriver::finish_training(Runtime& rt, int trained, int skipped, size_t gaussians, double first_train_psnr,
                                  const char* count_changes) {
  const double seconds = train_seconds();
  const int steps = std::max(1, trained);
  spdlog::info("trained {} iterations in {:.1f} s ({:.2f} ms/iteration){}", std::max(0, trained), seconds,
               1000 * seconds / steps, skipped ? fmt::format(", {} steps skipped", skipped) : "");
  const double median_ms = quantile(step_ms_, 0.5), p90_ms = quantile(step_ms_, 0.9);
  const double fixed_median_ms = quantile(step_ms_fixed_, 0.5);
  if (!step_ms_.empty())
    spdlog::info("step time: median {:.2f} ms, 90th percentile {:.2f} ms{}", median_ms, p90_ms,
                 step_ms_fixed_.empty() ? std::string()
                                        : fmt::format("; after {} stopped: median {:.2f} ms at {} Gaussians",
                                                      count_changes, fixed_median_ms, gaussians));
  if (args_.profile) {
    auto timings = rt.take_timings();
    double total = 0;
    for (auto& [k, ms] : timings) total += ms;
    spdlog::info("kernel time per iteration: {:.3f} ms in total", total / steps);
    for (auto& [k, ms] : timings)
      spdlog::info("  {:<17} {:8.3f} ms ({:4.1f}%)", k, ms / steps, total > 0 ? 100 * ms / total : 0.0);
  }
  metrics_["train_seconds"] = seconds;
  metrics_["ms_per_iteration"] = 1000 * seconds / steps;
  if (!step_ms_.empty()) {
    metrics_["ms_per_iteration_median"] = median_ms;
    metrics_["ms_per_iteration_p90"] = p90_ms;
  }
  if (!step_ms_fixed_.empty()) metrics_["ms_per_iteration_median_after_growing"] = fixed_median_ms;
  metrics_["skipped_steps"] = skipped;
  metrics_["gaussians"] = gaussians;
  metrics_["first_train_psnr"] = first_train_psnr;
  metrics_["eval_seconds"] = eval_seconds_;
  metrics_["device"] = rt.info().name;
  struct rusage ru {};
  ::getrusage(RUSAGE_SELF, &ru);
  metrics_["peak_rss_mb"] = ru.ru_maxrss / 1024.0;  // Linux: kilobytes
  return seconds;
}

void RunDriver::final_test(int iteration, const std::function<EvalStats()>& eval, const nlohmann::json& counts) {
  if (args_.eval) {
    const EvalStats ev = evaluate(iteration, eval, counts);
    metrics_["final"] = {{"iteration", iteration}, {"psnr", ev.psnr}, {"ssim", ev.ssim}, {"l1", ev.l1}};
  }
  write_metrics();
}

}  // namespace ag2gs::cli
