// Small text helpers shared by the library and the program.
#pragma once

#include <sstream>
#include <string>
#include <vector>

namespace ag2gs {

// "a, b,,c" -> {"a", "b", "c"}: comma-separated items, blanks around them
// trimmed, empty items dropped.
inline std::vector<std::string> split_list(const std::string& s) {
  std::vector<std::string> out;
  std::stringstream ss(s);
  std::string item;
  while (std::getline(ss, item, ',')) {
    item.erase(0, item.find_first_not_of(" \t"));
    item.erase(item.find_last_not_of(" \t") + 1);
    if (!item.empty()) out.push_back(item);
  }
  return out;
}

}  // namespace ag2gs
