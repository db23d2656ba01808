// The body of the two COLMAP targets: the input is split into cameras,
// images and points3D (fuzz_common.h: split_three) with the given extension,
// then read_colmap_model reads the folder.
#pragma once

#include <cstdlib>
#include <exception>
#include <filesystem>

#include "fuzz/fuzz_common.h"
#include "host/io/colmap_reader.h"

namespace ag2gs::fuzz {

inline int fuzz_colmap_model(const uint8_t* data, size_t size, const char* ext) {
  static const std::string dir = [] {
    const std::string d = temp_dir() + "/sparse";
    std::filesystem::create_directories(d);
    return d;
  }();
  const ThreeFiles files = split_three(data, size);
  const char* stems[3] = {"cameras", "images", "points3D"};
  for (int i = 0; i < 3; ++i) write_file(dir + "/" + stems[i] + ext, files.data[i], files.size[i]);
  ColmapModel model;
  try {
    model = read_colmap_model(dir);
  } catch (const std::exception&) {
    return 0;  // rejected with a message: fine
  }
  if (model.points.size() != model.colors.size()) std::abort();
  for (const Camera& cam : model.cameras_for_images) {
    try {
      cam.validate();
    } catch (const std::exception&) {
      std::abort();  // the reader returned an unusable camera
    }
  }
  return 0;
}

}  // namespace ag2gs::fuzz
