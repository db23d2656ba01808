// Double-precision reference of Adam as torch.optim.Adam documents it
// (weight decay 0, amsgrad and maximize off):
//   m_t = beta1 m_{t-1} + (1 - beta1) g_t
//   v_t = beta2 v_{t-1} + (1 - beta2) g_t^2
//   mhat = m_t / (1 - beta1^t),  vhat = v_t / (1 - beta2^t)
//   theta_t = theta_{t-1} - lr mhat / (sqrt(vhat) + eps)
// The device (host/optim/adam.h) computes the same thing in torch's implementation
// form; this is the documented one.
#pragma once

#include <cstdint>
#include <vector>

namespace ag2gs::ref {

struct RefAdamState {
  std::vector<double> m, v;  // zero-initialised to the parameter count on first use
  int64_t step = 0;
};

// One step. visible: per row of row_size values, rows with 0 are left
// untouched (parameters and moments); the step count advances regardless.
void adam_step(std::vector<double>& param, const std::vector<double>& grad, RefAdamState& state, double lr,
               double beta1 = 0.9, double beta2 = 0.999, double eps = 1e-15, const std::vector<int>* visible = nullptr,
               int row_size = 1);

}  // namespace ag2gs::ref
