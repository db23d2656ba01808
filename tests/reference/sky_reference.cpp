// Double-precision reference of the sky: compositing, its backward and loss.
#include "tests/reference/sky_reference.h"

#include <Eigen/Dense>

#include "tests/reference/reference_renderer.h"

namespace ag2gs::ref {

using Eigen::Vector3d;

Vector3d pixel_ray(const Camera& c, int x, int y) {
  const Vector3d dc((x + 0.5 - c.cx) / c.fx, (y + 0.5 - c.cy) / c.fy, 1.0);
  return (c.R.transpose() * dc).normalized();
}

Vector3d sky_radiance(int degree, const std::vector<float>& coef, const Vector3d& d) {
  double b[16];
  sh_values(degree, d, b);
  Vector3d s = Vector3d::Zero();
  for (int k = 0; k < (degree + 1) * (degree + 1); ++k)
    for (int c = 0; c < 3; ++c) s[c] += b[k] * coef[3 * k + c];
  return s;
}

RefSkyGrad sky_backward_reference(int degree, const std::vector<float>& coef, const std::vector<float>& grad,
                                  const std::vector<float>& alpha, const Camera& cam, const std::vector<float>* add_to,
                                  const std::vector<float>& weight) {
  const int w = cam.width, h = cam.height;
  const size_t n = static_cast<size_t>(w) * h;
  const int K = (degree + 1) * (degree + 1);
  RefSkyGrad g;
  g.alpha.assign(n, 0.0);
  g.coef.assign(3 * K, 0.0);
  for (int y = 0; y < h; ++y)
    for (int x = 0; x < w; ++x) {
      const size_t i = static_cast<size_t>(y) * w + x;
      const Vector3d d = pixel_ray(cam, x, y);
      double b[16];
      sh_values(degree, d, b);
      const Vector3d s = sky_radiance(degree, coef, d);
      double ga = add_to ? (*add_to)[i] : 0.0;
      const double wp = weight.empty() ? 1.0 : weight[i];
      for (int c = 0; c < 3; ++c) {
        ga -= grad[c * n + i] * s[c];
        for (int k = 0; k < K; ++k) g.coef[3 * k + c] += wp * (1.0 - alpha[i]) * b[k] * grad[c * n + i];
      }
      g.alpha[i] = ga;
    }
  return g;
}

double sky_loss_reference(int degree, const std::vector<double>& coef, const std::vector<double>& alpha,
                          const std::vector<float>& rgb, const std::vector<float>& grad, const Camera& cam) {
  const size_t n = static_cast<size_t>(cam.width) * cam.height;
  double loss = 0;
  for (int y = 0; y < cam.height; ++y)
    for (int x = 0; x < cam.width; ++x) {
      const size_t i = static_cast<size_t>(y) * cam.width + x;
      double b[16];
      sh_values(degree, pixel_ray(cam, x, y), b);
      for (int c = 0; c < 3; ++c) {
        double s = 0;
        for (int k = 0; k < (degree + 1) * (degree + 1); ++k) s += b[k] * coef[3 * k + c];
        loss += grad[c * n + i] * (rgb[c * n + i] + (1.0 - alpha[i]) * s);
      }
    }
  return loss;
}

}  // namespace ag2gs::ref
