// libFuzzer target for read_colmap_model on text models (cameras.txt,
// images.txt, points3D.txt split from one input: fuzz_common.h).
#include "fuzz/fuzz_colmap.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  return ag2gs::fuzz::fuzz_colmap_model(data, size, ".txt");
}
