// Size checks for the core data types (host/core/gaussians.h).
#include "host/core/gaussians.h"

#include <Eigen/LU>
#include <algorithm>
#include <cmath>
#include <sstream>
#include <stdexcept>
#include <string>

namespace ag2gs {

void GaussianSet::resize(size_t n) {
  const size_t k = static_cast<size_t>(sh_coeffs());
  means.resize(n * 3, 0.f);
  scales.resize(n * 3, 0.f);
  quats.resize(n * 4, 0.f);
  opacities.resize(n, 0.f);
  sh.resize(n * k * 3, 0.f);
  features.resize(n * 3, 0.f);
}

GaussianSet GaussianSet::rows(const std::vector<size_t>& ids) const {
  GaussianSet out;
  out.sh_degree = sh_degree;
  out.resize(ids.size());
  const size_t sc = static_cast<size_t>(sh_coeffs()) * 3;
  for (size_t r = 0; r < ids.size(); ++r) {
    const size_t g = ids[r];
    std::copy_n(&means[3 * g], 3, &out.means[3 * r]);
    std::copy_n(&scales[3 * g], 3, &out.scales[3 * r]);
    std::copy_n(&quats[4 * g], 4, &out.quats[4 * r]);
    out.opacities[r] = opacities[g];
    std::copy_n(&sh[sc * g], sc, &out.sh[sc * r]);
    std::copy_n(&features[3 * g], 3, &out.features[3 * r]);
  }
  return out;
}

namespace {

void check_array(const char* name, size_t actual, size_t n, size_t per, const char* shape) {
  if (actual == n * per) return;
  std::ostringstream msg;
  msg << "GaussianSet: '" << name << "' holds " << actual << " floats but expected " << n * per << " (shape " << shape
      << " with N = " << n << " from 'opacities')";
  throw std::invalid_argument(msg.str());
}

}  // namespace

void GaussianSet::validate() const {
  if (sh_degree < 0 || sh_degree > 3) {
    throw std::invalid_argument("GaussianSet: sh_degree is " + std::to_string(sh_degree) + "; it must be 0, 1, 2 or 3");
  }
  const size_t n = size();
  const size_t k = static_cast<size_t>(sh_coeffs());
  check_array("means", means.size(), n, 3, "[N,3]");
  check_array("scales", scales.size(), n, 3, "[N,3]");
  check_array("quats", quats.size(), n, 4, "[N,4]");
  const std::string sh_shape = "[N," + std::to_string(k) + ",3] for sh_degree " + std::to_string(sh_degree);
  check_array("sh", sh.size(), n, k * 3, sh_shape.c_str());
  check_array("features", features.size(), n, 3, "[N,3]");
}

void Camera::validate() const {
  const std::string who = "Camera" + (name.empty() ? std::string() : " '" + name + "'");
  auto fail = [&](const std::string& what) { throw std::invalid_argument(who + ": " + what); };
  if (width <= 0 || height <= 0) {
    fail("image size is " + std::to_string(width) + "x" + std::to_string(height) +
         "; width and height must be positive");
  }
  if (!(std::isfinite(fx) && fx > 0) || !(std::isfinite(fy) && fy > 0)) {
    std::ostringstream msg;
    msg << "focal lengths fx = " << fx << ", fy = " << fy << " must be finite and positive";
    fail(msg.str());
  }
  if (!std::isfinite(cx) || !std::isfinite(cy)) {
    std::ostringstream msg;
    msg << "principal point (" << cx << ", " << cy << ") must be finite";
    fail(msg.str());
  }
  // Finite but absurd numbers (a corrupt file: fx 1e300, t 1e300) would
  // overflow later, far from their cause. The bounds admit any real lens
  // (a focal length of 1e-4 to 1e6 image sizes) and geo-referenced poses.
  const double size = std::max(width, height);
  if (!(fx >= 1e-4 * size && fx <= 1e6 * size) || !(fy >= 1e-4 * size && fy <= 1e6 * size)) {
    std::ostringstream msg;
    msg << "focal lengths fx = " << fx << ", fy = " << fy << " are not those of a camera with a " << width << "x"
        << height << " image (expected 1e-4 to 1e6 times its size)";
    fail(msg.str());
  }
  if (!(std::abs(cx) <= 1e6 * size) || !(std::abs(cy) <= 1e6 * size)) {
    std::ostringstream msg;
    msg << "principal point (" << cx << ", " << cy << ") lies implausibly far outside the " << width << "x" << height
        << " image";
    fail(msg.str());
  }
  if (!R.allFinite() || !t.allFinite()) fail("pose (R, t) contains a non-finite value");
  if (!(t.cwiseAbs().maxCoeff() <= 1e9)) {
    std::ostringstream msg;
    msg << "translation (" << t.transpose() << ") is implausibly large (beyond 1e9 scene units)";
    fail(msg.str());
  }
  // A rotation: orthonormal with determinant +1. The tolerance admits doubles
  // built from a normalised quaternion, not a scaled or reflected matrix.
  const double ortho_err = (R.transpose() * R - Eigen::Matrix3d::Identity()).cwiseAbs().maxCoeff();
  if (ortho_err > 1e-6) {
    std::ostringstream msg;
    msg << "R is not a rotation: max |R^T R - I| = " << ortho_err << " (> 1e-6); build it from a normalised quaternion";
    fail(msg.str());
  }
  const double det = R.determinant();
  if (std::abs(det - 1.0) > 1e-6) {
    std::ostringstream msg;
    msg << "R is not a rotation: det(R) = " << det << " (a reflection when -1); expected +1";
    fail(msg.str());
  }
}

}  // namespace ag2gs
