// Running the ag2gs program from a test, as a script would.
#pragma once

#include <gtest/gtest.h>
#include <sys/wait.h>

#include <array>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <string>

#include "synth/synth_scene.h"

namespace ag2gs::test {

struct CliResult {
  int code;            // exit status, -1 when it did not exit normally
  std::string output;  // stdout and stderr together
};

// Runs `$AG2GS_BINARY args` (default ./ag2gs) through the shell.
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
