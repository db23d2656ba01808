// The k nearest other points of every point of a small 3-d set (SfM points:
// thousands to a few hundred thousand), exactly, by a sweep along the axis
// of widest spread (5th to 95th percentile): each point's candidates are scanned outwards in that
// order until the gap along the axis alone exceeds its k-th best distance.
// Deterministic (ties keep index order); the distances do not depend on the
// axis.
#pragma once

#include <Eigen/Core>
#include <vector>

namespace ag2gs {

// [points.size() * k] squared distances, each point's k smallest in
// ascending order (infinity where fewer than k other points exist).
// Non-finite points take part in nothing and get infinity.
std::vector<double> nearest_squared_distances(const std::vector<Eigen::Vector3d>& points, int k);

}  // namespace ag2gs
