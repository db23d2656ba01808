#include "cli/run_guard.h"

#include <spdlog/spdlog.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <ctime>
#include <filesystem>
#include <map>
#include <set>
#include <stdexcept>

namespace ag2gs::cli {

namespace fs = std::filesystem;

namespace {

constexpr int kSignals[3] = {SIGINT, SIGTERM, SIGHUP};
volatile std::sig_atomic_t g_signal = 0;
bool g_requested = false;  // g_signal came from request_stop(), not from a signal
timespec g_first{};        // when the first signal came

// The same signal again within this window is one request: `timeout` and
// job schedulers signal the process and its group, so one SIGTERM arrives
// twice; a user's second Ctrl-C comes later than that.
constexpr double kRepeatWindowS = 0.5;

// What the first signal's line says (a string literal: static storage).
std::atomic<const char*> g_stop_message{"\nstopping: finishing this iteration and saving (send it again to abort)\n"};

// Async-signal-safe: only clock_gettime(2), write(2) and _exit(2).
extern "C" void on_terminate(int sig) {
  if (g_signal) {
    timespec now{};
    clock_gettime(CLOCK_MONOTONIC, &now);
    const double since = static_cast<double>(now.tv_sec - g_first.tv_sec) + (now.tv_nsec - g_first.tv_nsec) * 1e-9;
    if (sig == g_signal && since < kRepeatWindowS) return;
    static const char msg[] = "\nsecond signal: aborting without saving\n";
    ssize_t ignored = ::write(2, msg, sizeof msg - 1);
    (void)ignored;
    ::_exit(128 + sig);
  }
  clock_gettime(CLOCK_MONOTONIC, &g_first);
  g_signal = sig;
  const char* msg = g_stop_message.load();
  ssize_t ignored = ::write(2, msg, std::strlen(msg));
  (void)ignored;
}

// `p` with `.`, `..` and the links of its existing part resolved.
fs::path resolved(const std::string& p) {
  std::error_code ec;
  fs::path r = fs::weakly_canonical(fs::absolute(p), ec);
  if (ec) r = fs::absolute(p).lexically_normal();
  return r.has_filename() ? r : r.parent_path();  // "a/b/" is "a/b"
}

}  // namespace

void InterruptGuard::set_stop_message(const char* message) {
  g_stop_message.store(message);
}

InterruptGuard::InterruptGuard() {
  g_signal = 0;
  g_requested = false;
  struct sigaction sa {};
  sa.sa_handler = on_terminate;
  sigemptyset(&sa.sa_mask);
  for (int i = 0; i < 3; ++i) ::sigaction(kSignals[i], &sa, &old_[i]);
}

InterruptGuard::~InterruptGuard() {
  for (int i = 0; i < 3; ++i) ::sigaction(kSignals[i], &old_[i], nullptr);
}

int InterruptGuard::signal() { return g_signal; }

std::string InterruptGuard::signal_name() {
  switch (g_signal) {
    case SIGINT: return "Ctrl-C";
    case SIGTERM: return "SIGTERM";
    case SIGHUP: return "SIGHUP";
    default: return "signal " + std::to_string(static_cast<int>(g_signal));
  }
}

namespace {
std::atomic<bool> g_throw_on_exit{false};
}

void InterruptGuard::set_throw_on_exit(bool on) {
  g_throw_on_exit = on;
}

void InterruptGuard::request_stop() {
  if (g_signal) return;
  clock_gettime(CLOCK_MONOTONIC, &g_first);
  g_requested = true;
  g_signal = SIGINT;
}

bool InterruptGuard::signalled() {
  return g_signal != 0 && !g_requested;
}

void InterruptGuard::exit_after_saving() {
  spdlog::default_logger()->flush();
  std::fflush(stdout);
  std::fflush(stderr);
  if (g_throw_on_exit) throw StoppedAfterSaving("stopped (" + signal_name() + ") after saving", exit_code());
  std::exit(exit_code());
}

std::vector<std::string> model_files_in(const std::string& dir) {
  std::vector<std::string> found;
  std::error_code ec;
  for (const char* name : {"model.ag2gs", "checkpoint.ag2gs", "point_cloud.ply", "point_cloud_objects.ply"})
    if (fs::exists(fs::path(dir) / name, ec)) found.push_back(name);
  return found;
}

void refuse_model_overwrite(const std::string& dir, bool force, const std::string& proceed) {
  const std::vector<std::string> found = model_files_in(dir);
  if (force || found.empty()) return;
  std::string list;
  for (const std::string& f : found) list += (list.empty() ? "" : ", ") + f;
  throw std::runtime_error(dir + " already holds a trained model (" + list + "); nothing was changed. Give " +
                           proceed + ", or choose another -o");
}

void refuse_nonempty_dir(const std::string& dir, bool force, const std::string& what) {
  std::error_code ec;
  if (force || !fs::is_directory(dir, ec) || fs::is_empty(dir, ec)) return;
  throw std::runtime_error(dir + " exists and is not empty; writing there would replace " + what +
                           ". Nothing was changed: choose a new folder, or give --force to write over it");
}

void refuse_existing_results(const std::string& flag, const std::string& out, const std::vector<std::string>& rel,
                             bool force) {
  if (force) return;
  std::error_code ec;
  std::vector<std::string> found;
  if (rel.empty() && fs::exists(out, ec)) found.push_back(out);
  for (const std::string& r : rel)
    if (fs::exists(fs::path(out) / r, ec)) found.push_back(r);
  if (found.empty()) return;
  const std::string which =
      found.front() + (found.size() > 1 ? " and " + std::to_string(found.size() - 1) + " more" : std::string());
  throw std::runtime_error(
      flag + " " + out + (rel.empty() ? " exists" : " already holds results this run would replace (" + which + ")") +
      "; nothing was changed. Give another " + flag + ", or --force to replace " + (found.size() > 1 ? "them" : "it"));
}

void refuse_output_over_inputs(const std::string& out, const std::vector<std::string>& inputs,
                               const std::string& flag) {
  const fs::path o = resolved(out);
  for (const std::string& in : inputs) {
    if (in.empty()) continue;
    if (o == resolved(in))
      throw std::runtime_error(flag + " " + out + " is the input " + in +
                               "; writing there would destroy it. Nothing was changed: choose another " + flag);
  }
}

bool path_is_within(const std::string& path, const std::string& dir) {
  const fs::path p = resolved(path), d = resolved(dir);
  return std::mismatch(d.begin(), d.end(), p.begin(), p.end()).first == d.end();
}

void refuse_output_in_inputs(const std::string& out, const std::string& scene,
                             const std::vector<std::string>& input_dirs, const std::string& flag) {
  const fs::path o = resolved(out);
  if (!scene.empty() && path_is_within(out, scene))
    throw std::runtime_error(flag + " " + out + " lies inside the scene folder " + scene +
                             "; writing there could replace its images, masks or poses. Nothing was changed: "
                             "choose a folder outside the scene");
  for (const std::string& d : input_dirs)
    if (!d.empty() && o == resolved(d))
      throw std::runtime_error(flag + " " + out + " is the input folder " + d +
                               "; nothing was changed: choose another " + flag);
}

void refuse_file_as_output_folder(const std::string& out, const std::string& flag) {
  std::error_code ec;
  if (fs::exists(out, ec) && !fs::is_directory(out, ec))
    throw std::runtime_error(flag + " " + out + " is a file, where " + flag +
                             " names the folder to write into; nothing was changed: choose a folder");
}

std::vector<std::string> output_stems(const std::vector<std::string>& image_names) {
  std::map<std::string, int> uses;
  for (const std::string& n : image_names) ++uses[fs::path(n).stem().string()];
  std::vector<std::string> stems;
  std::set<std::string> taken;
  for (const std::string& n : image_names) {
    std::string stem = fs::path(n).stem().string();
    if (uses[stem] > 1) {
      stem = (fs::path(n).parent_path() / fs::path(n).stem()).generic_string();
      std::replace(stem.begin(), stem.end(), '/', '_');
    }
    if (!taken.insert(stem).second)
      throw std::runtime_error("views '" + n + "' and another one would write the same files '" + stem +
                               ".*'; rename one of the images or pick views with --views");
    stems.push_back(stem);
  }
  return stems;
}

}  // namespace ag2gs::cli
