// Shared plumbing of the libFuzzer targets: every parser reads from a path,
// so each input is written to files in a temporary folder of this process
// first. A parser may throw only std::exception subclasses; anything else
// escaping it, a crash, a sanitizer report or a hang is a finding.
#pragma once

#include <unistd.h>

#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <string>

namespace ag2gs::fuzz {

// The per-process temporary folder ($TMPDIR or /tmp), removed at exit. The
// name lives on the heap, never freed, so that the exit handler cannot run
// after its destructor.
inline const std::string& temp_dir() {
  static const std::string* dir = [] {
    const char* base = std::getenv("TMPDIR");
    auto* name = new std::string(std::string(base && *base ? base : "/tmp") + "/ag2gs_fuzz_XXXXXX");
    if (!::mkdtemp(&(*name)[0])) {
      std::perror("mkdtemp");
      std::abort();
    }
    std::atexit([] {
      std::error_code ec;
      std::filesystem::remove_all(*dir, ec);
    });
    return name;
  }();
  return *dir;
}

// Writes bytes to `path`; a failure here is the harness's, not the parser's.
inline void write_file(const std::string& path, const uint8_t* data, size_t size) {
  std::FILE* f = std::fopen(path.c_str(), "wb");
  if (!f || (size > 0 && std::fwrite(data, 1, size, f) != size) || std::fclose(f) != 0) {
    std::perror(path.c_str());
    std::abort();
  }
}

// Splits an input into three files: two little-endian uint32 lengths, then
// the first file, the second file and the rest (lengths clamped to what is
// there), so that the fuzzer can grow or shrink each file on its own.
struct ThreeFiles {
  const uint8_t* data[3];
  size_t size[3];
};
inline ThreeFiles split_three(const uint8_t* data, size_t size) {
  auto take_u32 = [&](size_t at) -> uint32_t {
    uint32_t v = 0;
    for (size_t b = 0; b < 4 && at + b < size; ++b) v |= uint32_t(data[at + b]) << (8 * b);
    return v;
  };
  const uint32_t len0 = take_u32(0), len1 = take_u32(4);
  const size_t header = size < 8 ? size : 8;
  ThreeFiles f;
  size_t at = header;
  const size_t lens[2] = {len0, len1};
  for (int i = 0; i < 2; ++i) {
    const size_t n = lens[i] < size - at ? lens[i] : size - at;
    f.data[i] = data + at;
    f.size[i] = n;
    at += n;
  }
  f.data[2] = data + at;
  f.size[2] = size - at;
  return f;
}

}  // namespace ag2gs::fuzz
