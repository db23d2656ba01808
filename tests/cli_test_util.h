// Running the ag2gs program from a test, as a script would.
#pragma once

#include <gtest/gtest.h>
#include <sys/wait.h>
#include <unistd.h>

#include <array>
#include <csignal>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <functional>
#include <iterator>
#include <string>

#include "synth/synth_scene.h"

namespace ag2gs::test {

struct CliResult {
  int code;            // exit status, -1 when it did not exit normally
  std::string output;  // stdout and stderr together
};

// Runs `$AG2GS_BINARY args` (default ./ag2gs) through the shell.
// The bytes of a file ("" when it cannot be read).
inline std::string read_file(const std::filesystem::path& p) {
  std::ifstream f(p, std::ios::binary);
  return std::string(std::istreambuf_iterator<char>(f), {});
}

inline CliResult run_cli(const std::string& args) {
  const char* bin = std::getenv("AG2GS_BINARY");
  const std::string cmd = std::string(bin ? bin : "./ag2gs") + " " + args + " 2>&1";
  CliResult r{-1, ""};
  FILE* p = popen(cmd.c_str(), "r");
  if (!p) return r;
  std::array<char, 4096> buf;
  while (fgets(buf.data(), buf.size(), p)) r.output += buf.data();
  const int status = pclose(p);
  r.code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  return r;
}

// Starts `$AG2GS_BINARY args` with stdout and stderr on a pipe, sends `sig`
// after the first printed line for which `when` is true, and returns the
// exit status (-1 unless it exited) with everything it printed (plus a note
// when no line matched).
inline CliResult run_cli_interrupted_when(const std::string& args, const std::function<bool(const std::string&)>& when,
                                          int sig = SIGINT, int times = 1) {
  const char* bin = std::getenv("AG2GS_BINARY");
  const std::string cmd = "exec " + std::string(bin ? bin : "./ag2gs") + " " + args + " 2>&1";
  int fd[2];
  if (::pipe(fd) != 0) return {-1, "pipe failed"};
  const pid_t pid = ::fork();
  if (pid == 0) {
    ::dup2(fd[1], 1);
    ::close(fd[0]);
    ::close(fd[1]);
    ::execl("/bin/sh", "sh", "-c", cmd.c_str(), static_cast<char*>(nullptr));
    ::_exit(127);
  }
  ::close(fd[1]);
  CliResult r{-1, ""};
  bool sent = false;
  std::string line;
  char c;
  while (::read(fd[0], &c, 1) == 1) {
    r.output += c;
    if (c != '\n') {
      line += c;
      continue;
    }
    if (!sent && when(line)) {
      // times > 1: 20 ms apart, as `timeout` signals the process, then its
      // group (back to back, the kernel may merge them into one).
      for (int k = 0; k < times; ++k) {
        if (k > 0) ::usleep(20000);
        ::kill(pid, sig);
      }
      sent = true;
    }
    line.clear();
  }
  ::close(fd[0]);
  int status = 0;
  ::waitpid(pid, &status, 0);
  r.code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  if (!sent) r.output += "\n[test: no line asked for the interrupt]";
  return r;
}

// A 64x48 generated scene (seed 4, 8 views, one held out) at ROOT/scene and
// 150 iterations of stage 1 on it at ROOT/model: what the commands that act
// on a trained model (remove, simulate) are tested on. Without the learned
// sky (the default would choose one here: 20% of its pixels are open at a
// 2-px radius): 150 iterations with it leave the objects half transparent
// (alpha 0.33 at the click (32, 30) of view_001; the sky starts as the fit
// to the photos, docs/design.md section 5.7), and a click needs alpha 0.5.
inline void make_small_trained_model(const std::filesystem::path& root) {
  std::filesystem::remove_all(root);
  SynthOptions o;
  o.seed = 4;
  o.width = 64;
  o.height = 48;
  o.views = 8;
  o.points = 800;
  o.feature_dim = 84;
  write_synth_scene((root / "scene").string(), o);
  const auto r = run_cli("train " + (root / "scene").string() + " -o " + (root / "model").string() +
                         " --iters 150 --stages 1 --eval --seed 1 --quiet --sky-degree -1");
  EXPECT_EQ(r.code, 0) << r.output;
}

}  // namespace ag2gs::test
