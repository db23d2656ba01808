// Writing COLMAP sparse models (binary or text), readable by COLMAP itself
// (`colmap model_converter`) and by host/io/colmap_reader.h.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <string>
#include <vector>

#include "host/core/gaussians.h"

namespace ag2gs {

// Writes cameras, images and points3D (.bin when binary, else .txt) into
// `sparse_dir` (created if missing). Every image gets its own PINHOLE camera
// (camera id = image id = index + 1) with the intrinsics of `cameras[i]`; the
// image name is cameras[i].name; the rotation is stored as a unit quaternion
// (w, x, y, z) of R. Points get ids 1..P, colours `colors` (same length as
// `points`, or empty = grey), error 0 and an empty track; images list no 2D
// points. Each file is written atomically (temp file + rename). Throws
// std::invalid_argument for mismatched sizes or an invalid camera,
// std::runtime_error naming the file when writing fails.
void write_colmap_model(const std::string& sparse_dir, const std::vector<Camera>& cameras,
                        const std::vector<Eigen::Vector3d>& points,
                        const std::vector<Eigen::Vector3<uint8_t>>& colors, bool binary = true);

}  // namespace ag2gs
