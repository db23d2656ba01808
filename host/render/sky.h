// The sky: a learned colour per viewing direction behind the Gaussians
// (kernels/sky.cl, docs/design.md section 12). Open-air captures show the
// sky in most views and no SfM point lies on it; without a model of its
// own, the trainer either leaves it black or smears large, faint Gaussians
// between the cameras and the objects to paint it, and those floaters hide
// the objects in new views. The sky is a sum of real spherical harmonics
// of the world-space ray direction (degree 0..3, K = (degree + 1)^2
// coefficients per channel, linear: no offset, no clamp), composited where
// the Gaussians leave the ray transparent:
//
//   out = rgb + (1 - alpha) * sky(d)
//
// with rgb the renderer's blend over a black background. Degree 0 is a
// learned constant background. Everything per pixel runs on the device; the
// coefficient gradient is summed in a fixed order (no atomics), so training
// with the sky stays bit-reproducible.
#pragma once

#include <Eigen/Core>
#include <array>
#include <cstddef>
#include <cstdint>
#include <map>
#include <optional>
#include <string>
#include <vector>

#include "host/core/gaussians.h"
#include "host/device/cl_runtime.h"
#include "host/io/model_io.h"

namespace ag2gs {

constexpr int kSkyMaxDegree = 3;

// Coefficients [K, 3] of a constant colour (only the degree-0 term set).
std::vector<float> sky_constant(int degree, const std::array<float, 3>& colour);
// The degree whose coefficient count K*3 is `values`; -1 when none is.
int sky_degree_for(size_t values);

// Which pixels may teach the sky. A pixel near the projection of an SfM
// point (in front of the camera) shows a surface, which is the Gaussians'
// to explain; the others (open sky, or a surface without features such as
// a white wall far behind) are open. open_sky_pixels: [H, W], 1 where no
// point projects within `radius` pixels, else 0. open_sky_radius: the
// default radius, 3% of the longer image side (at least 2 pixels).
// open_sky_weights: each f x f block's open fraction, [H/f, W/f] (rounded
// down, at least 1), the layout of box_downscale_planar.
std::vector<uint8_t> open_sky_pixels(const Camera& camera, const std::vector<Eigen::Vector3d>& points, int radius);
int open_sky_radius(const Camera& camera);
void open_sky_weights(const std::vector<uint8_t>& open, int width, int height, int factor, std::vector<float>& out);

// The far shell: where open pixels show surfaces without SfM points (a
// room's far walls and furniture), points for the anchors to start from.
// far_shell_radius: the sphere around `centre` (the cameras' mean centre)
// that holds 98% of the finite points, and at least `least` (beyond every
// camera, so each ray leaves it once). far_shell_points appends, for every
// `stride`-th pixel in x and y (from stride / 2) that is open, where its ray
// leaves that sphere, with the photo's colour there (`rgb` [H, W, 3] in
// [0, 1]).
double far_shell_radius(const std::vector<Eigen::Vector3d>& points, const Eigen::Vector3d& centre, double least);
void far_shell_points(const Camera& camera, const std::vector<uint8_t>& open, const std::vector<float>& rgb,
                      const Eigen::Vector3d& centre, double radius, int stride, std::vector<Eigen::Vector3d>& points,
                      std::vector<Eigen::Vector3<uint8_t>>& colors);

// The archive entry "sky/sh" [K, 3] (model.ag2gs, checkpoints): absent for
// a model without a sky. sky_from_archive throws std::runtime_error naming
// the archive's file when the entry has a shape no degree gives.
void sky_to_archive(ModelArchive& archive, const std::vector<float>& coefficients);
std::optional<std::vector<float>> sky_from_archive(const ModelArchive& archive);

class Sky {
 public:
  explicit Sky(Runtime& rt);

