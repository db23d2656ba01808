// libFuzzer target for read_ply (host/io/ply_io.h). A file that reads must give
// a GaussianSet whose arrays agree in size.
#include <cstdlib>
#include <exception>

#include "fuzz/fuzz_common.h"
#include "host/io/ply_io.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string path = ag2gs::fuzz::temp_dir() + "/input.ply";
  ag2gs::fuzz::write_file(path, data, size);
  ag2gs::GaussianSet gs;
  try {
    gs = ag2gs::read_ply(path);
  } catch (const std::exception&) {
    return 0;  // rejected with a message: fine
  }
  try {
    gs.validate();
  } catch (const std::exception&) {
    std::abort();  // the reader returned inconsistent arrays
  }
  return 0;
}
