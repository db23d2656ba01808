// Double-precision reference of the k nearest squared distances
// (host/core/nearest.h, nearest_squared_distances), a brute-force O(N^2)
// loop instead of the library's sweep: for every finite point, the squared
// distances to every other finite point, sorted, the k smallest kept
// (infinity where fewer exist); non-finite points get infinity.
#pragma once

#include <Eigen/Core>
#include <vector>

namespace ag2gs::ref {

// [p.size() * k], each point's k smallest in ascending order.
std::vector<double> nearest_squared_distances_reference(const std::vector<Eigen::Vector3d>& p, int k);

}  // namespace ag2gs::ref
