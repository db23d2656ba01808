// ag2gs: the command-line front end. It parses arguments and calls the core
// library; exceptions become a message on stderr and a non-zero exit here only.
#include <spdlog/spdlog.h>

#include <CLI/CLI.hpp>
#include <cstdio>
#include <exception>
#include <string>

#include "cli/commands.h"

int main(int argc, char** argv) {
  CLI::App app{"ag2gs: anchor-graph structured Gaussian splatting on any OpenCL device"};
  ag2gs::cli::GlobalOptions global;
  ag2gs::cli::build_app(app, global);
  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    if (e.get_exit_code() != 0) {
      const std::string hint = ag2gs::cli::unknown_command_hint(app, argc, argv);
      if (!hint.empty()) {
        std::fprintf(stderr, "%s\n", hint.c_str());
        return 2;
      }
    }
    return app.exit(e);
  }
  return ag2gs::cli::run_selected(app, global);
}
