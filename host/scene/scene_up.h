// Which way is up in a capture, and the plane things stand on: what the
// physics (gravity, the ground) and the support-plane click of a model
// without trained features (queries/query.h) need from a scene.
//
// Up from the cameras alone, the mean of their image "up" axes (-y in
// COLMAP's camera frame), is wrong for photos stored sideways (a phone held
// upright, saved landscape without an orientation tag): then the images'
// x axes carry up, and the -y mean lies along the table. So the main plane of
// the SfM points decides: when its normal lies within 45 degrees of one of
// the cameras' mean image axes (+-x, +-y: a floor or table photographed
// upright, sideways or upside down), up is that normal, on the side where
// most camera centres are; otherwise (a wall behind the object, too few
// points) the cameras' -y mean as before.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "host/scene/scene.h"

namespace ag2gs {

struct Plane {
  Eigen::Vector3d normal = Eigen::Vector3d::UnitZ();  // unit
  double offset = 0;                                  // normal . x = offset on the plane
  size_t inliers = 0;                                 // points within `tolerance` of it
  double tolerance = 0;
  double height(const Eigen::Vector3d& x) const { return normal.dot(x) - offset; }
};

// The plane through the most points, within 1% of the points' spread (the
// 90th percentile of their distances from the median point): 512 planes
// through point triples drawn from a counter RNG of `seed`, the best refitted
// twice to its inliers by least squares. Deterministic. Empty below 30 points
// or when the best plane holds fewer than 10% of them.
std::optional<Plane> main_plane(const std::vector<Eigen::Vector3d>& points, uint64_t seed = 1);

// The cameras' mean image axes: x (right) and -y (up in the image), not
// normalised (their length, up to 1, says how well the cameras agree).
Eigen::Vector3d mean_camera_right(const std::vector<Camera>& cameras);
Eigen::Vector3d mean_camera_up(const std::vector<Camera>& cameras);

// The up direction the cameras agree on: the mean of their "up" axes (-y in
// COLMAP's camera frame), normalised. Throws when they cancel out.
Eigen::Vector3d up_from_cameras(const std::vector<Camera>& cameras);

struct SceneUp {
  Eigen::Vector3d up = Eigen::Vector3d::UnitZ();
  std::optional<Plane> plane;  // the main plane, with `normal` along `up` when it gave up
  bool from_plane = false;     // up is the plane's normal (else the cameras' -y mean)
  std::string image_axis;      // the image axis the plane's normal lies along: "-y", "+y", "+x", "-x"; else ""
  std::string describe() const;
};

// See the file comment. Throws std::runtime_error when no plane decides and
// the cameras do not agree on an up direction (give --up).
SceneUp scene_up(const std::vector<Camera>& cameras, const std::vector<Eigen::Vector3d>& points);

}  // namespace ag2gs
