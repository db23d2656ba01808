#include "cli/commands.h"

#include <spdlog/spdlog.h>

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <map>
#include <sstream>
#include <utility>

#include "cli/run_guard.h"

namespace ag2gs::cli {

namespace {

std::map<CLI::App*, std::function<void()>>& actions() {
  static std::map<CLI::App*, std::function<void()>> a;
  return a;
}

}  // namespace

void register_commands(CLI::App& app, GlobalOptions& global) {
  register_devices(app, global);
  register_render(app, global);
  register_info(app, global);
  register_scene_commands(app, global);
  register_synth(app, global);
  register_train(app, global);
  register_baseline(app, global);
  register_query(app, global);
  register_eval(app, global);
  register_remove(app, global);
  register_simulate(app, global);
  register_view(app, global);
}

namespace {

// Whether `v` is a finite number written alone; its value in *x.
bool parse_finite(const std::string& v, double* x) {
  char* end = nullptr;
  *x = std::strtod(v.c_str(), &end);
  return end != v.c_str() && *end == 0 && std::isfinite(*x);
}

// Most settings are stored as float: a larger value would become infinite.
constexpr double kFlagMax = 3.4e38;

}  // namespace

CLI::Validator positive_number() {
  return CLI::Validator(
      [](std::string& v) -> std::string {
        double x = 0;
        if (!parse_finite(v, &x) || !(x > 0) || x > kFlagMax)
          return "must be a number > 0 (at most 3.4e38), not '" + v + "'";
        return {};
      },
      "> 0", "positive");
}

CLI::Validator non_negative_number() {
  return CLI::Validator(
      [](std::string& v) -> std::string {
        double x = 0;
        if (!parse_finite(v, &x) || !(x >= 0) || x > kFlagMax)
          return "must be a number >= 0 (at most 3.4e38), not '" + v + "'";
        return {};
      },
      ">= 0", "non-negative");
}

CLI::Validator finite_range(double lo, double hi) {
  const std::string range = fmt::format("[{} - {}]", lo, hi);
  return CLI::Validator(
      [lo, hi, range](std::string& v) -> std::string {
        double x = 0;
        if (!parse_finite(v, &x) || !(x >= lo && x <= hi)) return "must be a number in " + range + ", not '" + v + "'";
        return {};
      },
      range, "finite range");
}

CLI::Validator output_path() {
  return CLI::Validator(
      [](std::string& v) -> std::string {
        return v.empty() ? "must name a file or folder; it is empty (a quoted '' or an unset shell variable?)" : "";
      },
      "PATH", "output path");
}

CLI::Validator seed_number() {
  return CLI::Validator(
      [](std::string& v) -> std::string {
        const std::string bad = "must be a whole number from 0 to 18446744073709551615, not '" + v + "'";
        if (v.empty() || v.size() > 20 || v.find_first_not_of("0123456789") != std::string::npos) return bad;
        errno = 0;
        std::strtoull(v.c_str(), nullptr, 10);
        if (errno == ERANGE) return bad;
        return {};
      },
      "0..2^64-1", "seed");
}

std::shared_ptr<bool> add_print_config_flag(CLI::App* sub, const std::string& verb) {
  auto flag = std::make_shared<bool>(false);
  sub->add_flag("--print-config", *flag,
                "Print the settings this command would " + verb +
                    " (the defaults, then the flags given; JSON) and exit without reading anything");
  return flag;
}

void build_app(CLI::App& app, GlobalOptions& global) {
  app.require_subcommand(1);
  app.fallthrough();  // global options also after the subcommand: `ag2gs render ... --device 1`
  app.add_option("--device", global.device,
                 "OpenCL device index (see `ag2gs devices`); default $AG2GS_DEVICE, "
                 "else the first GPU, else the CPU")
      ->check(non_negative_number());
  app.add_flag("-v,--verbose", global.verbose, "Log more detail");
  app.add_flag("-q,--quiet", global.quiet, "Log only warnings and errors");
  register_commands(app, global);
}

namespace {

// The whole command line built for one in-process call; however the call
// ends, its subcommands' actions leave the table with it.
struct ScopedApp {
  CLI::App app{"ag2gs"};
  GlobalOptions global;
  ScopedApp() { build_app(app, global); }
  ~ScopedApp() {
    for (CLI::App* sub : app.get_subcommands({})) actions().erase(sub);
  }
};

}  // namespace

void run_command(const std::vector<std::string>& args) {
  ScopedApp scoped;
  CLI::App& app = scoped.app;
  const GlobalOptions& global = scoped.global;
  std::vector<std::string> reversed(args.rbegin(), args.rend());  // CLI11 takes them last first
  try {
    app.parse(reversed);
  } catch (const CLI::ParseError& e) {
    if (e.get_exit_code() == 0) {  // --help: printed as the program prints it
      app.exit(e);
      return;
    }
    std::string what = e.what();
    if (what.empty()) what = "invalid command line";
    throw std::invalid_argument(what);
  }
  // The command logs as the program does; the caller's level comes back after.
  struct Restore {
    spdlog::level::level_enum level = spdlog::get_level();
    ~Restore() {
      InterruptGuard::set_throw_on_exit(false);
      spdlog::set_level(level);
    }
  } restore;
  spdlog::set_level(global.verbose ? spdlog::level::debug : global.quiet ? spdlog::level::warn : spdlog::level::info);
  spdlog::set_pattern("%^%l%$: %v");
  InterruptGuard::set_throw_on_exit(true);
  for (auto* sub : app.get_subcommands()) {
    auto it = actions().find(sub);
    if (it == actions().end()) continue;
    it->second();
    return;
  }
  throw std::invalid_argument("no command given");
}

std::string command_help(const std::string& command) {
  ScopedApp scoped;
  for (CLI::App* sub : scoped.app.get_subcommands({}))
    if (sub->get_name() == command) return sub->help("ag2gs " + command);
  throw std::invalid_argument("no command '" + command + "'; see `ag2gs --help`");
}

namespace {
TrainProgressHook& progress_hook() {
  static TrainProgressHook hook;
  return hook;
}
}  // namespace

void set_train_progress_hook(TrainProgressHook hook) {
  progress_hook() = std::move(hook);
}
const TrainProgressHook& train_progress_hook() {
  return progress_hook();
}

void set_action(CLI::App* sub, std::function<void()> action) {
  actions()[sub] = std::move(action);
}

std::string unknown_command_hint(CLI::App& app, int argc, const char* const* argv) {
  std::string word;
  for (int i = 1; i < argc && word.empty(); ++i) {
    const std::string a = argv[i];
    if (a == "--device") {
      ++i;  // its value
    } else if (!a.empty() && a[0] != '-') {
      word = a;
    }
  }
  if (word.empty()) return "";
  // Levenshtein distance, for the nearest name.
  auto distance = [](const std::string& x, const std::string& y) {
    std::vector<size_t> row(y.size() + 1);
    for (size_t j = 0; j <= y.size(); ++j) row[j] = j;
    for (size_t i = 1; i <= x.size(); ++i) {
      size_t diag = row[0];
      row[0] = i;
      for (size_t j = 1; j <= y.size(); ++j) {
        const size_t up = row[j];
        row[j] = std::min({row[j] + 1, row[j - 1] + 1, diag + (x[i - 1] == y[j - 1] ? 0 : 1)});
        diag = up;
      }
    }
    return row[y.size()];
  };
  std::string best, names;
  size_t best_d = SIZE_MAX;
  for (const CLI::App* sub : app.get_subcommands([](CLI::App*) { return true; })) {
    const std::string& name = sub->get_name();
    if (name == word) return "";
    names += (names.empty() ? "" : ", ") + name;
    const size_t d = distance(word, name);
    if (d < best_d) best_d = d, best = name;
  }
  std::string hint = "ag2gs: unknown command '" + word + "'";
  if (best_d <= std::max<size_t>(2, word.size() / 3)) hint += "; did you mean '" + best + "'?";
  return hint + " The commands: " + names + " (`ag2gs --help` says what each does)";
}

int run_selected(CLI::App& app, const GlobalOptions& global) {
  spdlog::set_level(global.verbose ? spdlog::level::debug : global.quiet ? spdlog::level::warn : spdlog::level::info);
  spdlog::set_pattern("%^%l%$: %v");
  for (auto* sub : app.get_subcommands()) {
    auto it = actions().find(sub);
    if (it == actions().end()) continue;
    try {
      it->second();
      return 0;
    } catch (const std::exception& e) {
      std::fprintf(stderr, "ag2gs %s: error: %s\n", sub->get_name().c_str(), e.what());
      return 1;
    }
  }
  return 2;
}

}  // namespace ag2gs::cli
