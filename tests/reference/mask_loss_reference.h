// Double-precision reference of the SAM mask losses (host/losses/mask_loss.h):
//   L_is = sum_j sum_{p in M_j} |G(p) - Gbar_j|_1 / sum_j |M_j|
//   L_ic = 1 / (m (m - 1)) sum_{j != k} 1 / (|Gbar_j - Gbar_k|_1 + 1)
// with G = F, or F / alpha and pixels with alpha < alpha_min excluded.
// Written the plain way, independent of the device's structure: explicit
// membership lists, the loss differentiated with respect to the mask means
// and the pixels, then the means scattered back to their pixels (chain rule
// step by step). The feature map is [H,W,3] interleaved, alpha [H,W] or none,
// labels [layers,H,W] with -1 for no mask.
#pragma once

#include <cstdint>
#include <vector>

namespace ag2gs::ref {

struct RefMaskLoss {
  double l_is = 0, l_ic = 0;
  int masks = 0;               // present masks m
  int64_t mask_pixels = 0;     // sum_j |M_j| over valid pixels
  std::vector<double> means;   // [count,3] Gbar_j (0 for absent masks)
  std::vector<int64_t> sizes;  // [count] |M_j|
  // Gradients of each loss separately (when requested): [H,W,3] w.r.t. F and
  // [H,W] w.r.t. alpha (zero without alpha).
  std::vector<double> grad_is, grad_ic, grad_alpha_is, grad_alpha_ic;
  // Distance to the kinks of |.|: the smallest |G_c(p) - Gbar_jc| over mask
  // pixels, and the smallest |Gbar_jc - Gbar_kc| over pairs of present masks
  // (+inf when there is none). Finite differences need both well above the step.
  double margin_is = 0, margin_ic = 0;
};

RefMaskLoss mask_loss(const std::vector<double>& feature, const std::vector<double>* alpha,
                      const std::vector<int32_t>& labels, int layers, int count, int width, int height, bool with_grad,
                      double alpha_min = 0.1);

// Convenience for float inputs.
RefMaskLoss mask_loss(const std::vector<float>& feature, const std::vector<float>* alpha,
                      const std::vector<int32_t>& labels, int layers, int count, int width, int height, bool with_grad,
                      double alpha_min = 0.1);

}  // namespace ag2gs::ref