  // Uploads [K, 3] coefficients of a degree in 0..3 (std::invalid_argument
  // for another degree or a size that does not match it).
  void set(int degree, const std::vector<float>& coefficients);
  bool enabled() const { return degree_ >= 0; }
  // Back to no sky (the coefficients are dropped).
  void clear() {
    degree_ = -1;
    values_ = 0;
  }
  int degree() const { return degree_; }
  size_t values() const { return values_; }  // K * 3
  std::vector<float> download() const;

  // The coefficients for an optimiser to change: the sky colours kept from
  // the last compose() are no longer taken by backward() after this.
  DeviceBuffer& coefficients() {
    composed_ = {};
    return coef_;
  }
  // dL/d coefficients [K, 3] of the last backward().
  const DeviceBuffer& gradient() const { return grad_; }

  // out [3, H, W] = rgb + (1 - alpha) sky(d) for the camera's pixels, into
  // a buffer of the Sky's (valid until the next compose).
  const DeviceBuffer& compose(const DeviceBuffer& rgb, const DeviceBuffer& alpha, const Camera& camera);
  // From dL/d out [3, H, W] (which is also dL/d rgb): writes dL/d alpha
  // [H, W] into grad_alpha (added to what it holds when add is true) and
  // dL/d coefficients into gradient(). It takes sky(d) from the last
  // compose() when that was for this camera (and the coefficients did not
  // change since), else evaluates it.
  // With `weight` [H, W], pixel p counts W(p) times in the coefficient
  // gradient (the alpha gradient is the same); without it, once.
  void backward(const DeviceBuffer& grad_out, const DeviceBuffer& alpha, const Camera& camera, DeviceBuffer& grad_alpha,
                bool add, const DeviceBuffer* weight = nullptr);

  // The sky's start: the least-squares fit of a sky alone to photos (each
  // pixel as if nothing covered it, weighted by `weight` [H, W] when
  // given), so the Gaussians need not paint the sky while it is learned.
  // add_fit sums one photo [3, H, W] into the normal equations (gram
  // K x K, rhs K x 3; empty matrices start at zero). solve_fit returns the
  // coefficients [K, 3], with a ridge towards `start` [K, 3] of 1e-3 of
  // the Gram matrix's mean diagonal, and at least the degree-0 diagonal
  // entry that `min_ridge_pixels` pixels give (each adds Y_0^2), so
  // directions no open pixel saw stay near the start.
  // `squares` (when given) gains the weighted sum of I_c^2 per channel,
  // which fit_residual_rms needs.
  void add_fit(const DeviceBuffer& image, const Camera& camera, Eigen::MatrixXd& gram, Eigen::MatrixXd& rhs,
               const DeviceBuffer* weight = nullptr, Eigen::Vector3d* squares = nullptr);
  // The root-mean-square colour error of `coefficients` [K, 3] over the
  // fitted pixels (weighted), from the sums alone: E = sum W I^2 - 2 x.rhs
  // + x^T gram x per channel. A sky seen through many photos is one colour
  // per direction and fits them closely; surfaces at a finite distance do
  // not (each photo shows them in other directions), nor does a textured
  // wall. 0 when nothing was fitted.
  static double fit_residual_rms(const Eigen::MatrixXd& gram, const Eigen::MatrixXd& rhs,
                                 const Eigen::Vector3d& squares, const std::vector<float>& coefficients);
  static std::vector<float> solve_fit(const Eigen::MatrixXd& gram, const Eigen::MatrixXd& rhs,
                                      const std::vector<float>& start = {}, double min_ridge_pixels = 0);

 private:
  std::map<std::string, std::string> defines() const;  // SKY_K for the kernels

  Runtime& rt_;
  int degree_ = -1;
  size_t values_ = 0;
  DeviceBuffer coef_, grad_, partial_, out_;
  DeviceBuffer sky_;  // [3, H, W] sky(d) of the camera in composed_
  // The camera of sky_ (kernel arguments and size); width 0: none.
  struct Composed {
    int width = 0, height = 0;
    float args[16] = {};
  } composed_;
};

}  // namespace ag2gs
