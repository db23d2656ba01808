// libFuzzer target for read_model_archive (host/io/model_io.h). An archive that
// reads must survive write + read with identical arrays and metadata.
#include <cstdlib>
#include <exception>

#include "fuzz/fuzz_common.h"
#include "host/io/model_io.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string path = ag2gs::fuzz::temp_dir() + "/input.ag2gs";
  ag2gs::fuzz::write_file(path, data, size);
  ag2gs::ModelArchive a;
  try {
    a = ag2gs::read_model_archive(path);
  } catch (const std::exception&) {
    return 0;  // rejected with a message: fine
  }
  const std::string again = ag2gs::fuzz::temp_dir() + "/again.ag2gs";
  ag2gs::write_model_archive(again, a);
  const ag2gs::ModelArchive b = ag2gs::read_model_archive(again);
  if (b.meta != a.meta || b.arrays().size() != a.arrays().size()) std::abort();
  for (const auto& [name, t] : a.arrays()) {
    const ag2gs::Tensor& u = b.tensor(name);
    if (u.dtype != t.dtype || u.shape != t.shape || u.bytes != t.bytes) std::abort();
  }
  return 0;
}
