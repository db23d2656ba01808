#include "host/render/importance.h"

#include <algorithm>
#include <numeric>
#include <stdexcept>
#include <string>

namespace ag2gs {

std::vector<double> blend_weight_sums(Renderer& renderer, const DeviceGaussians& g, const std::vector<Camera>& cameras,
                                      const RenderSettings& settings) {
  std::vector<double> sums(g.n, 0.0);
  if (g.n == 0) return sums;
  std::vector<float> grads;
  for (const Camera& cam : cameras) {
    renderer.bin(g, cam, settings);
    renderer.blend_weights();
    renderer.device_weight_sums().download(grads, g.n);
    for (size_t i = 0; i < g.n; ++i) sums[i] += static_cast<double>(grads[i]);
  }
  return sums;
}

std::vector<uint8_t> least_drawing_anchors(const std::vector<double>& per_child, int children, double share) {
  if (children < 1 || per_child.size() % static_cast<size_t>(children) != 0)
    throw std::invalid_argument("least_drawing_anchors: " + std::to_string(per_child.size()) +
                                " weight sums are not a whole number of anchors of " + std::to_string(children) +
                                " children");
  const size_t anchors = per_child.size() / static_cast<size_t>(children);
  std::vector<double> drawn(anchors, 0.0);
  double total = 0;
  for (size_t a = 0; a < anchors; ++a) {
    for (int i = 0; i < children; ++i) drawn[a] += per_child[a * children + i];
    total += drawn[a];
  }
  std::vector<uint8_t> keep(anchors, 1);
  std::vector<size_t> order(anchors);
  std::iota(order.begin(), order.end(), size_t{0});
  std::sort(order.begin(), order.end(),
            [&](size_t x, size_t y) { return drawn[x] < drawn[y] || (drawn[x] == drawn[y] && x < y); });
  const double budget = share * total;
  double taken = 0;
  for (size_t k = 0; k + 1 < anchors; ++k) {
    const size_t a = order[k];
    if (taken + drawn[a] > budget) break;
    taken += drawn[a];
    keep[a] = 0;
  }
  return keep;
}

}  // namespace ag2gs
