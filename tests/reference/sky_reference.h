// Double-precision reference of the sky (host/render/sky.h, kernels/sky.cl),
// written from its definition pixel by pixel:
//   out = rgb + (1 - alpha) sky(d),  sky(d) = sum_k coef_k Y_k(d)
// with d the world direction of the pixel centre's ray and Y_k the real SH
// basis of the reference renderer (ref::sh_values). Its backward for
// L = sum over pixels and channels of g out:
//   dL/dalpha(p) = -sum_c g_c(p) sky_c(d)
//   dL/dcoef_kc  = sum_p W(p) (1 - alpha(p)) Y_k(d) g_c(p)
// and L itself, for central differences. Planes are [3,H,W] (channel-major)
// and [H,W], as the device stores them.
#pragma once

#include <Eigen/Core>
#include <vector>

#include "host/core/gaussians.h"

namespace ag2gs::ref {

// The world direction of pixel (x, y)'s centre ray, unit length.
Eigen::Vector3d pixel_ray(const Camera& c, int x, int y);

// sky(d) for coefficients [K,3] of SH degree `degree`.
Eigen::Vector3d sky_radiance(int degree, const std::vector<float>& coef, const Eigen::Vector3d& d);

struct RefSkyGrad {
  std::vector<double> alpha;  // [H,W]
  std::vector<double> coef;   // [K,3]
};

// grad: g = dL/d out [3,H,W]; alpha [H,W]. add_to [H,W] (or null): the
// alpha gradient is added to it, as Sky::backward's add. weight [H,W] (empty:
// 1) scales each pixel's share in the coefficient gradient.
RefSkyGrad sky_backward_reference(int degree, const std::vector<float>& coef, const std::vector<float>& grad,
                                  const std::vector<float>& alpha, const Camera& cam,
                                  const std::vector<float>* add_to = nullptr, const std::vector<float>& weight = {});

// L = sum over pixels and channels of g (rgb + (1 - alpha) sky(d)), with the
// coefficients and alpha in double; rgb and grad [3,H,W].
double sky_loss_reference(int degree, const std::vector<double>& coef, const std::vector<double>& alpha,
                          const std::vector<float>& rgb, const std::vector<float>& grad, const Camera& cam);

}  // namespace ag2gs::ref
