// Plain-loop references of the language attachment: the per-pair scores and
// the softmax-weighted CLIP feature of a cluster.
#include "tests/reference/language_reference.h"

#include <algorithm>
#include <cmath>

namespace ag2gs::ref {

std::vector<MaskMatch> language_scores_reference(const std::vector<int32_t>& ids, int clusters,
                                                 const std::vector<float>& feat, const std::vector<float>& alpha,
                                                 const ViewMasks& masks, bool by_alpha) {
  const size_t npix = ids.size();
  auto in_mask = [&](size_t p, int m) {
    for (int l = 0; l < masks.layers; ++l)
      if (masks.labels[l * npix + p] == m) return true;
    return false;
  };
  auto g_at = [&](size_t p, double g[3]) {
    for (int k = 0; k < 3; ++k) g[k] = feat[k * npix + p];
    if (!by_alpha) return true;
    if (!(alpha[p] >= 0.1f)) return false;
    for (int k = 0; k < 3; ++k) g[k] = static_cast<float>(static_cast<float>(g[k]) / alpha[p]);
    return true;
  };
  std::vector<MaskMatch> out;
  for (int c = 0; c < clusters; ++c)
    for (int m = 0; m < masks.count; ++m) {
      int64_t inter = 0, uni = 0, nc = 0, nm = 0;
      double sc[3] = {0, 0, 0}, sm[3] = {0, 0, 0};
      for (size_t p = 0; p < npix; ++p) {
        const bool a = ids[p] == c, b = in_mask(p, m);
        inter += a && b;
        uni += a || b;
        double g[3];
        if (!g_at(p, g)) continue;
        if (a) {
          ++nc;
          for (int k = 0; k < 3; ++k) sc[k] += g[k];
        }
        if (b) {
          ++nm;
          for (int k = 0; k < 3; ++k) sm[k] += g[k];
        }
      }
      if (inter == 0) continue;
      MaskMatch mm;
      mm.cluster = c;
      mm.mask = m;
      mm.intersection = inter;
      mm.iou = double(inter) / double(uni);
      if (nc > 0 && nm > 0) {
        double d = 0;
        for (int k = 0; k < 3; ++k) d += std::abs(sc[k] / nc - sm[k] / nm);
        mm.feature_l1 = d;
        mm.score = mm.iou * (1 - d);
      } else {
        mm.feature_l1 = NAN;
      }
      out.push_back(mm);
    }
  return out;
}

std::vector<double> language_feature_reference(const std::vector<std::pair<double, std::vector<double>>>& matches,
                                               int dim, double softmax_scale) {
  double smax = -1e9, z = 0;
  for (auto& [s, f] : matches) smax = std::max(smax, s);
  std::vector<double> mean(dim, 0);
  for (auto& [s, f] : matches) {
    const double w = std::exp(softmax_scale * (s - smax));
    z += w;
    for (int k = 0; k < dim; ++k) mean[k] += w * f[k];
  }
  double n = 0;
  for (double& x : mean) {
    x /= z;
    n += x * x;
  }
  n = std::sqrt(n);
  for (double& x : mean) x /= n;
  return mean;
}

}  // namespace ag2gs::ref
