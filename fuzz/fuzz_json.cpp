// libFuzzer target for the JSON readers of queries and evaluation
// (host/io/semantic_io.h): the first input byte picks the reader.
#include <exception>

#include "fuzz/fuzz_common.h"
#include "host/io/semantic_io.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  if (size < 1) return 0;
  const std::string path = ag2gs::fuzz::temp_dir() + "/input.json";
  ag2gs::fuzz::write_file(path, data + 1, size - 1);
  try {
    switch (data[0] % 3) {
      case 0:
        ag2gs::read_vocabulary(path);
        break;
      case 1: {
        const ag2gs::LabelFrame f = ag2gs::read_label_frame(path);
        // Rasterise small frames too (polygons with wild coordinates).
        if (static_cast<long>(f.width) * f.height <= 1 << 16) {
          for (const std::string& c : f.categories()) f.mask(c);
        }
        break;
      }
      default:
        ag2gs::read_clicks(path);
    }
  } catch (const std::exception&) {
  }
  return 0;
}
