// Double-precision reference of torch.optim.Adam's documented update.
#include "tests/reference/adam_reference.h"

#include <cmath>
#include <stdexcept>

namespace ag2gs::ref {

void adam_step(std::vector<double>& param, const std::vector<double>& grad, RefAdamState& state, double lr,
               double beta1, double beta2, double eps, const std::vector<int>* visible, int row_size) {
  if (grad.size() != param.size()) throw std::invalid_argument("ref::adam_step: param and grad sizes differ");
  if (state.m.empty() && state.v.empty()) {
    state.m.assign(param.size(), 0.0);
    state.v.assign(param.size(), 0.0);
  }
  if (state.m.size() != param.size() || state.v.size() != param.size())
    throw std::invalid_argument("ref::adam_step: state size differs from the parameter count");
  state.step += 1;
  const double t = static_cast<double>(state.step);
  for (size_t i = 0; i < param.size(); ++i) {
    if (visible && (*visible)[i / row_size] == 0) continue;
    state.m[i] = beta1 * state.m[i] + (1 - beta1) * grad[i];
    state.v[i] = beta2 * state.v[i] + (1 - beta2) * grad[i] * grad[i];
    const double mhat = state.m[i] / (1 - std::pow(beta1, t));
    const double vhat = state.v[i] / (1 - std::pow(beta2, t));
    param[i] -= lr * mhat / (std::sqrt(vhat) + eps);
  }
}

}  // namespace ag2gs::ref
