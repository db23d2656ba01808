// libFuzzer target for read_npy (host/io/npy_io.h). A file that reads must also
// survive write_npy + read_npy unchanged (shape and every bit).
#include <cstdlib>
#include <cstring>
#include <exception>

#include "fuzz/fuzz_common.h"
#include "host/io/npy_io.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string path = ag2gs::fuzz::temp_dir() + "/input.npy";
  ag2gs::fuzz::write_file(path, data, size);
  ag2gs::NpyArray a;
  try {
    a = ag2gs::read_npy(path);
  } catch (const std::exception&) {
    return 0;  // rejected with a message: fine
  }
  size_t count = 1;
  for (int64_t d : a.shape) count *= static_cast<size_t>(d);
  if (count != a.data.size()) std::abort();  // the shape must describe the data

  const std::string copy = ag2gs::fuzz::temp_dir() + "/copy.npy";
  ag2gs::write_npy(copy, a.data, a.shape);
  const ag2gs::NpyArray b = ag2gs::read_npy(copy);
  if (b.shape != a.shape || b.data.size() != a.data.size() ||
      (!a.data.empty() && std::memcmp(a.data.data(), b.data.data(), a.data.size() * sizeof(float)) != 0)) {
    std::abort();
  }
  return 0;
}
