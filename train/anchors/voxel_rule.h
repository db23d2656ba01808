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
// Floor (point spacing): the finest voxel is also at least the SfM points'
// median spacing (each distinct point's distance to its nearest other one)
// divided by kPointSpacingPerFinestVoxel. A pixel shrinks with the training
// resolution while the points that seed the anchors do not get denser: at
// 530x946 the fox's points lie 3.5 px apart and one-pixel voxels seeded
// nearly an anchor per point, growing 56% more Gaussians than at half the
// size, where the baseline's count does not grow. Growth still adds finer
// anchors where the images ask (docs/benchmarks.md, "The voxel floor").
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
// The finest voxel is at least the points' median spacing / this. The
// generated scenes' points lie 1.2-2.3 px apart and keep one-pixel voxels;
// the sparse captures (kumamon, the fox at 530x946: 3.4-3.5 px) get 1.5 px.
inline constexpr double kPointSpacingPerFinestVoxel = 2.25;
// Top-layer cells along the robust extent when the footprint has no data.
inline constexpr int kFallbackTopCells = 25;

struct VoxelChoice {
  double top_voxel = 0;   // edge of a top-layer voxel, world units
  std::string rule;       // which rule chose it, for the log ("--voxel-size", "--top-cells", "footprint",
                          // "point spacing", "fallback")
  double pixel_size = 0;  // footprint rule: world size of one pixel at the median depth (0 otherwise)
  double point_spacing = 0;  // footprint rule: the points' median nearest-neighbour distance (0: fewer than 2)
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

// The median over the distinct finite points of the distance to the nearest
// other one; 0 with fewer than two distinct points.
double median_point_spacing(const std::vector<Eigen::Vector3d>& points);

// --voxel-size (config.voxel_size > 0) wins, then --top-cells (> 0, the
// robust extent / top_cells), then the footprint rule above on `cameras`
// (the training views at the loaded resolution) with its point-spacing
// floor, then the fallback.
// Throws std::invalid_argument when the result is not a positive finite
// number (no spread of points and no camera sees one).
VoxelChoice choose_top_voxel(const AnchorConfig& config, const SceneBounds& bounds,
                             const std::vector<Eigen::Vector3d>& points, const std::vector<Camera>& cameras);

}  // namespace ag2gs
