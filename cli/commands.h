#pragma once

#include <CLI/CLI.hpp>
#include <functional>

#include "queries/query.h"

namespace ag2gs::cli {

struct GlobalOptions {
  int device = -1;
  bool verbose = false;
  bool quiet = false;
};

// Number checks with readable messages (CLI11's PositiveNumber and
// NonNegativeNumber print the largest double, 309 digits, as the bound).
CLI::Validator positive_number();      // a finite number > 0
CLI::Validator non_negative_number();  // a finite number >= 0
// A seed: a whole number from 0 to 2^64 - 1, written in digits (no sign,
// fraction or exponent: "-1" and "1e23" would otherwise wrap silently).
CLI::Validator seed_number();

// Adds every subcommand; each stores its action for run_selected().
void register_commands(CLI::App& app, GlobalOptions& global);
// Stores the action run when `sub` is the selected subcommand.
void set_action(CLI::App* sub, std::function<void()> action);

// Subcommands defined in their own files.
void register_devices(CLI::App& app, GlobalOptions& global);        // devices (cmd_devices.cpp)
void register_render(CLI::App& app, GlobalOptions& global);         // render (cmd_render.cpp)
void register_scene_commands(CLI::App& app, GlobalOptions& global);  // info, sfm, undistort (cmd_scene.cpp)
void register_synth(CLI::App& app, GlobalOptions& global);          // synth (cmd_synth.cpp)
void register_train(CLI::App& app, GlobalOptions& global);          // train (cmd_train.cpp)
void register_baseline(CLI::App& app, GlobalOptions& global);       // baseline (cmd_baseline.cpp)
void register_query(CLI::App& app, GlobalOptions& global);          // query (cmd_query.cpp)
void register_eval(CLI::App& app, GlobalOptions& global);           // eval (cmd_eval.cpp)
// The QueryConfig flags shared by query and eval (cmd_query.cpp).
void add_query_config_options(CLI::App* sub, QueryConfig& config);
// Runs the parsed subcommand; returns the process exit code.
int run_selected(CLI::App& app, const GlobalOptions& global);

}  // namespace ag2gs::cli
