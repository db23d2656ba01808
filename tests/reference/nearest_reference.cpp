// Double-precision reference of the k nearest squared distances: brute force.
#include "tests/reference/nearest_reference.h"

#include <algorithm>
#include <limits>

namespace ag2gs::ref {

std::vector<double> nearest_squared_distances_reference(const std::vector<Eigen::Vector3d>& p, int k) {
  const double inf = std::numeric_limits<double>::infinity();
  std::vector<double> out(p.size() * k, inf);
  for (size_t i = 0; i < p.size(); ++i) {
    if (!p[i].allFinite()) continue;
    std::vector<double> d;
    for (size_t j = 0; j < p.size(); ++j)
      if (j != i && p[j].allFinite()) d.push_back((p[j] - p[i]).squaredNorm());
    std::sort(d.begin(), d.end());
    for (int c = 0; c < k && c < static_cast<int>(d.size()); ++c) out[i * k + c] = d[c];
  }
  return out;
}

}  // namespace ag2gs::ref
