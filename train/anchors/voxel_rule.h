// The top-layer voxel edge of the anchor grid, chosen from the scene when the
// user gives neither --voxel-size nor --top-cells.
//
// Rule (footprint): the finest layer's voxel should cover about
// kFinestVoxelPixels pixels of a training view at the typical depth of the
// scene's SfM points, so that the finest anchors are as fine as the images
// can show and no finer. For each training view, the median over the points
// that project into it of depth / focal length (world units per pixel at
// that point) is taken; the median of those over the views is the scene's
// world size of a pixel, and
//
//   top voxel = kFinestVoxelPixels * pixel size * layer_ratio^(layers - 1).
//
// Both medians ignore outliers (a few far or near points move neither), and
// duplicate points count once per copy, which a median also shrugs off. With
// no point in front of any view the rule falls back to the robust extent of
// the points divided by kFallbackTopCells.
//
// Measured against fixed cell counts on the panel (README, train section).
#pragma once

#include <Eigen/Core>
#include <string>
#include <vector>

#include "host/core/gaussians.h"
#include "host/scene/scene.h"
#include "train/anchors/anchor_model.h"

namespace ag2gs {

// Pixels covered by a finest-layer voxel edge at the points' median depth.
inline constexpr double kFinestVoxelPixels = 1.0;
// Top-layer cells along the robust extent when the footprint has no data.
inline constexpr int kFallbackTopCells = 25;

struct VoxelChoice {
  double top_voxel = 0;   // edge of a top-layer voxel, world units
  std::string rule;       // which rule chose it, for the log ("--voxel-size", "--top-cells", "footprint", ...)
  double pixel_size = 0;  // footprint rule: world size of one pixel at the median depth (0 otherwise)
  int views_used = 0;     // footprint rule: views with at least one point in front and inside
  double extent = 0;      // the robust extent of the points
  // One line for the log: the value and why.
  std::string describe(int layers, int layer_ratio) const;
};

// The world size of one pixel at the points' typical depth: the median over
// `cameras` of the median of z / fx over the points inside that camera's
// image (z > 0). Returns 0 (and views_used 0) when no camera sees a point.
// Non-finite points are skipped.
double median_pixel_size(const std::vector<Eigen::Vector3d>& points, const std::vector<Camera>& cameras,
                         int* views_used = nullptr);

// --voxel-size (config.voxel_size > 0) wins, then --top-cells (> 0, the
// robust extent / top_cells), then the footprint rule above on `cameras`
// (the training views at the loaded resolution), then the fallback.
// Throws std::invalid_argument when the result is not a positive finite
// number (no spread of points and no camera sees one).
VoxelChoice choose_top_voxel(const AnchorConfig& config, const SceneBounds& bounds,
                             const std::vector<Eigen::Vector3d>& points, const std::vector<Camera>& cameras);

}  // namespace ag2gs
