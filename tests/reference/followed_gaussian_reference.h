// Double-precision reference of the Gaussians that follow their particles
// (apps/simulation/simulation.h, kernels/mpm.cl mpm_gaussians), written from
// their definition with Eigen in double:
//   mean   = the particle's position taken back to the world (frame.to_world)
//   cov    = Fw R0 S0^2 R0^T Fw^T,  Fw = A^T F A (F in the world frame)
//   colour = sum_k Y_k(d) sh_k,  d = RF^T (mean - campos) / |...|, RF the
//            rotation of Fw's polar decomposition (U V^T of its SVD)
// The colour is the SH sum alone: the kernel bakes it into the DC
// coefficient, colour / C0, with the other coefficients zero.
#pragma once

#include <Eigen/Core>

#include "apps/simulation/simulation.h"
#include "host/core/gaussians.h"

namespace ag2gs::ref {

struct RefFollowedGaussian {
  Eigen::Vector3d mean;
  Eigen::Matrix3d cov;
  Eigen::Vector3d colour;
};

// Gaussian g of `set` (its trained scales, rotation and SH, degree
// set.sh_degree) following a particle at x (box coordinates) with
// deformation gradient F (box frame), seen from campos (world).
RefFollowedGaussian followed_gaussian_reference(const GaussianSet& set, int g, const SimulationFrame& fr,
                                                const Eigen::Vector3d& x, const Eigen::Matrix3d& F,
                                                const Eigen::Vector3d& campos);

}  // namespace ag2gs::ref
