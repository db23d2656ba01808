#include "tests/reference/propagation_loss_reference.h"

#include <cmath>

namespace ag2gs::ref {

namespace {

double sq_dist(const std::vector<double>& f, int i, int j) {
  double s = 0;
  for (int c = 0; c < 3; ++c) s += (f[3 * i + c] - f[3 * j + c]) * (f[3 * i + c] - f[3 * j + c]);
  return s;
}

}  // namespace

RefPropLoss propagation_loss_reference(const std::vector<std::pair<int, int>>& edges, const std::vector<double>& f,
                                       double tau, bool differentiate_weights) {
  RefPropLoss r;
  r.grad.assign(f.size(), 0.0);
  if (edges.empty()) return r;
  const double n = static_cast<double>(edges.size());
  const double two_tau2 = 2 * tau * tau;
  for (const auto& [i, j] : edges) {
    const double d = sq_dist(f, i, j);
    const double w = std::exp(-d / two_tau2);
    r.loss += w * d / n;
    // dL/dd for this edge: w (weights constant) or w + d dw/dd = w (1 - d / (2 tau^2)).
    const double dl_dd = (differentiate_weights ? w * (1 - d / two_tau2) : w) / n;
    for (int c = 0; c < 3; ++c) {
      const double dd_dfi = 2 * (f[3 * i + c] - f[3 * j + c]);  // dd/df_j is its negative
      r.grad[3 * i + c] += dl_dd * dd_dfi;
      r.grad[3 * j + c] -= dl_dd * dd_dfi;
    }
  }
  return r;
}

double propagation_loss_frozen_weights(const std::vector<std::pair<int, int>>& edges, const std::vector<double>& f,
                                       const std::vector<double>& f_weights, double tau) {
  if (edges.empty()) return 0;
  double loss = 0;
  for (const auto& [i, j] : edges) loss += std::exp(-sq_dist(f_weights, i, j) / (2 * tau * tau)) * sq_dist(f, i, j);
  return loss / static_cast<double>(edges.size());
}

}  // namespace ag2gs::ref
