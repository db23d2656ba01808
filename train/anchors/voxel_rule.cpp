#include "train/anchors/voxel_rule.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <stdexcept>

#include "host/core/nearest.h"

namespace ag2gs {
namespace {

// The lower median (deterministic for even counts); `v` is reordered.
double median_of(std::vector<double>& v) {
  const auto mid = v.begin() + static_cast<std::ptrdiff_t>((v.size() - 1) / 2);
  std::nth_element(v.begin(), mid, v.end());
  return *mid;
}

std::string fmt_g(double x) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%.4g", x);
  return buf;
}

}  // namespace

double median_pixel_size(const std::vector<Eigen::Vector3d>& points, const std::vector<Camera>& cameras,
                         int* views_used) {
  std::vector<double> per_view, ratios;
  ratios.reserve(points.size());
  for (const Camera& cam : cameras) {
    if (!(cam.fx > 0) || !(cam.fy > 0)) continue;
    ratios.clear();
    for (const Eigen::Vector3d& p : points) {
      if (!p.allFinite()) continue;
      const Eigen::Vector3d q = cam.R * p + cam.t;
      if (!(q.z() > 0)) continue;
      const double u = cam.fx * q.x() / q.z() + cam.cx, v = cam.fy * q.y() / q.z() + cam.cy;
      if (!(u >= 0 && u < cam.width && v >= 0 && v < cam.height)) continue;
      ratios.push_back(q.z() / cam.fx);
    }
    if (!ratios.empty()) per_view.push_back(median_of(ratios));
  }
  if (views_used) *views_used = static_cast<int>(per_view.size());
  return per_view.empty() ? 0.0 : median_of(per_view);
}

double median_point_spacing(const std::vector<Eigen::Vector3d>& points) {
  std::vector<Eigen::Vector3d> distinct;
  for (const Eigen::Vector3d& p : points)
    if (p.allFinite()) distinct.push_back(p);
  std::sort(distinct.begin(), distinct.end(), [](const Eigen::Vector3d& a, const Eigen::Vector3d& b) {
    return std::lexicographical_compare(a.data(), a.data() + 3, b.data(), b.data() + 3);
  });
  distinct.erase(std::unique(distinct.begin(), distinct.end()), distinct.end());
  if (distinct.size() < 2) return 0.0;
  std::vector<double> d = nearest_squared_distances(distinct, 1);
  return std::sqrt(median_of(d));
}

VoxelChoice choose_top_voxel(const AnchorConfig& config, const SceneBounds& bounds,
                             const std::vector<Eigen::Vector3d>& points, const std::vector<Camera>& cameras) {
  VoxelChoice c;
  c.extent = bounds.longest_extent();
  if (!(c.extent > 0) || !std::isfinite(c.extent)) c.extent = 2.0 * bounds.camera_radius;
  if (config.voxel_size > 0) {
    c.top_voxel = config.voxel_size;
    c.rule = "--voxel-size";
  } else if (config.top_cells > 0) {
    c.top_voxel = c.extent / config.top_cells;
    c.rule = "--top-cells " + std::to_string(config.top_cells);
  } else {
    c.pixel_size = median_pixel_size(points, cameras, &c.views_used);
    const double layers_factor = std::pow(static_cast<double>(config.layer_ratio), config.layers - 1);
    if (c.pixel_size > 0 && std::isfinite(c.pixel_size)) {
      c.point_spacing = median_point_spacing(points);
      const double footprint = kFinestVoxelPixels * c.pixel_size;
      const double floor = c.point_spacing / kPointSpacingPerFinestVoxel;
      c.rule = floor > footprint ? "point spacing" : "footprint";
      c.top_voxel = std::max(footprint, floor) * layers_factor;
    } else {
      c.top_voxel = c.extent / kFallbackTopCells;
      c.rule = "fallback";
    }
  }
  if (!(c.top_voxel > 0) || !std::isfinite(c.top_voxel))
    throw std::invalid_argument(
        "the anchor voxel size is " + fmt_g(c.top_voxel) + " (" + c.rule +
        "): the scene's SfM points have no spread and no camera sees them; give --voxel-size in world units");
  return c;
}

std::string VoxelChoice::describe(int layers, int layer_ratio) const {
  const double finest = top_voxel / std::pow(static_cast<double>(layer_ratio), layers - 1);
  std::string why;
  if (rule == "footprint" || rule == "point spacing") {
    why = "a finest voxel of " + fmt_g(finest / pixel_size) + " px at the points' median depth (" + fmt_g(pixel_size) +
          " per pixel, " + std::to_string(views_used) + " views)";
    const std::string spacing = "the SfM points' median spacing (" + fmt_g(point_spacing) + ", " +
                                fmt_g(point_spacing / pixel_size) + " px) / " + fmt_g(kPointSpacingPerFinestVoxel);
    if (rule == "point spacing")
      why += ": " + spacing + ", coarser than " + fmt_g(kFinestVoxelPixels) + " px";
    else if (point_spacing > 0)
      why += "; " + spacing + " is finer";
  } else if (rule == "fallback")
    why = "no training view sees a SfM point: the robust extent / " + std::to_string(kFallbackTopCells);
  else
    why = "as given by " + rule;
  return "voxel " + fmt_g(top_voxel) + " (top layer, " + fmt_g(extent / top_voxel) +
         " cells along the extent; finest " + fmt_g(finest) + "): " + why;
}

}  // namespace ag2gs
