#include "host/device/kernel_source.h"

#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <stdexcept>

namespace fs = std::filesystem;

namespace ag2gs {

std::string kernel_source(const std::string& name) {
  auto read_file = [](const fs::path& p, std::string& out) {
    std::ifstream f(p, std::ios::binary);
    if (!f) return false;
    std::ostringstream s;
    s << f.rdbuf();
    out = s.str();
    return true;
  };
  std::string text;
  if (const char* dir = std::getenv("AG2GS_KERNEL_DIR"); dir && *dir) {
    if (read_file(fs::path(dir) / name, text)) return text;
    throw std::runtime_error("AG2GS_KERNEL_DIR=" + std::string(dir) + " has no " + name +
                             "; point it at the kernels/ folder of the source tree or unset it");
  }
#ifdef AG2GS_EMBED_KERNELS
  for (auto& k : embedded_kernels())
    if (name == k.name) return k.text;
#endif
  if (read_file(fs::path(AG2GS_SOURCE_KERNEL_DIR) / name, text)) return text;
  throw std::runtime_error("kernel source " + name + " not found (not embedded and not in " +
                           std::string(AG2GS_SOURCE_KERNEL_DIR) + "); set AG2GS_KERNEL_DIR to the kernels/ folder");
}

}  // namespace ag2gs
