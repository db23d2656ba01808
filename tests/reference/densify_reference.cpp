// Double-precision reference of the baseline's densification decisions,
// written the way 3DGS's densify_and_prune is.
#include "tests/reference/densify_reference.h"

#include <algorithm>
#include <cmath>

namespace ag2gs::ref {

namespace {

// One row of the growing set.
struct RefRow {
  int kind, source, sample;
  double grad, max_scale, opacity;
  int radius;
};

}  // namespace

std::vector<DensifyRow> densify_reference(const FreeGaussians& g, const DensifyStats& s, const FreeTrainConfig& c,
                                          double extent, bool prune_big) {
  std::vector<RefRow> rows;
  for (size_t i = 0; i < g.size(); ++i) {
    double ms = -1e300;
    for (int k = 0; k < 3; ++k) ms = std::max(ms, std::exp(static_cast<double>(g.log_scale[i * 3 + k])));
    const double grad = s.count[i] == 0 ? 0.0 : static_cast<double>(s.grad_sum[i]) / s.count[i];
    rows.push_back({0, static_cast<int>(i), 0, grad, ms, 1 / (1 + std::exp(-static_cast<double>(g.opacity_logit[i]))),
                    s.max_radius[i]});
  }
  const size_t n = rows.size();
  for (size_t i = 0; i < n; ++i)
    if (rows[i].grad >= c.grad_threshold && rows[i].max_scale <= c.percent_dense * extent) {
      RefRow r = rows[i];
      r.kind = 1;
      r.grad = 0;
      r.radius = 0;
      rows.push_back(r);
    }
  std::vector<bool> remove(rows.size(), false);
  const size_t grown = rows.size();
  for (int sample = 0; sample < 2; ++sample)
    for (size_t i = 0; i < grown; ++i)
      if (rows[i].grad >= c.grad_threshold && rows[i].max_scale > c.percent_dense * extent) {
        RefRow r = rows[i];
        r.kind = 2;
        r.sample = sample;
        r.grad = 0;
        r.radius = 0;
        r.max_scale = rows[i].max_scale / 1.6;
        rows.push_back(r);
        remove[i] = true;
      }
  remove.resize(rows.size(), false);
  std::vector<DensifyRow> out;
  for (size_t i = 0; i < rows.size(); ++i) {
    if (remove[i]) continue;
    bool prune = rows[i].opacity < c.prune_opacity;
    if (prune_big) {
      prune = prune || rows[i].radius > c.max_screen_size;
      prune = prune || rows[i].max_scale > c.max_world_size * extent;
    }
    if (!prune) out.emplace_back(rows[i].kind, rows[i].source, rows[i].sample);
  }
  return out;
}

}  // namespace ag2gs::ref
