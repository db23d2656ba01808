// Plain-loop reference of region growing: a fixed point over the anchor graph.
#include "tests/reference/region_grow_reference.h"

#include <cmath>

namespace ag2gs::ref {

std::vector<int32_t> region_grow_reference(const AnchorGraph& g, const std::vector<float>& features, int32_t seed,
                                           float tau, float min_weight) {
  std::vector<uint8_t> in(g.anchors(), 0);
  in[seed] = 1;
  for (bool changed = true; changed;) {
    changed = false;
    for (size_t i = 0; i < in.size(); ++i) {
      if (!in[i]) continue;
      for (int e = g.row_offsets()[i]; e < g.row_offsets()[i + 1]; ++e) {
        const int j = g.neighbours()[e];
        double d2 = 0;
        for (int c = 0; c < 3; ++c) d2 += std::pow(double(features[3 * i + c]) - features[3 * j + c], 2);
        if (!in[j] && std::exp(-d2 / (2.0 * tau * tau)) > min_weight) in[j] = 1, changed = true;
      }
    }
  }
  std::vector<int32_t> out;
  for (size_t i = 0; i < in.size(); ++i)
    if (in[i]) out.push_back(static_cast<int32_t>(i));
  return out;
}

}  // namespace ag2gs::ref
