#include "host/core/nearest.h"

#include <algorithm>
#include <cstddef>
#include <limits>
#include <stdexcept>

namespace ag2gs {

std::vector<double> nearest_squared_distances(const std::vector<Eigen::Vector3d>& points, int k) {
  if (k < 1) throw std::invalid_argument("nearest_squared_distances: k must be >= 1");
  const double inf = std::numeric_limits<double>::infinity();
  const size_t kk = static_cast<size_t>(k);
  std::vector<double> out(points.size() * kk, inf);
  std::vector<int> order;
  for (size_t i = 0; i < points.size(); ++i)
    if (points[i].allFinite()) order.push_back(static_cast<int>(i));
  // Sweep along the axis of widest spread, from the 5th to the 95th
  // percentile so that a few far points do not choose it: points on a plane
  // across the sweep's axis would make it visit every pair.
  int axis = 0;
  double widest = -1;
  for (int a = 0; a < 3 && !order.empty(); ++a) {
    std::vector<double> v;
    v.reserve(order.size());
    for (int i : order) v.push_back(points[i][a]);
    const size_t lo = v.size() / 20, hi = v.size() - 1 - v.size() / 20;
    std::nth_element(v.begin(), v.begin() + static_cast<std::ptrdiff_t>(lo), v.end());
    const double vlo = v[lo];
    std::nth_element(v.begin(), v.begin() + static_cast<std::ptrdiff_t>(hi), v.end());
    if (v[hi] - vlo > widest) widest = v[hi] - vlo, axis = a;
  }
  std::sort(order.begin(), order.end(), [&](int a, int b) {
    const double xa = points[a][axis], xb = points[b][axis];
    return xa < xb || (xa == xb && a < b);
  });
  const size_t n = order.size();
  for (size_t oi = 0; oi < n; ++oi) {
    const Eigen::Vector3d& p = points[order[oi]];
    double* best = out.data() + static_cast<size_t>(order[oi]) * kk;  // ascending
    auto consider = [&](size_t oj) {
      double d = (points[order[oj]] - p).squaredNorm();
      if (!(d < best[kk - 1])) return;
      size_t j = kk - 1;
      for (; j > 0 && best[j - 1] > d; --j) best[j] = best[j - 1];
      best[j] = d;
    };
    for (size_t oj = oi + 1; oj < n; ++oj) {
      const double dx = points[order[oj]][axis] - p[axis];
      if (dx * dx > best[kk - 1]) break;
      consider(oj);
    }
    for (size_t oj = oi; oj-- > 0;) {
      const double dx = p[axis] - points[order[oj]][axis];
      if (dx * dx > best[kk - 1]) break;
      consider(oj);
    }
  }
  return out;
}

}  // namespace ag2gs
