// Running the ag2gs program from a test, as a script would.
#pragma once

#include <sys/wait.h>

#include <array>
#include <cstdio>
#include <cstdlib>
#include <string>

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

}  // namespace ag2gs::test
