#include "host/render/sky_bake.h"

#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <string>

#include "host/render/sky.h"

namespace ag2gs {

SkyShell sky_shell(const GaussianSet& objects, const std::vector<Camera>& cameras, const SkyBakeConfig& config) {
  SkyShell shell;
  if (!cameras.empty()) {
    Eigen::Vector3d sum = Eigen::Vector3d::Zero();
    for (const Camera& c : cameras) sum += c.center();
    shell.centre = sum / static_cast<double>(cameras.size());
  }
  double far = 0.0;
  for (const Camera& c : cameras) far = std::max(far, (c.center() - shell.centre).norm());
  for (size_t i = 0; i < objects.size(); ++i) {
    const Eigen::Vector3d m(objects.means[3 * i], objects.means[3 * i + 1], objects.means[3 * i + 2]);
    const double d = (m - shell.centre).norm();
    if (std::isfinite(d)) far = std::max(far, d);
  }
  shell.radius = config.radius_factor * std::max(far, 1.0 / config.radius_factor);
  return shell;
}

int sky_bake_count(int degree) {
  // Lattice spacings of about 8.3, 5.2, 4.5 and 3.7 degrees. On a generated
  // open-sky scene (degree 3) the .ply renders 46.1 dB from the model's
  // render with 2,000, 47.6 dB with 3,000 and 48.8 dB with 10,000; on
  // tests/host/render/test_sky_bake.cpp's random skies the worst view is at 40-57 dB.
  static constexpr int kCount[] = {600, 1500, 2000, 3000};
  if (degree < 0 || degree > kSkyMaxDegree) throw std::invalid_argument("sky degree " + std::to_string(degree));
  return kCount[degree];
}

GaussianSet bake_sky(const std::vector<float>& coefficients, const SkyShell& shell, int sh_degree_out,
                     const SkyBakeConfig& config) {
  const int degree = sky_degree_for(coefficients.size());
  if (degree < 0)
    throw std::invalid_argument("bake_sky: " + std::to_string(coefficients.size()) +
                                " coefficients are no sky of SH degree 0..3");
  if (sh_degree_out < degree || sh_degree_out > kSkyMaxDegree)
    throw std::invalid_argument("bake_sky: output SH degree " + std::to_string(sh_degree_out) + " is below the sky's " +
                                std::to_string(degree) + " or above 3");
  const int n = config.count > 0 ? config.count : sky_bake_count(degree);
  const double kPi = 3.14159265358979323846;
  const double golden = kPi * (3.0 - std::sqrt(5.0));  // the golden angle
  const double spacing = std::sqrt(4.0 * kPi / n);     // radians between neighbours, on average
  const float sigma = static_cast<float>(config.sigma_spacing * spacing * shell.radius);
  const int k_sky = sh_coeffs_for_degree(degree);

  GaussianSet gs;
  gs.sh_degree = sh_degree_out;
  gs.resize(static_cast<size_t>(n));
  const int k_out = gs.sh_coeffs();
  for (int i = 0; i < n; ++i) {
    const double z = 1.0 - (2.0 * i + 1.0) / n;
    const double r = std::sqrt(std::max(0.0, 1.0 - z * z));
    const double phi = golden * i;
    const Eigen::Vector3d p = shell.centre + shell.radius * Eigen::Vector3d(r * std::cos(phi), r * std::sin(phi), z);
    for (int a = 0; a < 3; ++a) {
      gs.means[3 * i + a] = static_cast<float>(p[a]);
      gs.scales[3 * i + a] = sigma;
    }
    gs.quats[4 * i] = 1.f;
    gs.opacities[i] = static_cast<float>(config.opacity);
    float* sh = &gs.sh[static_cast<size_t>(i) * k_out * 3];
    for (int k = 0; k < k_sky; ++k)
      for (int c = 0; c < 3; ++c) sh[k * 3 + c] = coefficients[k * 3 + c];
    // The renderer adds 0.5 to the SH sum; the sky has no offset.
    for (int c = 0; c < 3; ++c) sh[c] = static_cast<float>(coefficients[c] - 0.5 / kShC0);
  }
  return gs;
}

GaussianSet concat_gaussians(const GaussianSet& a, const GaussianSet& b) {
  GaussianSet out;
  out.sh_degree = std::max(a.sh_degree, b.sh_degree);
  out.resize(a.size() + b.size());
  const int k_out = out.sh_coeffs();
  size_t row = 0;
  for (const GaussianSet* s : {&a, &b}) {
    const int k_in = s->sh_coeffs();
    for (size_t i = 0; i < s->size(); ++i, ++row) {
      std::copy_n(&s->means[3 * i], 3, &out.means[3 * row]);
      std::copy_n(&s->scales[3 * i], 3, &out.scales[3 * row]);
      std::copy_n(&s->quats[4 * i], 4, &out.quats[4 * row]);
      std::copy_n(&s->features[3 * i], 3, &out.features[3 * row]);
      out.opacities[row] = s->opacities[i];
      std::copy_n(&s->sh[i * k_in * 3], k_in * 3, &out.sh[row * k_out * 3]);
    }
  }
  return out;
}

}  // namespace ag2gs
