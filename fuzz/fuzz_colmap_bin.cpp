// libFuzzer target for read_colmap_model on binary models (cameras.bin,
// images.bin, points3D.bin split from one input: fuzz_common.h).
#include "fuzz/fuzz_colmap.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  return ag2gs::fuzz::fuzz_colmap_model(data, size, ".bin");
}
