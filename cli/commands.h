#pragma once

#include <CLI/CLI.hpp>
#include <cstdio>
#include <functional>
#include <memory>
#include <nlohmann/json.hpp>
#include <string>
#include <utility>
#include <vector>

#include "apps/selection/selection.h"  // QueryRequest, TrainedModel and the query's steps
#include "host/core/text.h"            // split_list
#include "host/io/model_io.h"
#include "host/scene/scene.h"
#include "queries/query.h"
#include "train/anchors/anchor_model.h"
#include "train/model_check.h"  // recorded_resolution, recorded_sh_degree
#include "train/stage3/clustering.h"
#include "train/stage3/language.h"

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
// A finite number in [lo, hi] (CLI::Range lets 'nan' through).
CLI::Validator finite_range(double lo, double hi);

// A seed: a whole number from 0 to 2^64 - 1, written in digits (no sign,
// fraction or exponent: "-1" and "1e23" would otherwise wrap silently).
CLI::Validator seed_number();
// An output path: not empty (`-o ''` wrote into the current folder).
CLI::Validator output_path();

// --print-config: "Print the settings this command would <verb> ... and
// exit"; the flag's value lives as long as the action holding it.
std::shared_ptr<bool> add_print_config_flag(CLI::App* sub, const std::string& verb);
// Validates `config` and prints its to_json() alone on stdout (2-space JSON).
template <typename Config>
void print_config_json(const Config& config) {
  config.validate();
  std::printf("%s\n", config.to_json().dump(2).c_str());
}

// Adds every subcommand; each stores its action for run_selected().
void register_commands(CLI::App& app, GlobalOptions& global);
// The program's whole command line as main() builds it: the global options
// (--device, -v, -q) and every subcommand.
void build_app(CLI::App& app, GlobalOptions& global);

// One command line (the words after `ag2gs`) run in this process, as the
// program runs it, for the Python module: a parse error throws
// std::invalid_argument with CLI11's message, a command's error propagates
// as thrown, and a run stopped by a signal or by the progress hook below
// throws StoppedAfterSaving once its checkpoint is written.
void run_command(const std::vector<std::string>& args);
// `ag2gs COMMAND --help`'s text (the Python module's docstrings).
std::string command_help(const std::string& command);

// Training progress for a library caller, called after every training
// iteration with {"iteration", "iterations", "stage", "loss", "psnr", "l1",
// "ssim", "anchors", "gaussians"}; returning false stops the run as Ctrl-C
// does (it finishes the iteration and writes its checkpoint). Empty = none.
using TrainProgressHook = std::function<bool(const nlohmann::json&)>;
void set_train_progress_hook(TrainProgressHook hook);
const TrainProgressHook& train_progress_hook();
// Stores the action run when `sub` is the selected subcommand.
void set_action(CLI::App* sub, std::function<void()> action);

// Subcommands defined in their own files.
void register_devices(CLI::App& app, GlobalOptions& global);        // devices (cmd_devices.cpp)
void register_render(CLI::App& app, GlobalOptions& global);         // render (cmd_render.cpp)
void register_info(CLI::App& app, GlobalOptions& global);           // info (cmd_info.cpp)
void register_scene_commands(CLI::App& app, GlobalOptions& global);  // sfm, undistort (cmd_scene.cpp)
void register_synth(CLI::App& app, GlobalOptions& global);          // synth (cmd_synth.cpp)
void register_train(CLI::App& app, GlobalOptions& global);          // train (cmd_train.cpp)
void register_baseline(CLI::App& app, GlobalOptions& global);       // baseline (cmd_baseline.cpp)
void register_query(CLI::App& app, GlobalOptions& global);          // query (cmd_query.cpp)
void register_eval(CLI::App& app, GlobalOptions& global);           // eval (cmd_eval.cpp)
void register_remove(CLI::App& app, GlobalOptions& global);         // remove (cmd_remove.cpp)
void register_simulate(CLI::App& app, GlobalOptions& global);       // simulate (cmd_simulate.cpp)
void register_view(CLI::App& app, GlobalOptions& global);           // view (viewer/view_server.cpp)
// The QueryConfig flags shared by query and eval (cmd_query.cpp).
void add_query_config_options(CLI::App* sub, QueryConfig& config);

// --view, --click, --text, --vocab, --text-embedding, --click-by (a
// QueryRequest, apps/selection/selection.h).
void add_query_request_options(CLI::App* sub, QueryRequest& request);
// A 0/1 mask [H,W] as the bytes of an 8-bit PNG (0/255).
std::vector<uint8_t> encode_mask_png(const std::vector<uint8_t>& mask, int width, int height);
// The same PNG, written atomically.
void write_mask_png(const std::string& path, const std::vector<uint8_t>& mask, int width, int height);
// Runs the parsed subcommand; returns the process exit code.
int run_selected(CLI::App& app, const GlobalOptions& global);
// For a command line whose first word is not a subcommand ("ag2gs trian
// ..."): "unknown command 'trian'; did you mean 'train'? ..." naming the
// nearest subcommand by edit distance; empty when the word is a subcommand
// or there is no word.
std::string unknown_command_hint(CLI::App& app, int argc, const char* const* argv);

}  // namespace ag2gs::cli
