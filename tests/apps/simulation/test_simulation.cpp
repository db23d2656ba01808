// The simulation stage (apps/simulation/simulation.h): interior filling, the ground
// under an object, the up direction, and the Gaussians that follow their
// particles (kernels/mpm.cl, mpm_gaussians) against a double-precision
// reference of F Sigma F^T and of the SH colour at the turned view direction
// (tests/reference/followed_gaussian_reference.h).
#include <gtest/gtest.h>

#include <Eigen/Dense>
#include <cmath>
#include <random>
#include <vector>

#include "apps/simulation/simulation.h"
#include "tests/reference/followed_gaussian_reference.h"
#include "tests/test_util.h"

namespace ag2gs {
namespace {

using Eigen::Matrix3d;
using Eigen::Vector3d;

TEST(Simulation, FillSolidFillsAClosedShellAndNotAnOpenCup) {
  // A sphere shell of radius 0.2, sampled sparsely (Gaussians about 1.5
  // cells apart), on a grid of 1/32.
  const double cell = 1.0 / 32;
  std::vector<Vector3d> shell, cup;
  for (int i = 0; i < 60; ++i)
    for (int j = 0; j < 30; ++j) {
      const double th = M_PI * (j + 0.5) / 30, ph = 2 * M_PI * i / 60;
      const Vector3d p = Vector3d(0.5, 0.5, 0.5) +
                         0.2 * Vector3d(std::sin(th) * std::cos(ph), std::sin(th) * std::sin(ph), std::cos(th));
      shell.push_back(p);
      if (p(2) < 0.55) cup.push_back(p);  // the top cut off: open upwards
    }
  const std::vector<Vector3d> solid = fill_solid(shell, cell);
  // Every cell lies within a cell of the sphere, and together they make
  // its volume grown by the half cell of the occupied cells around it:
  // (1 + (cell / 2) / 0.2)^3 = 1.25.
  for (const Vector3d& c : solid) EXPECT_LT((c - Vector3d(0.5, 0.5, 0.5)).norm(), 0.2 + cell);
  const double volume = solid.size() * cell * cell * cell, sphere = 4.0 / 3 * M_PI * 0.2 * 0.2 * 0.2;
  std::printf("solid of %zu cells, %.3f of the sphere's volume\n", solid.size(), volume / sphere);
  EXPECT_NEAR(volume / sphere, 1.25, 0.1);
  // The open cup: its wall only (within two cells of the sphere), nothing
  // above the cut, no inside.
  const std::vector<Vector3d> walls = fill_solid(cup, cell);
  for (const Vector3d& c : walls) {
    EXPECT_LT(c(2), 0.55 + 2 * cell);
    EXPECT_GT((c - Vector3d(0.5, 0.5, 0.5)).norm(), 0.2 - 2.5 * cell);
  }
  EXPECT_LT(walls.size() * cell * cell * cell, 0.5 * sphere);
  EXPECT_TRUE(fill_solid({}, cell).empty());
}

TEST(Simulation, GroundIsTheSurfaceUnderTheObject) {
  // A table top at height 1 (with a floor at 0 further out), an object above.
  std::mt19937 rng(3);
  std::uniform_real_distribution<double> u(-1, 1);
  std::vector<Vector3d> points, object;
  for (int i = 0; i < 400; ++i) points.emplace_back(u(rng), u(rng), 1.0 + 0.002 * u(rng));
  for (int i = 0; i < 400; ++i) points.emplace_back(3 * u(rng), 3 * u(rng), 0.0);
  for (int i = 0; i < 300; ++i) object.emplace_back(0.1 * u(rng), 0.1 * u(rng), 1.05 + 0.05 * (u(rng) + 1));
  EXPECT_NEAR(ground_below(points, object, Vector3d::UnitZ()), 1.0, 0.003);
  // Without points under it: the object's own lowest Gaussian.
  EXPECT_NEAR(ground_below({}, object, Vector3d::UnitZ()), 1.05, 0.01);
  // Up from cameras: COLMAP cameras looking at the origin from around it, all upright.
  std::vector<Camera> cams;
  for (int i = 0; i < 6; ++i) {
    const double a = 2 * M_PI * i / 6;
    cams.push_back(test::look_at(Vector3d(3 * std::cos(a), 3 * std::sin(a), 1.0), Vector3d::Zero(), 32, 32, 30));
  }
  const Vector3d up = up_from_cameras(cams);
  EXPECT_GT(up.dot(Vector3d::UnitZ()), 0.9) << up.transpose();
}

TEST(Simulation, GaussiansFollowTheirParticles) {
  // Five Gaussians with SH of degree 3; each particle gets its own F (a
  // rotation times a stretch) and a shift; the kernel's means, covariances
  // and baked colours against the definitions in double.
  GaussianSet set;
  set.sh_degree = 3;
  const int K = 16;
  std::mt19937 rng(11);
  std::uniform_real_distribution<double> u(-1, 1);
  const int n = 5;
  set.resize(n);
  for (int g = 0; g < n; ++g) {
    for (int c = 0; c < 3; ++c) {
      set.means[3 * g + c] = static_cast<float>(0.3 * u(rng));
      set.scales[3 * g + c] = static_cast<float>(0.02 + 0.01 * u(rng));
    }
    const Eigen::Quaterniond q = Eigen::Quaterniond(1 + u(rng), u(rng), u(rng), u(rng)).normalized();
    set.quats[4 * g] = static_cast<float>(q.w());
    set.quats[4 * g + 1] = static_cast<float>(q.x());
    set.quats[4 * g + 2] = static_cast<float>(q.y());
    set.quats[4 * g + 3] = static_cast<float>(q.z());
    set.opacities[g] = 0.8f;
    for (int k = 0; k < 3 * K; ++k) set.sh[3 * K * g + k] = static_cast<float>(0.3 * u(rng));
  }
  SimulationSettings ss;
  ss.with_background = false;
  ss.grid = 32;
  ss.up = Vector3d(0.2, 0.1, 1.0);
  ss.ground = -1.0;
  ss.object.E = 1e5;
  Simulation sim(test::runtime(), set, std::vector<uint8_t>(n, 1), {}, {}, ss);
  // The Gaussians' particles come first, then those that fill their cells.
  ASSERT_EQ(sim.object_gaussians(), static_cast<size_t>(n));
  MpmParticles p;
  sim.solver().download(p);
  std::vector<Matrix3d> Fs;
  for (int i = 0; i < n; ++i) {
    const Matrix3d R = Eigen::AngleAxisd(0.7 * u(rng), Vector3d(u(rng), u(rng), u(rng)).normalized()).matrix();
    Matrix3d S = Matrix3d::Identity() + 0.2 * Matrix3d::Random();
    S = 0.5 * (S + S.transpose()).eval() + 0.5 * Matrix3d::Identity();  // symmetric positive definite
    const Matrix3d F = R * S;
    Fs.push_back(F);
    for (int k = 0; k < 9; ++k) p.F[9 * i + k] = static_cast<float>(F(k / 3, k % 3));
    for (int k = 0; k < 3; ++k) p.x[3 * i + k] += static_cast<float>(0.01 * u(rng));
  }
  sim.solver().upload(p);
  const Vector3d campos(2.0, -1.0, 0.5);
  const GaussianSet out = sim.gaussians(campos);
  const SimulationFrame& fr = sim.frame();
  for (int g = 0; g < n; ++g) {
    const Vector3d x(p.x[3 * g], p.x[3 * g + 1], p.x[3 * g + 2]);
    const ref::RefFollowedGaussian want = ref::followed_gaussian_reference(set, g, fr, x, Fs[g], campos);
    // Mean: the particle taken back to the world.
    for (int c = 0; c < 3; ++c) EXPECT_NEAR(out.means[3 * g + c], want.mean(c), 1e-5) << g;
    // Covariance: Fw R0 S0^2 R0^T Fw^T with Fw = A^T F A.
    const Eigen::Quaterniond q(out.quats[4 * g], out.quats[4 * g + 1], out.quats[4 * g + 2], out.quats[4 * g + 3]);
    const Vector3d s(out.scales[3 * g], out.scales[3 * g + 1], out.scales[3 * g + 2]);
    const Matrix3d got = q.normalized().matrix() * s.cwiseAbs2().asDiagonal() * q.normalized().matrix().transpose();
    EXPECT_LT((got - want.cov).norm(), 1e-4 * want.cov.norm()) << g << "\n" << got << "\nwant\n" << want.cov;
    // Colour: the trained SH at the view direction turned back by F's rotation.
    for (int c = 0; c < 3; ++c) {
      EXPECT_NEAR(out.sh[(g * K) * 3 + c] * 0.28209479177387814, want.colour(c), 2e-5) << g << " channel " << c;
      for (int k = 1; k < K; ++k) EXPECT_EQ(out.sh[(g * K + k) * 3 + c], 0.f);
    }
  }
  // Without baking, the trained SH stay.
  const GaussianSet raw = sim.gaussians(campos, false);
  EXPECT_EQ(raw.sh, set.sh);
}

}  // namespace
}  // namespace ag2gs
