// Double-precision reference of the instance maps: every cluster's blending
// weight per pixel, accumulated exactly.
#include "tests/reference/instance_map_reference.h"

#include <algorithm>
#include <cmath>

namespace ag2gs::ref {

RefInstance instance_map_reference(const GaussianSet& set, const Camera& cam,
                                   const std::vector<int32_t>& anchor_cluster, int K, double min_fraction) {
  const std::vector<RefProjected> P = project(set, cam, RenderSettings{});
  std::vector<int> order;
  for (size_t i = 0; i < P.size(); ++i)
    if (P[i].visible) order.push_back(static_cast<int>(i));
  std::stable_sort(order.begin(), order.end(),
                   [&](int a, int b) { return P[a].z < P[b].z || (P[a].z == P[b].z && a < b); });
  const size_t npix = static_cast<size_t>(cam.width) * cam.height;
  RefInstance r;
  r.W.resize(npix);
  r.id.assign(npix, -1);
  r.best.assign(npix, 0);
  for (int y = 0; y < cam.height; ++y)
    for (int x = 0; x < cam.width; ++x) {
      const size_t p = static_cast<size_t>(y) * cam.width + x;
      const double px = x + 0.5, py = y + 0.5;
      double T = 1;
      for (int id : order) {
        const RefProjected& g = P[id];
        const double dx = g.u - px, dy = g.v - py;
        const double sigma = 0.5 * (g.conic[0] * dx * dx + g.conic[2] * dy * dy) + g.conic[1] * dx * dy;
        if (sigma < 0) continue;
        const double alpha = std::min(0.99, g.opacity * std::exp(-sigma));
        if (alpha < 1.0 / 255.0) continue;
        if (T * (1 - alpha) < 1e-4) break;
        const int c = anchor_cluster[id / K];
        if (c >= 0) r.W[p][c] += alpha * T;
        T *= 1 - alpha;
      }
      for (auto& [c, w] : r.W[p]) {
        if (w > r.best[p]) r.best[p] = w;
        if (w > min_fraction) r.id[p] = c;
      }
    }
  return r;
}

}  // namespace ag2gs::ref
