// Double-precision reference of the propagation loss (train/graph/propagation_loss.h)
// written from an explicit list of undirected edges rather than from CSR rows:
//   L = (1 / |E|) sum_{(i,j) in E} w_ij d_ij,  d_ij = |f_i - f_j|^2,
//   w_ij = exp(-d_ij / (2 tau^2))
// and its gradient, scattered edge by edge to both ends.
#pragma once

#include <utility>
#include <vector>

namespace ag2gs::ref {

struct RefPropLoss {
  double loss = 0;
  std::vector<double> grad;  // [A,3] dL/df
};

// edges: pairs (i, j), i != j, each undirected edge once; f: [A,3].
// differentiate_weights = false: w_ij is treated as a constant in the
// gradient; true: the exact gradient of L.
RefPropLoss propagation_loss_reference(const std::vector<std::pair<int, int>>& edges, const std::vector<double>& f,
                                       double tau, bool differentiate_weights);

// The loss with the weights computed from `f_weights` instead of f, i.e. the
// function whose gradient at f = f_weights is the stop-gradient gradient
// (for finite differences of that mode).
double propagation_loss_frozen_weights(const std::vector<std::pair<int, int>>& edges, const std::vector<double>& f,
                                       const std::vector<double>& f_weights, double tau);

}  // namespace ag2gs::ref
