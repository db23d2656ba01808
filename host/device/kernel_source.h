// Kernel sources: embedded at build time (cmake/embed_kernels.cmake) or read
// from a directory while editing (AG2GS_KERNEL_DIR=path/to/kernels).
#pragma once

#include <string>
#include <vector>

namespace ag2gs {

struct EmbeddedKernel {
  const char* name;  // file name, e.g. "blend_fwd.cl"
  std::string text;
};

// Generated; empty when built with AG2GS_EMBED_KERNELS=OFF.
const std::vector<EmbeddedKernel>& embedded_kernels();

// The source of kernels/<name>: from $AG2GS_KERNEL_DIR when set, else the
// embedded copy, else the source tree. Throws naming the file when missing.
std::string kernel_source(const std::string& name);

}  // namespace ag2gs
