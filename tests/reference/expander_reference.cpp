// Double-precision reference of the expansion's backward pass.
#include "tests/reference/expander_reference.h"

#include <cmath>

namespace ag2gs::ref {

namespace {

double sigmoid(double x) {
  return 1.0 / (1.0 + std::exp(-x));
}

}  // namespace

RefAnchorGrads expand_backward_reference(const AnchorModel& m, const RefGrads& v, int sh_degree) {
  const size_t K = m.children(), N = m.gaussians();
  const int S = sh_coeffs_for_degree(sh_degree);
  RefAnchorGrads r;
  r.feature.assign(m.size() * 3, 0.0);
  r.offset.resize(N * 3);
  r.scale_logit.resize(N * 3);
  r.quat.resize(N * 4);
  r.opacity_logit.resize(N);
  r.sh.assign(N * 48, 0.0);
  for (size_t g = 0; g < N; ++g) {
    const size_t a = g / K;
    const double l = m.voxel()[a], cap = m.config().cap(m.layer()[a]);
    for (int k = 0; k < 3; ++k) {
      r.offset[3 * g + k] = v.means[3 * g + k] * l;
      // s (1 - s) as sigmoid(x) sigmoid(-x): 1 - s cancels catastrophically for large x.
      const double x = m.scale_logit()[3 * g + k];
      r.scale_logit[3 * g + k] = v.scales[3 * g + k] * l * cap * sigmoid(x) * sigmoid(-x);
      r.feature[3 * a + k] += v.features[3 * g + k];
    }
    for (int k = 0; k < 4; ++k) r.quat[4 * g + k] = v.quats[4 * g + k];
    const double x = m.opacity_logit()[g];
    r.opacity_logit[g] = v.opacities[g] * sigmoid(x) * sigmoid(-x);
    for (int j = 0; j < S * 3; ++j) r.sh[48 * g + j] = v.sh[S * 3 * g + j];
  }
  return r;
}

}  // namespace ag2gs::ref
