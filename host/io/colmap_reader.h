// A minimal reader for COLMAP sparse models (cameras, images, points3D; binary
// or text) and the camera helpers the CLI needs: resolution scaling and view
// selection. Conventions: docs/formats.md and host/core/gaussians.h (Camera).
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <string>
#include <vector>

#include "host/core/gaussians.h"

namespace ag2gs {

struct ColmapModel {
  // One Camera per registered image, sorted by image name; Camera.name is the
  // image name as COLMAP stores it (relative to the images/ folder).
  std::vector<Camera> cameras_for_images;
  // COLMAP camera model name of each image (same order), e.g. "PINHOLE".
  std::vector<std::string> camera_models;
  std::vector<Eigen::Vector3d> points;          // sparse points, by point3D id
  std::vector<Eigen::Vector3<uint8_t>> colors;  // RGB of each point
};

// Reads cameras, images and points3D from `sparse_dir` (e.g. scene/sparse/0),
// each from its .bin file when present, else from its .txt file. Supports the
// PINHOLE and SIMPLE_PINHOLE camera models. Every COLMAP model is parsed; an
// image using a distorted one (SIMPLE_RADIAL, OPENCV, ...) throws, saying how
// to undistort the images with COLMAP, unless allow_distorted (then its
// Camera holds the focal lengths and principal point only, and
// camera_models says which model it was: for reports, never for rendering).
// Throws std::runtime_error naming the file on missing files, truncated or
// malformed data and unknown camera ids.
ColmapModel read_colmap_model(const std::string& sparse_dir, bool allow_distorted = false);

// True for the models ag2gs renders directly (PINHOLE, SIMPLE_PINHOLE).
bool is_pinhole_model(const std::string& model_name);

// The camera at 1/factor resolution, as 3DGS does it: new width =
// round(width / factor) with ties to even (Python's round), likewise height;
// fx and cx scale by new_width / width, fy and cy by new_height / height.
// factor 1 returns the camera unchanged. Throws std::invalid_argument when
// factor < 1 or the image would vanish.
Camera scale_camera(const Camera& camera, int factor);
// The camera with an image of width x height (both >= 1): fx and cx scale by
// width / camera.width, fy and cy by height / camera.height.
Camera resize_camera(const Camera& camera, int width, int height);

// The cameras named in `comma_list` ("a.png,b" or "a, b"), in list order.
// Each entry matches an image name exactly, or its name without extension, or
// its file stem (no folder, no extension). An empty list selects every camera.
// Throws std::invalid_argument for an unknown or ambiguous entry, listing a
// few valid names.
std::vector<Camera> select_views(const std::vector<Camera>& cameras, const std::string& comma_list);

}  // namespace ag2gs
