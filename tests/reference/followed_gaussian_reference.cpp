// Double-precision reference of the Gaussians that follow their particles.
#include "tests/reference/followed_gaussian_reference.h"

#include <Eigen/Dense>
#include <Eigen/Geometry>

#include "tests/reference/reference_renderer.h"

namespace ag2gs::ref {

using Eigen::Matrix3d;
using Eigen::Vector3d;

RefFollowedGaussian followed_gaussian_reference(const GaussianSet& set, int g, const SimulationFrame& fr,
                                                const Vector3d& x, const Matrix3d& F, const Vector3d& campos) {
  RefFollowedGaussian r;
  r.mean = fr.to_world(x);
  const Matrix3d Fw = fr.A.transpose() * F * fr.A;
  const Eigen::Quaterniond q0(set.quats[4 * g], set.quats[4 * g + 1], set.quats[4 * g + 2], set.quats[4 * g + 3]);
  const Vector3d s0(set.scales[3 * g], set.scales[3 * g + 1], set.scales[3 * g + 2]);
  const Matrix3d cov0 = q0.normalized().matrix() * s0.cwiseAbs2().asDiagonal() * q0.normalized().matrix().transpose();
  r.cov = Fw * cov0 * Fw.transpose();
  Eigen::JacobiSVD<Matrix3d> svd(Fw, Eigen::ComputeFullU | Eigen::ComputeFullV);
  const Matrix3d RF = svd.matrixU() * svd.matrixV().transpose();
  const Vector3d d = RF.transpose() * (r.mean - campos).normalized();
  double b[16];
  sh_values(set.sh_degree, d, b);
  const int K = set.sh_coeffs();
  for (int c = 0; c < 3; ++c) {
    double colour = 0;
    for (int k = 0; k < K; ++k) colour += b[k] * set.sh[(g * K + k) * 3 + c];
    r.colour[c] = colour;
  }
  return r;
}

}  // namespace ag2gs::ref
