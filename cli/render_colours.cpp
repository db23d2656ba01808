#include "cli/render_colours.h"

#include <cmath>

namespace ag2gs::cli {

std::vector<float> instance_colours(const std::vector<int32_t>& ids) {
  std::vector<float> rgb(3 * ids.size(), 0.f);
  for (size_t p = 0; p < ids.size(); ++p) {
    if (ids[p] < 0) continue;
    const double h = std::fmod(0.618033988749895 * ids[p], 1.0) * 6.0;
    const int k = static_cast<int>(h);
    const float f = static_cast<float>(h - k), v = 0.95f, s = 0.75f;
    const float pp = v * (1 - s), q = v * (1 - s * f), t = v * (1 - s * (1 - f));
    const float c[6][3] = {{v, t, pp}, {q, v, pp}, {pp, v, t}, {pp, q, v}, {t, pp, v}, {v, pp, q}};
    for (int j = 0; j < 3; ++j) rgb[3 * p + j] = c[k % 6][j];
  }
  return rgb;
}

std::vector<float> feature_colours(const std::vector<float>& feature, const std::vector<float>& alpha) {
  std::vector<float> rgb(feature.size(), 0.f);
  for (size_t p = 0; p < alpha.size(); ++p) {
    const float* f = &feature[3 * p];
    const float n = std::sqrt(f[0] * f[0] + f[1] * f[1] + f[2] * f[2]);
    if (alpha[p] < 0.1f || n < 1e-12f) continue;
    for (int c = 0; c < 3; ++c) rgb[3 * p + c] = 0.5f + 0.5f * f[c] / n;
  }
  return rgb;
}

}  // namespace ag2gs::cli
