// Double-precision reference of one MLS-MPM substep, scattering into a dense grid.
#include "tests/reference/mpm_reference.h"

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>

namespace ag2gs::ref {

namespace {

using Eigen::Matrix3d;
using Eigen::Vector3d;

// Kirchhoff stress after the return mapping, in double, from the definitions
// (host/physics/mpm.h lists the materials).
Matrix3d stress(const MpmMaterial& mat, Matrix3d& F, double& plastic) {
  const double mu = mat.mu(), la = mat.lambda();
  Eigen::JacobiSVD<Matrix3d> svd(F, Eigen::ComputeFullU | Eigen::ComputeFullV);
  Matrix3d U = svd.matrixU(), V = svd.matrixV();
  Vector3d sig = svd.singularValues();
  if (U.determinant() < 0) {
    U.col(2) *= -1;
    sig(2) *= -1;
  }
  if (V.determinant() < 0) {
    V.col(2) *= -1;
    sig(2) *= -1;
  }
  if (mat.kind == MaterialKind::kJelly) {
    const double J = F.determinant();
    const Matrix3d R = U * V.transpose();
    return 2 * mu * (F - R) * F.transpose() + la * (J - 1) * J * Matrix3d::Identity();
  }
  Vector3d eps = sig.cwiseMax(1e-4).array().log();
  const double tr = eps.sum();
  const Vector3d dev = eps - Vector3d::Constant(tr / 3);
  const double ndev = dev.norm();
  const double yield0 = mat.yield_stress > 0 ? mat.yield_stress : mat.E / 100;
  if (mat.kind == MaterialKind::kMetal || mat.kind == MaterialKind::kPlasticine) {
    const double yield = mat.kind == MaterialKind::kPlasticine ? yield0 / (1 + mat.softening * plastic) : yield0;
    const double dg = ndev - yield / (2 * mu);
    if (dg > 0) {
      eps -= dg / ndev * dev;
      plastic += dg;
    }
  } else {
    const double s = std::sin(mat.friction_deg * M_PI / 180);
    const double alpha = std::sqrt(2.0 / 3.0) * 2 * s / (3 - s);
    if (tr >= 0 || ndev <= 0) {
      plastic += eps.norm();
      eps.setZero();
    } else {
      const double dg = ndev + (3 * la + 2 * mu) / (2 * mu) * tr * alpha;
      if (dg > 0) {
        eps -= dg / ndev * dev;
        plastic += dg;
      }
    }
  }
  F = U * eps.array().exp().matrix().asDiagonal() * V.transpose();
  const Vector3d t = 2 * mu * eps + Vector3d::Constant(la * eps.sum());
  return U * t.asDiagonal() * U.transpose();
}

}  // namespace

void mpm_substep(MpmParticles& p, const MpmConfig& cfg, const std::vector<MpmMaterial>& mats, double dt, bool forces) {
  const int g = cfg.grid;
  const double dx = 1.0 / g, inv_dx = g;
  const size_t n = p.size();
  std::vector<Vector3d> mom(static_cast<size_t>(g) * g * g, Vector3d::Zero());
  std::vector<double> mass(mom.size(), 0);
  auto node_id = [g](int i, int j, int k) { return (static_cast<size_t>(i) * g + j) * g + k; };
  auto base_of = [&](const Vector3d& x) {
    Eigen::Vector3i b;
    for (int k = 0; k < 3; ++k)
      b(k) = std::clamp(static_cast<int>(std::floor(static_cast<float>(x(k)) * static_cast<float>(inv_dx) - 0.5f)), 0,
                        g - 3);
    return b;
  };
  auto weights = [](double fx) {
    return Vector3d(0.5 * (1.5 - fx) * (1.5 - fx), 0.75 - (fx - 1) * (fx - 1), 0.5 * (fx - 0.5) * (fx - 0.5));
  };
  for (size_t i = 0; i < n; ++i) {
    const MpmMaterial& mat = mats[p.material[i]];
    Matrix3d F;
    for (int k = 0; k < 9; ++k) F(k / 3, k % 3) = p.F[9 * i + k];
    double pl = p.plastic[i];
    const Matrix3d tau = stress(mat, F, pl);
    for (int k = 0; k < 9; ++k) p.F[9 * i + k] = static_cast<float>(F(k / 3, k % 3));
    p.plastic[i] = static_cast<float>(pl);
    Matrix3d C;
    for (int k = 0; k < 9; ++k) C(k / 3, k % 3) = p.C[9 * i + k];
    const double m = p.mass[i];
    const Matrix3d Q = -dt * p.volume[i] * 4 * inv_dx * inv_dx * tau + m * C;
    const Vector3d x(p.x[3 * i], p.x[3 * i + 1], p.x[3 * i + 2]);
    Vector3d mv = m * Vector3d(p.v[3 * i], p.v[3 * i + 1], p.v[3 * i + 2]);
    if (forces) mv += m * dt * Vector3d(mat.force[0], mat.force[1], mat.force[2]);
    const Eigen::Vector3i b = base_of(x);
    const Vector3d fx = x * inv_dx - b.cast<double>();
    const Vector3d w[3] = {weights(fx(0)), weights(fx(1)), weights(fx(2))};
    for (int a = 0; a < 3; ++a)
      for (int bb = 0; bb < 3; ++bb)
        for (int c = 0; c < 3; ++c) {
          const double wt = w[0](a) * w[1](bb) * w[2](c);
          const Vector3d dpos = (Vector3d(a, bb, c) - fx) * dx;
          const size_t id = node_id(b(0) + a, b(1) + bb, b(2) + c);
          mom[id] += wt * (mv + Q * dpos);
          mass[id] += wt * m;
        }
  }
  std::vector<Vector3d> vel(mom.size(), Vector3d::Zero());
  for (int i = 0; i < g; ++i)
    for (int j = 0; j < g; ++j)
      for (int k = 0; k < g; ++k) {
        const size_t id = node_id(i, j, k);
        if (mass[id] <= 0) continue;
        Vector3d v = (mom[id] / mass[id] + dt * Vector3d(cfg.gravity[0], cfg.gravity[1], cfg.gravity[2])) /
                     (1 + cfg.damping * dt);
        const int nd[3] = {i, j, k};
        for (int a = 0; a < 3; ++a) {
          if (nd[a] < 3 && v(a) < 0) v(a) = 0;
          if (nd[a] > g - 3 && v(a) > 0) v(a) = 0;
        }
        if (cfg.ground >= 0 && k * dx <= cfg.ground + 1.5 * dx && v(2) < 0) {
          const double vt = std::hypot(v(0), v(1));
          const double keep = vt > 0 ? std::max(1 + cfg.friction * v(2) / vt, 0.0) : 0.0;
          v(0) *= keep;
          v(1) *= keep;
          v(2) = 0;
        }
        vel[id] = v;
      }
  for (size_t i = 0; i < n; ++i) {
    const Vector3d x(p.x[3 * i], p.x[3 * i + 1], p.x[3 * i + 2]);
    const Eigen::Vector3i b = base_of(x);
    const Vector3d fx = x * inv_dx - b.cast<double>();
    const Vector3d w[3] = {weights(fx(0)), weights(fx(1)), weights(fx(2))};
    Vector3d v = Vector3d::Zero();
    Matrix3d B = Matrix3d::Zero();
    for (int a = 0; a < 3; ++a)
      for (int bb = 0; bb < 3; ++bb)
        for (int c = 0; c < 3; ++c) {
          const double wt = w[0](a) * w[1](bb) * w[2](c);
          const Vector3d dpos = (Vector3d(a, bb, c) - fx) * dx;
          const Vector3d gv = vel[node_id(b(0) + a, b(1) + bb, b(2) + c)];
          v += wt * gv;
          B += wt * gv * dpos.transpose();
        }
    const Matrix3d C = 4 * inv_dx * inv_dx * B;
    Matrix3d F;
    for (int k = 0; k < 9; ++k) F(k / 3, k % 3) = p.F[9 * i + k];
    F = (Matrix3d::Identity() + dt * C) * F;
    for (int k = 0; k < 3; ++k) {
      p.v[3 * i + k] = static_cast<float>(v(k));
      p.x[3 * i + k] = static_cast<float>(x(k) + dt * v(k));
    }
    for (int k = 0; k < 9; ++k) {
      p.C[9 * i + k] = static_cast<float>(C(k / 3, k % 3));
      p.F[9 * i + k] = static_cast<float>(F(k / 3, k % 3));
    }
  }
}

}  // namespace ag2gs::ref
