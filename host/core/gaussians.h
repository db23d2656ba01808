// Core data types shared by the renderer, the I/O code, the stages and the
// tests. Semantics of every field: docs/rasterizer.md.
#pragma once

#include <Eigen/Core>
#include <array>
#include <cstddef>
#include <string>
#include <vector>

namespace ag2gs {

// The degree-0 real spherical harmonic, Y_0^0 = 1 / (2 sqrt(pi)): a DC
// coefficient c gives the colour c * kShC0 (+ 0.5 in the renderer).
constexpr double kShC0 = 0.28209479177387814;

// SH coefficients per colour channel for a degree (0..3).
inline int sh_coeffs_for_degree(int degree) {
  return (degree + 1) * (degree + 1);
}

// A set of 3D Gaussians with activated parameters (float32, row-major).
struct GaussianSet {
  int sh_degree = 0;             // 0..3
  std::vector<float> means;      // [N,3] world position
  std::vector<float> scales;     // [N,3] standard deviations (> 0)
  std::vector<float> quats;      // [N,4] w x y z, need not be normalised
  std::vector<float> opacities;  // [N]   in [0,1]
  std::vector<float> sh;         // [N,K,3] K = (sh_degree+1)^2, sh[(n*K+k)*3+c]
  std::vector<float> features;   // [N,3] semantic feature

  size_t size() const { return opacities.size(); }
  int sh_coeffs() const { return sh_coeffs_for_degree(sh_degree); }
  // Resizes every array for n Gaussians (new entries zero).
  void resize(size_t n);
  // The Gaussians at rows `ids` (each < size()), in that order.
  GaussianSet rows(const std::vector<size_t>& ids) const;
  // Throws std::invalid_argument naming the array whose size is wrong.
  void validate() const;
};

// Gradients with the shapes of a GaussianSet's arrays.
struct GaussianGrads {
  std::vector<float> means;      // [N,3]
  std::vector<float> scales;     // [N,3]
  std::vector<float> quats;      // [N,4]
  std::vector<float> opacities;  // [N]
  std::vector<float> sh;         // [N,K,3]
  std::vector<float> features;   // [N,3]
  std::vector<float> means2d;    // [N,2] screen-space gradient (for densification)
};

// A pinhole camera in COLMAP's convention: X_cam = R X_world + t, +z forward,
// x right, y down, u = fx x/z + cx, top-left pixel centre at (0.5, 0.5).
struct Camera {
  int width = 0;
  int height = 0;
  double fx = 0, fy = 0, cx = 0, cy = 0;
  Eigen::Matrix3d R = Eigen::Matrix3d::Identity();  // world -> camera
  Eigen::Vector3d t = Eigen::Vector3d::Zero();
  std::string name;  // image file name, when known

  Eigen::Vector3d center() const { return -R.transpose() * t; }
  // Throws std::invalid_argument when sizes or intrinsics are unusable.
  void validate() const;
};

struct RenderSettings {
  std::array<float, 3> background{0.f, 0.f, 0.f};
  float near_plane = 0.01f;
  int sh_degree = -1;      // active SH degree; -1 = the set's degree
  float dist_near = 0.2f;  // depth mapping of the distortion term (2DGS)
  float dist_far = 100.0f;
  // Screen-space low-pass added to each splat's 2D covariance, in pixels^2
  // of the rendered image (3DGS: 0.3).
  static constexpr float kDefaultLowpass = 0.3f;
  float lowpass = kDefaultLowpass;
  // false: the semantic feature planes are not blended (written as zeros),
  // ~15% less blend_fwd work on CPUs; for frames whose features nobody reads
  // (training steps without mask losses). The renderer's backward pass
  // then refuses a feature gradient (std::logic_error).
  bool features = true;
};

// Per-pixel images, row-major [H,W,C].
struct RenderOutput {
  int width = 0;
  int height = 0;
  std::vector<float> rgb;         // [H,W,3] includes T * background
  std::vector<float> feature;     // [H,W,3]
  std::vector<float> depth;       // [H,W]   sum w z (divide by alpha for mean depth)
  std::vector<float> alpha;       // [H,W]   1 - T
  std::vector<float> distortion;  // [H,W]   sum_{i<j} w_i w_j (m_i - m_j)^2
  std::vector<int> n_contrib;     // [H,W]   Gaussians blended (device only)
  std::vector<int> radii;         // [N]     0 = culled
};

// Upstream gradients on the outputs; an empty vector means zero.
struct OutputGrads {
  std::vector<float> rgb;         // [H,W,3]
  std::vector<float> feature;     // [H,W,3]
  std::vector<float> depth;       // [H,W]
  std::vector<float> alpha;       // [H,W]
  std::vector<float> distortion;  // [H,W]
};

}  // namespace ag2gs
