// Double-precision reference of the anchor growth statistics.
#include "tests/reference/growth_stats_reference.h"

#include <cmath>

namespace ag2gs::ref {

RefGrowthStats growth_stats_reference(size_t n) {
  RefGrowthStats s;
  s.grad_sum.assign(n, 0);
  s.count.assign(n, 0);
  s.last_seen.assign(n, 0);
  return s;
}

void accumulate_growth_stats(RefGrowthStats& s, const std::vector<float>& v_px, const std::vector<int>& radii,
                             int width, int height, bool ndc) {
  ++s.step;
  const double sx = ndc ? 0.5 * width : 1, sy = ndc ? 0.5 * height : 1;
  for (size_t g = 0; g < s.grad_sum.size(); ++g) {
    if (radii[g] <= 0) continue;
    const double gx = double(v_px[2 * g]) * sx, gy = double(v_px[2 * g + 1]) * sy;
    const double norm = std::sqrt(gx * gx + gy * gy);
    if (std::isfinite(norm) && std::abs(gy) < 1e29) s.grad_sum[g] += norm;
    ++s.count[g];
    s.last_seen[g] = s.step;
  }
}

}  // namespace ag2gs::ref
