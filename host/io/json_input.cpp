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

std::string json_error_text(const nlohmann::json::exception& e) {
  std::string text = e.what();
  if (text.rfind("[json.exception.", 0) == 0) {
    const size_t end = text.find("] ");
    if (end != std::string::npos) text.erase(0, end + 2);
  }
  // "syntax error while parsing value - unexpected end of input; ..." says
  // the same twice.
  const std::string noise = "syntax error while parsing value - ";
  const size_t at = text.find(noise);
  if (at != std::string::npos) text.erase(at, noise.size());
  return text;
}

nlohmann::json parse_json_input(const std::string& text, const std::string& source) {
  if (json_nesting_depth(text) > kJsonMaxDepth)
    throw std::runtime_error(source + ": JSON nested deeper than " + std::to_string(kJsonMaxDepth) +
                             " levels; this is not a file ag2gs wrote (or it was damaged)");
  if (text.find_first_not_of(" \t\r\n") == std::string::npos)
    throw std::runtime_error(source + ": not valid JSON (it is empty)");
  try {
    return nlohmann::json::parse(text);
  } catch (const nlohmann::json::exception& e) {
    throw std::runtime_error(source + ": not valid JSON (" + json_error_text(e) + ")");
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
