#pragma once

#include <CLI/CLI.hpp>
#include <functional>

namespace ag2gs::cli {

struct GlobalOptions {
  int device = -1;
  bool verbose = false;
  bool quiet = false;
};

// Adds every subcommand; each stores its action for run_selected().
void register_commands(CLI::App& app, GlobalOptions& global);
// Runs the parsed subcommand; returns the process exit code.
int run_selected(CLI::App& app, const GlobalOptions& global);

}  // namespace ag2gs::cli
