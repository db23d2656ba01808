#include "host/io/json_input.h"

#include <filesystem>
#include <fstream>
#include <sstream>
#include <stdexcept>

namespace ag2gs {

int json_nesting_depth(const std::string& text, int stop_at) {
  int depth = 0, deepest = 0;
  bool in_string = false, escaped = false;
  for (char c : text) {
    if (in_string) {
      if (escaped)
        escaped = false;
      else if (c == '\\')
        escaped = true;
      else if (c == '"')
        in_string = false;
      continue;
    }
    if (c == '"') {
      in_string = true;
    } else if (c == '[' || c == '{') {
      if (++depth > deepest) deepest = depth;
      if (deepest > stop_at) return deepest;
    } else if ((c == ']' || c == '}') && depth > 0) {
      --depth;
    }
  }
  return deepest;
}

nlohmann::json parse_json_input(const std::string& text, const std::string& source) {
  if (json_nesting_depth(text) > kJsonMaxDepth)
    throw std::runtime_error(source + ": JSON nested deeper than " + std::to_string(kJsonMaxDepth) +
                             " levels; this is not a file ag2gs wrote (or it was damaged)");
  try {
    return nlohmann::json::parse(text);
  } catch (const nlohmann::json::exception& e) {
    throw std::runtime_error(source + ": not valid JSON (" + e.what() + ")");
  }
}

nlohmann::json read_json_file(const std::string& path) {
  std::error_code ec;
  if (std::filesystem::is_directory(path, ec))
    throw std::runtime_error(path + ": is a folder, where a JSON file was expected");
  std::ifstream in(path, std::ios::binary);
  if (!in) throw std::runtime_error(path + ": cannot open (missing or unreadable)");
  std::stringstream ss;
  ss << in.rdbuf();
  if (in.bad()) throw std::runtime_error(path + ": cannot be read");
  return parse_json_input(ss.str(), path);
}

}  // namespace ag2gs
