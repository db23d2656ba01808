// Double-precision reference of the 3DGS photometric loss (host/losses/image_loss.h):
//   L = (1 - lambda) L1 + lambda (1 - SSIM)
// written the plain way, independent of the device's structure: the 11x11
// window is summed directly in 2D (no separable passes) and the gradient is
// the quotient rule on the raw moments, scattered back through the 2D window.
// Images are [H,W,3] row-major interleaved; weights [H,W] or none.
#pragma once

#include <vector>

namespace ag2gs::ref {

struct RefImageLoss {
  double loss = 0, l1 = 0, ssim = 1, mse = 0;
  std::vector<double> ssim_map;  // [H,W,3]
  std::vector<double> grad;      // [H,W,3] dL/d(rendered), when requested
};

// 3DGS's gaussian(11, 1.5), normalised: taps at offsets -5..5.
std::vector<double> ssim_window_1d();

RefImageLoss image_loss(const std::vector<double>& rendered, const std::vector<double>& target, int width, int height,
                        double lambda, bool with_grad, const std::vector<double>* weights = nullptr);

// Convenience for float images.
RefImageLoss image_loss(const std::vector<float>& rendered, const std::vector<float>& target, int width, int height,
                        double lambda, bool with_grad, const std::vector<float>* weights = nullptr);

}  // namespace ag2gs::ref
