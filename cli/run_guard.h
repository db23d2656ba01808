// What keeps a user's work safe across the subcommands: termination signals
// that end a long run cleanly, and outputs that never replace results or
// inputs by accident.
#pragma once

#include <csignal>
#include <stdexcept>
#include <string>
#include <vector>

namespace ag2gs::cli {

// While alive, SIGINT (Ctrl-C), SIGTERM (job schedulers, `docker stop`,
// `timeout`) and SIGHUP (a closed terminal) set a flag that a training loop
// reads after each iteration, so it can write its checkpoint and exit with
// 128 + the signal's number (130, 143, 129). A second signal ends the
// process at once with that status. The previous handlers come back on
// destruction.
// What exit_after_saving throws for a library caller.
struct StoppedAfterSaving : std::runtime_error {
  StoppedAfterSaving(const std::string& what, int code) : std::runtime_error(what), exit_code(code) {}
  int exit_code;
};

class InterruptGuard {
 public:
  InterruptGuard();
  ~InterruptGuard();
  InterruptGuard(const InterruptGuard&) = delete;
  InterruptGuard& operator=(const InterruptGuard&) = delete;

  // The signal received (0 = none).
  static int signal();
  static bool interrupted() { return signal() != 0; }
  // 128 + signal(): the shell's status for a process ended by it.
  static int exit_code() { return 128 + signal(); }
  // "Ctrl-C", "SIGTERM", "SIGHUP".
  static std::string signal_name();
  // The line the first signal prints (default: "stopping: finishing this
  // iteration and saving ..."); `message` must be a string literal.
  static void set_stop_message(const char* message);
  // Flushes the log and the standard streams and exits with exit_code(),
  // once the caller has saved its work.
  // Or, after set_throw_on_exit(true) (a library caller: the Python
  // module), throws StoppedAfterSaving instead of exiting.
  [[noreturn]] static void exit_after_saving();
  static void set_throw_on_exit(bool on);
  // A stop asked for by the program itself (a library caller's progress
  // hook), handled as a first Ctrl-C.
  static void request_stop();
  // A signal came (not request_stop()): a run that finished its work anyway
  // still exits with the signal's status.
  static bool signalled();

 private:
  struct sigaction old_[3];
};

// `dir` holds the files of a trained model (model.ag2gs, checkpoint.ag2gs or
// point_cloud.ply): the names of those present, empty otherwise.
std::vector<std::string> model_files_in(const std::string& dir);

// Refuses (std::runtime_error) to start a new model in a folder that holds
// one, unless `force`: the message names the files and the flags that
// proceed (`proceed`, e.g. "--resume to continue it, --force to replace it").
void refuse_model_overwrite(const std::string& dir, bool force, const std::string& proceed);

// Refuses to write into a folder that exists and is not empty, unless
// `force`; `what` says what would be replaced ("the scene's images").
void refuse_nonempty_dir(const std::string& dir, bool force, const std::string& what);

// Refuses, unless `force`, to replace the results of an earlier run: the
// files this run would write, `rel` (paths inside the folder `out`), or
// `out` itself when `rel` is empty. The message names the first one found,
// how many more there are, and `flag` (e.g. "-o").
void refuse_existing_results(const std::string& flag, const std::string& out, const std::vector<std::string>& rel,
                             bool force);

// Refuses an output path that names one of the input files (`flag` names
// the option, e.g. "-o"). Paths are compared after resolving `.`, `..` and
// the symbolic links of the parts that exist.
void refuse_output_over_inputs(const std::string& out, const std::vector<std::string>& inputs,
                               const std::string& flag);
// `path` is `dir` or lies inside it, compared after resolving `.`, `..` and
// the symbolic links of the parts that exist.
bool path_is_within(const std::string& path, const std::string& dir);

// The file-name stem of each view's outputs: the image's stem, or, where two
// images share one (a/1.jpg, b/1.jpg), the image's path without its
// extension with '/' as '_' (a_1, b_1), so no view overwrites another.
// Throws std::runtime_error when two views would still write one name.
std::vector<std::string> output_stems(const std::vector<std::string>& image_names);
// Refuses an output (folder or file) that lies inside the scene folder, a
// dataset whose images, masks and poses it could replace, or that is one of
// the input folders (a model folder: writing beside its files is fine,
// writing as it is not). Empty entries are skipped.
void refuse_output_in_inputs(const std::string& out, const std::string& scene,
                             const std::vector<std::string>& input_dirs, const std::string& flag);

// Refuses an output folder that exists as something else (a file): the
// message names `flag` instead of a failed mkdir deep in the run.
void refuse_file_as_output_folder(const std::string& out, const std::string& flag);

}  // namespace ag2gs::cli
