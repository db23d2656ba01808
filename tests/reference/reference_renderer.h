// A plain double-precision CPU reference of the rasterizer (forward and
// analytic backward), implementing docs/rasterizer.md literally: no tiles, every
// pixel loops over all visible Gaussians in (z, index) order. The device kernels
// are compared against it, and it is itself checked against central finite
// differences (tests/host/render/test_reference_gradients.cpp).
//
// Culling by extent (step 9) uses the exact box [u - rx, u + rx] x [v - ry, v + ry]
// without the kernels' 0.1% + 0.01 px widening: a Gaussian is visible when some
// pixel centre of the image lies in it. Images are unaffected by the widening
// (outside the box alpha < 1/255), but radii and visibility can differ from the
// device's at that rounding margin.
#pragma once

#include <cstddef>
#include <vector>

#include "host/core/gaussians.h"

namespace ag2gs::ref {

// A GaussianSet in double, same layout, so that finite-difference perturbations
// are not rounded to float.
struct RefGaussians {
  int sh_degree = 0;
  std::vector<double> means;      // [N,3]
  std::vector<double> scales;     // [N,3]
  std::vector<double> quats;      // [N,4] w x y z
  std::vector<double> opacities;  // [N]
  std::vector<double> sh;         // [N,K,3]
  std::vector<double> features;   // [N,3]

  size_t size() const { return opacities.size(); }
  int sh_coeffs() const { return sh_coeffs_for_degree(sh_degree); }
};

RefGaussians to_double(const GaussianSet& set);

// One Gaussian after projection (docs/rasterizer.md steps 1-11).
struct RefProjected {
  bool visible = false;
  double u = 0, v = 0;          // mean2d in pixels
  double conic[3] = {0, 0, 0};  // (A, B, C) = inverse of cov2d
  double cov2d[3] = {0, 0, 0};  // (a, b, c), includes the low-pass (RenderSettings::lowpass)
  double z = 0;                 // camera-space depth
  double opacity = 0;
  double rgb[3] = {0, 0, 0};  // SH colour + 0.5, clamped at 0
  double feature[3] = {0, 0, 0};
  double rx = 0, ry = 0;  // half-widths of the alpha >= 1/255 box
  int radius = 0;         // ceil(max(rx, ry)), 0 when culled
  // Discrete states the backward pass keeps fixed.
  int clamp_x = 0, clamp_y = 0;                 // Jacobian clamp: -1 low limit, 0 free, +1 high limit
  bool rgb_clamped[3] = {false, false, false};  // SH colour + 0.5 < 0
};

// Double images, row-major like RenderOutput.
struct RefImages {
  int width = 0, height = 0;
  std::vector<double> rgb;         // [H,W,3] includes T * background
  std::vector<double> feature;     // [H,W,3]
  std::vector<double> depth;       // [H,W] sum w z
  std::vector<double> alpha;       // [H,W] 1 - T
  std::vector<double> distortion;  // [H,W] sum_{i<j} w_i w_j (m_i - m_j)^2
  std::vector<int> n_contrib;      // [H,W] Gaussians blended per pixel
  std::vector<int> radii;          // [N]
};

// Double gradients with the shapes of GaussianGrads.
struct RefGrads {
  std::vector<double> means;      // [N,3]
  std::vector<double> scales;     // [N,3]
  std::vector<double> quats;      // [N,4] w.r.t. the unnormalised input
  std::vector<double> opacities;  // [N]
  std::vector<double> sh;         // [N,K,3], 0 above the active degree
  std::vector<double> features;   // [N,3]
  std::vector<double> means2d;    // [N,2] w.r.t. (u, v)
};

// Gradients w.r.t. the projected quantities, the output of the blending
// backward (zero for Gaussians that are not visible).
struct RefProjectedGrads {
  double u = 0, v = 0;
  double conic[3] = {0, 0, 0};
  double z = 0;
  double opacity = 0;
  double rgb[3] = {0, 0, 0};
  double feature[3] = {0, 0, 0};
};

// Active SH degree: settings.sh_degree < 0 ? set degree : min(settings, set).
int active_sh_degree(int set_degree, const RenderSettings& settings);
// The real SH basis of degree 0..3 (3DGS constants and order) at unit d: b[0..(degree+1)^2).
void sh_values(int degree, const Eigen::Vector3d& d, double b[16]);

// Projection of every Gaussian (culled ones have visible = false, radius 0).
std::vector<RefProjected> project(const RefGaussians& set, const Camera& camera, const RenderSettings& settings);
std::vector<RefProjected> project(const GaussianSet& set, const Camera& camera, const RenderSettings& settings);

// Blending of already projected Gaussians (the second half of render).
RefImages blend(const std::vector<RefProjected>& projected, const Camera& camera, const RenderSettings& settings);

// render = blend(project(...)).
RefImages render(const RefGaussians& set, const Camera& camera, const RenderSettings& settings);
RefImages render(const GaussianSet& set, const Camera& camera, const RenderSettings& settings);
// The reference at a sample of pixels (row-major indices into the camera's
// image); returns images of width pixels.size() and height 1.
RefImages render_pixels(const GaussianSet& set, const Camera& camera, const RenderSettings& settings,
                        const std::vector<int>& pixels);

// Backward of blend: upstream image gradients -> per-Gaussian gradients of the
// projected quantities. Empty vectors in `grads` mean zero.
std::vector<RefProjectedGrads> blend_backward(const std::vector<RefProjected>& projected, const Camera& camera,
                                              const RenderSettings& settings, const OutputGrads& grads);

// Full analytic backward of render.
RefGrads render_backward(const RefGaussians& set, const Camera& camera, const RenderSettings& settings,
                         const OutputGrads& grads);
RefGrads render_backward(const GaussianSet& set, const Camera& camera, const RenderSettings& settings,
                         const OutputGrads& grads);

// An encoding of every discrete decision of render: visibility, sort order,
// Jacobian and colour clamp states, and per pixel the fate of each Gaussian
// considered (skipped for sigma < 0, skipped for alpha < 1/255, blended,
// blended with alpha clamped at 0.99, stop). Equal vectors mean the same smooth
// piece of the function; finite differences are only valid when x-h, x and x+h
// give equal vectors.
std::vector<int> discrete_decisions(const RefGaussians& set, const Camera& camera, const RenderSettings& settings);
// The blending part alone: sort order and per-pixel fates.
std::vector<int> discrete_decisions(const std::vector<RefProjected>& projected, const Camera& camera,
                                    const RenderSettings& settings);

}  // namespace ag2gs::ref
