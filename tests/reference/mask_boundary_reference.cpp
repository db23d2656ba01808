// Plain-loop reference of a mask's boundary region, from its definition.
#include "tests/reference/mask_boundary_reference.h"

namespace ag2gs::ref {

std::vector<uint8_t> mask_boundary_reference(const std::vector<uint8_t>& m, int w, int h, int d) {
  std::vector<uint8_t> out(m.size(), 0);
  for (int y = 0; y < h; ++y)
    for (int x = 0; x < w; ++x) {
      if (!m[static_cast<size_t>(y) * w + x]) continue;
      bool edge = false;
      for (int dy = -d; dy <= d && !edge; ++dy)
        for (int dx = -d; dx <= d && !edge; ++dx) {
          const int u = x + dx, v = y + dy;
          edge = u < 0 || v < 0 || u >= w || v >= h || !m[static_cast<size_t>(v) * w + u];
        }
      out[static_cast<size_t>(y) * w + x] = edge;
    }
  return out;
}

}  // namespace ag2gs::ref
