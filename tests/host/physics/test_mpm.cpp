// The MLS-MPM solver (host/physics/mpm.h, kernels/mpm.cl) against a plain
// double-precision reference of the same method, and against physics: free
// fall, conservation of momentum, an elastic bounce that never gains energy,
// a stiff object that keeps its shape, a damped fall at its terminal speed,
// and bit-identical substeps whatever the thread count. Sand piles and
// slopes: tests/host/physics/test_mpm_sand.cpp.
#include <gtest/gtest.h>
#include <unistd.h>

#include <Eigen/Dense>
#include <cmath>
#include <cstdlib>
#include <fstream>
#include <limits>
#include <numeric>
#include <random>
#include <vector>

#include "host/physics/mpm.h"
#include "tests/reference/mpm_reference.h"
#include "tests/test_util.h"

namespace ag2gs {
namespace {

using namespace test;
using Eigen::Matrix3d;
using Eigen::Vector3d;

// ------------------------------------------------------------ scenes

// A cube of side `side` centred at `c`, particles every `spacing` (two per
// cell at spacing dx / 2), all of material `m`.
void add_cube(MpmParticles& p, const Vector3d& c, double side, double spacing, int32_t m, double density) {
  const int k = std::max(1, static_cast<int>(std::lround(side / spacing)));
  for (int i = 0; i < k; ++i)
    for (int j = 0; j < k; ++j)
      for (int l = 0; l < k; ++l) {
        const Vector3d x = c + (Vector3d(i, j, l) + Vector3d::Constant(0.5 - k / 2.0)) * spacing;
        p.add({static_cast<float>(x(0)), static_cast<float>(x(1)), static_cast<float>(x(2))},
              static_cast<float>(spacing * spacing * spacing), m, density);
      }
}

std::vector<MpmMaterial> one_material(MaterialKind kind, double E, double nu = 0.3) {
  MpmMaterial m;
  m.kind = kind;
  m.E = E;
  m.nu = nu;
  return {m};
}

MpmParticles run(const MpmConfig& cfg, const std::vector<MpmMaterial>& mats, const MpmParticles& start, double dt,
                 int steps) {
  MpmSolver solver(runtime(), cfg, mats);
  solver.upload(start);
  for (int s = 0; s < steps; ++s) solver.step(dt, true);
  MpmParticles out;
  solver.download(out);
  return out;
}

// ------------------------------------------------------------ tests

// Four materials side by side, each particle with a random deformation
// (large enough that metal, sand and plasticine yield), a random velocity
// and affine matrix; gravity, a force on material 0, walls, the ground and
// damping.
// `spacing_cells`: particle spacing in cells; `side`: each cube's side.
void check_against_reference(double side, double spacing_cells, const std::vector<int>& substeps) {
  MpmConfig cfg;
  cfg.grid = 24;
  cfg.ground = 0.2;
  cfg.friction = 0.4;
  cfg.damping = 5;  // the grid's drag, 1 / (1 + 5 dt) a substep
  std::vector<MpmMaterial> mats;
  for (MaterialKind k : {MaterialKind::kJelly, MaterialKind::kMetal, MaterialKind::kSand, MaterialKind::kPlasticine}) {
    MpmMaterial m;
    m.kind = k;
    m.E = 5e4;
    m.nu = 0.3;
    mats.push_back(m);
  }
  mats[0].force = {3, 0, 1};
  MpmParticles p;
  const double dx = 1.0 / cfg.grid;
  for (int m = 0; m < 4; ++m)
    add_cube(p, Vector3d(0.3 + 0.13 * m, 0.5, 0.2 + side / 2), side, dx * spacing_cells, m, 1000);
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> u(-1, 1);
  for (size_t i = 0; i < p.size(); ++i) {
    for (int k = 0; k < 3; ++k) p.v[3 * i + k] = static_cast<float>(0.2 * u(rng));
    for (int k = 0; k < 9; ++k) {
      p.F[9 * i + k] += static_cast<float>(0.06 * u(rng));
      p.C[9 * i + k] = static_cast<float>(0.5 * u(rng));
    }
  }
  const double dt = 2e-4;
  ASSERT_LT(dt, MpmSolver(runtime(), cfg, mats).max_stable_dt(1.0));
  for (int steps : substeps) {
    MpmParticles dev = run(cfg, mats, p, dt, steps);
    MpmParticles r = p;
    for (int s = 0; s < steps; ++s) ref::mpm_substep(r, cfg, mats, dt, true);
    std::printf("%zu particles after %d substep(s):\n", p.size(), steps);
    // Tolerances measured (float kernels with a float SVD by Jacobi
    // rotations, against Eigen's SVD in double), max abs after 10 substeps:
    // x 6e-8, v 3e-6, F 4e-6, C 1e-4 (C ranges over +-0.5), plastic 7e-6;
    // set at 2-50x of that.
    expect_close("x", compare(dev.x, r.x, 1e-6, 1e-6));
    expect_close("v", compare(dev.v, r.v, 5e-5, 1e-4));
    expect_close("F", compare(dev.F, r.F, 1e-5, 1e-5));
    expect_close("C", compare(dev.C, r.C, 5e-3, 1e-3));
    expect_close("plastic", compare(dev.plastic, r.plastic, 1e-5, 1e-4));
  }
  // Plasticity acted: every yielding material accumulated plastic strain.
  MpmParticles dev = run(cfg, mats, p, dt, 1);
  for (int m = 1; m < 4; ++m) {
    double sum = 0;
    for (size_t i = 0; i < dev.size(); ++i)
      if (dev.material[i] == m) sum += dev.plastic[i];
    EXPECT_GT(sum, 0) << material_name(mats[m].kind);
  }
}

TEST(Mpm, SubstepsMatchTheDoubleReferenceForEveryMaterial) {
  check_against_reference(0.1, 0.5, {1, 10});
}

// The same with 8 particles per material sharing cells (the Oclgrind suite
// runs this one).
TEST(Mpm, FewParticlesMatchTheDoubleReference) {
  check_against_reference(0.05, 0.6, {2});
}

TEST(Mpm, FreeFallFollowsTheParabola) {
  // A cube in uniform motion has F = I and C = 0, so the grid carries it
  // like a rigid body. Symplectic Euler (grid velocity first, then the
  // position) puts z_n = z0 + v0 t - g t^2 / 2 - g t dt / 2: the relative
  // error against the parabola's drop is dt / t, exactly, up to float.
  MpmConfig cfg;
  cfg.grid = 32;
  cfg.gravity = {0, 0, -9.8};
  MpmParticles p;
  add_cube(p, Vector3d(0.5, 0.5, 0.75), 0.1, 1.0 / 64, 0, 1000);
  const float v0[3] = {0.3f, -0.2f, 0.5f};
  for (size_t i = 0; i < p.size(); ++i)
    for (int k = 0; k < 3; ++k) p.v[3 * i + k] = v0[k];
  const auto c0 = centre_of_mass(p);
  const double dt = 1e-3;
  const int steps = 200;
  const MpmParticles out = run(cfg, one_material(MaterialKind::kJelly, 1e5), p, dt, steps);
  const auto c = centre_of_mass(out);
  const double t = dt * steps;
  const double drop = 9.8 * t * t / 2;
  EXPECT_NEAR(c[0], c0[0] + v0[0] * t, 1e-5);
  EXPECT_NEAR(c[1], c0[1] + v0[1] * t, 1e-5);
  const double err = (c0[2] + v0[2] * t - drop) - c[2];
  std::printf("free fall: z error %.3e, relative to the drop %.4f (dt / t = %.4f)\n", err, err / drop, dt / t);
  EXPECT_NEAR(err / drop, dt / t, 2e-4);
  EXPECT_LT(diagnose(out, 1.0 / cfg.grid).max_strain, 1e-4);
}

TEST(Mpm, MomentumIsConservedWithoutGravityOrWalls) {
  // A spinning, drifting jelly cube far from the walls, no gravity: the
  // transfers conserve linear momentum exactly (up to float) and APIC keeps
  // the angular momentum too; the elastic forces are internal.
  MpmConfig cfg;
  cfg.grid = 32;
  cfg.gravity = {0, 0, 0};
  MpmParticles p;
  const Vector3d c(0.5, 0.5, 0.5), omega(0, 2, 5), drift(0.2, 0.1, -0.1);
  add_cube(p, c, 0.16, 1.0 / 64, 0, 1000);
  for (size_t i = 0; i < p.size(); ++i) {
    const Vector3d x(p.x[3 * i], p.x[3 * i + 1], p.x[3 * i + 2]);
    const Vector3d v = drift + omega.cross(x - c);
    for (int k = 0; k < 3; ++k) p.v[3 * i + k] = static_cast<float>(v(k));
  }
  const MpmDiagnostics d0 = diagnose(p, 1.0 / cfg.grid);
  const MpmParticles out = run(cfg, one_material(MaterialKind::kJelly, 1e5), p, 1e-3, 150);
  const MpmDiagnostics d1 = diagnose(out, 1.0 / cfg.grid);
  ASSERT_TRUE(d1.finite);
  const double P = std::hypot(d0.momentum[0], d0.momentum[1], d0.momentum[2]);
  for (int k = 0; k < 3; ++k) {
    std::printf("momentum[%d] %.6e -> %.6e, angular %.6e -> %.6e\n", k, d0.momentum[k], d1.momentum[k], d0.angular[k],
                d1.angular[k]);
    EXPECT_NEAR(d1.momentum[k], d0.momentum[k], 1e-5 * P);
  }
  // Angular momentum about the origin, with APIC's particle spin: exact on
  // the grid for a symmetric stress; what drifts is float rounding.
  const double L0 = std::hypot(d0.angular[0], d0.angular[1], d0.angular[2]);
  const double dL =
      std::hypot(d1.angular[0] - d0.angular[0], d1.angular[1] - d0.angular[1], d1.angular[2] - d0.angular[2]);
  std::printf("angular momentum change %.3e of %.3e\n", dL, L0);
  EXPECT_LT(dL, 1e-4 * L0);
}

// Elastic energy of the fixed-corotated model, mu sum (s_i - 1)^2 + lambda / 2 (J - 1)^2, per rest volume.
double elastic_energy(const MpmParticles& p, const MpmMaterial& m) {
  double e = 0;
  for (size_t i = 0; i < p.size(); ++i) {
    Matrix3d F;
    for (int k = 0; k < 9; ++k) F(k / 3, k % 3) = p.F[9 * i + k];
    Eigen::JacobiSVD<Matrix3d> svd(F);
    Vector3d s = svd.singularValues();
    const double J = F.determinant();
    if (J < 0) s(2) = -s(2);
    e += p.volume[i] * (m.mu() * (s - Vector3d::Ones()).squaredNorm() + 0.5 * m.lambda() * (J - 1) * (J - 1));
  }
  return e;
}

TEST(Mpm, AnElasticCubeBouncesAndNeverGainsEnergy) {
  MpmConfig cfg;
  cfg.grid = 32;
  cfg.ground = 0.15;
  const auto mats = one_material(MaterialKind::kJelly, 2e5, 0.3);
  MpmParticles p;
  add_cube(p, Vector3d(0.5, 0.5, 0.35), 0.12, 1.0 / 64, 0, 1000);
  MpmSolver solver(runtime(), cfg, mats);
  solver.upload(p);
  const double dt = 2e-4;
  ASSERT_LT(dt, solver.max_stable_dt(3));
  auto total = [&](const MpmParticles& q) {
    double pot = 0;
    for (size_t i = 0; i < q.size(); ++i) pot += q.mass[i] * 9.8 * q.x[3 * i + 2];
    return diagnose(q, 1.0 / cfg.grid).kinetic + pot + elastic_energy(q, mats[0]);
  };
  const double e0 = total(p);
  double e_max = e0, vz_after = -1e9, vz_min = 0;
  bool touched = false;
  MpmParticles q;
  for (int s = 1; s <= 2500; ++s) {
    solver.step(dt, true);
    if (s % 25) continue;
    solver.download(q);
    ASSERT_TRUE(diagnose(q, 1.0 / cfg.grid).finite) << "substep " << s;
    e_max = std::max(e_max, total(q));
    const double vz = diagnose(q, 1.0 / cfg.grid).momentum[2];
    vz_min = std::min(vz_min, vz);
    if (vz_min < 0 && vz > 0) touched = true;
    if (touched) vz_after = std::max(vz_after, vz);
  }
  std::printf("energy: start %.5f J, max %.5f J, end %.5f J; momentum z min %.4f, max after contact %.4f\n", e0, e_max,
              total(q), vz_min, vz_after);
  EXPECT_LE(e_max, e0 * (1 + 1e-3));
  EXPECT_TRUE(touched) << "the cube never moved up after falling";
  EXPECT_GT(vz_after, 0.1 * -vz_min) << "no bounce";
}

TEST(Mpm, AStiffCubeKeepsItsShapeOnTheGround) {
  // E = 2e8 (the paper's selected object): resting on the ground, its
  // strain stays near rho g h / E (5e-6 here) and its centre stays put.
  MpmConfig cfg;
  cfg.grid = 24;
  cfg.ground = 0.2;
  const auto mats = one_material(MaterialKind::kJelly, 2e8, 0.4);
  MpmParticles p;
  const double dx = 1.0 / cfg.grid;
  add_cube(p, Vector3d(0.5, 0.5, 0.2 + 0.05 + dx / 4), 0.1, dx / 2, 0, 1000);
  MpmSolver solver(runtime(), cfg, mats);
  solver.upload(p);
  const double dt = solver.max_stable_dt(0.5);
  for (int s = 0; s < 1500; ++s) solver.step(dt, true);
  MpmParticles q;
  solver.download(q);
  const MpmDiagnostics d = diagnose(q, 1.0 / cfg.grid);
  const auto c0 = centre_of_mass(p), c1 = centre_of_mass(q);
  std::printf("stiff cube: dt %.3e, %.4f s, max |F - I| %.3e, centre moved %.3e\n", dt, 1500 * dt, d.max_strain,
              std::hypot(c1[0] - c0[0], c1[1] - c0[1], c1[2] - c0[2]));
  ASSERT_TRUE(d.finite);
  EXPECT_LT(d.max_strain, 1e-3);
  EXPECT_LT(std::hypot(c1[0] - c0[0], c1[1] - c0[1], c1[2] - c0[2]), 0.25 * dx);
}

TEST(Mpm, ADampedFallApproachesItsTerminalSpeed) {
  // The grid divides its velocities by 1 + c dt each substep, after
  // gravity: v_n+1 = (v_n - g dt) / (1 + c dt) for a cube in uniform motion,
  // whose fixed point is the terminal speed -g / c exactly, approached as
  // v_n = -g / c + (v0 + g / c) k^n with k = 1 / (1 + c dt); the position
  // is the sum of dt v_n. The continuous drag law gives e^(-c t) for k^n.
  MpmConfig cfg;
  cfg.grid = 32;
  cfg.damping = 20;
  cfg.gravity = {0, 0, -9.8};
  MpmParticles p;
  add_cube(p, Vector3d(0.5, 0.5, 0.75), 0.1, 1.0 / 64, 0, 1000);
  const double v0 = 0.5;
  for (size_t i = 0; i < p.size(); ++i) p.v[3 * i + 2] = static_cast<float>(v0);
  const double z0 = centre_of_mass(p)[2];
  const double dt = 1e-3;
  const int steps = 300;
  const MpmParticles out = run(cfg, one_material(MaterialKind::kJelly, 1e5), p, dt, steps);
  const double k = 1 / (1 + cfg.damping * dt), vt = -9.8 / cfg.damping;
  double z = z0, v = v0;
  for (int n = 0; n < steps; ++n) {
    v = vt + (v0 - vt) * std::pow(k, n + 1);
    z += dt * v;
  }
  const double t = dt * steps;
  const double z_ode = z0 + vt * t + (v0 - vt) * (1 - std::exp(-cfg.damping * t)) / cfg.damping;
  const double vz = diagnose(out, 1.0 / cfg.grid).momentum[2] / std::accumulate(out.mass.begin(), out.mass.end(), 0.0);
  std::printf("damped fall: v %.5f (recurrence %.5f, terminal %.5f), z %.6f (recurrence %.6f, drag law %.6f)\n", vz, v,
              vt, centre_of_mass(out)[2], z, z_ode);
  EXPECT_NEAR(vz, v, 1e-4);
  EXPECT_NEAR(centre_of_mass(out)[2], z, 1e-5);
  EXPECT_NEAR(v, vt, 0.01 * std::abs(vt));             // within 1% of terminal after c t = 6
  EXPECT_NEAR(z, z_ode, 0.02 * std::abs(z_ode - z0));  // the drag law, to O(c dt)
  EXPECT_LT(diagnose(out, 1.0 / cfg.grid).max_strain, 1e-4);
}

TEST(Mpm, AnObjectAtRestStaysAtRest) {
  // Without gravity or forces an undeformed body has no stress: every bit
  // stays. With gravity on the ground it settles, and stays settled.
  MpmConfig cfg;
  cfg.grid = 32;
  cfg.gravity = {0, 0, 0};
  std::vector<MpmMaterial> mats = one_material(MaterialKind::kJelly, 1e5);
  mats.push_back(mats[0]);
  mats[1].kind = MaterialKind::kMetal;
  MpmParticles p;
  add_cube(p, Vector3d(0.4, 0.5, 0.5), 0.1, 1.0 / 64, 0, 1000);
  add_cube(p, Vector3d(0.6, 0.5, 0.5), 0.1, 1.0 / 64, 1, 1000);
  const MpmParticles out = run(cfg, mats, p, 1e-3, 50);
  EXPECT_EQ(out.x, p.x);
  EXPECT_EQ(out.F, p.F);
  for (float v : out.v) EXPECT_EQ(v, 0.f);
  cfg.gravity = {0, 0, -9.8};
  cfg.ground = 0.2;
  MpmParticles rest;
  add_cube(rest, Vector3d(0.5, 0.5, 0.25 + 1.0 / 128), 0.1, 1.0 / 64, 0, 1000);
  MpmSolver solver(runtime(), cfg, mats);
  solver.upload(rest);
  const double dt = solver.max_stable_dt(1);
  for (int s = 0; s < static_cast<int>(0.3 / dt); ++s) solver.step(dt, true);
  MpmParticles a, b;
  solver.download(a);
  for (int s = 0; s < static_cast<int>(0.1 / dt); ++s) solver.step(dt, true);
  solver.download(b);
  double vmax = 0, moved = 0;
  for (size_t i = 0; i < b.size(); ++i)
    for (int k = 0; k < 3; ++k) {
      vmax = std::max(vmax, std::abs(static_cast<double>(b.v[3 * i + k])));
      moved = std::max(moved, std::abs(static_cast<double>(b.x[3 * i + k]) - a.x[3 * i + k]));
    }
  std::printf("settled cube: |v| max %.2e m/s, moved at most %.2e m in the last 0.1 s\n", vmax, moved);
  EXPECT_LT(vmax, 0.02);
  EXPECT_LT(moved, 0.05 / cfg.grid);
}

TEST(Mpm, RefusesBadSettingsAndParticlesOutsideTheBox) {
  MpmConfig cfg;
  cfg.grid = 4;
  EXPECT_THROW(MpmSolver(runtime(), cfg, one_material(MaterialKind::kJelly, 1e5)), std::invalid_argument);
  cfg.grid = 32;
  cfg.damping = -1;
  EXPECT_THROW(MpmSolver(runtime(), cfg, one_material(MaterialKind::kJelly, 1e5)), std::invalid_argument);
  cfg.damping = std::numeric_limits<double>::infinity();
  EXPECT_THROW(MpmSolver(runtime(), cfg, one_material(MaterialKind::kJelly, 1e5)), std::invalid_argument);
  cfg.damping = 0;
  EXPECT_THROW(MpmSolver(runtime(), cfg, one_material(MaterialKind::kJelly, -1)), std::invalid_argument);
  EXPECT_THROW(MpmSolver(runtime(), cfg, one_material(MaterialKind::kJelly, 1e5, 0.5)), std::invalid_argument);
  EXPECT_THROW(parse_material("rubber"), std::invalid_argument);
  MpmSolver solver(runtime(), cfg, one_material(MaterialKind::kJelly, 1e5));
  MpmParticles p;
  p.add({0.5f, 0.5f, 0.02f}, 1e-6f, 0, 1000);
  EXPECT_THROW(solver.upload(p), std::invalid_argument);
  MpmParticles q;
  q.add({0.5f, 0.5f, 0.5f}, 1e-6f, 3, 1000);
  EXPECT_THROW(solver.upload(q), std::invalid_argument);
  // The stable substep shrinks with stiffness as 1 / wave speed.
  MpmSolver stiff(runtime(), cfg, one_material(MaterialKind::kJelly, 1e7));
  EXPECT_NEAR(solver.max_stable_dt() / stiff.max_stable_dt(), 10.0, 1e-9);
}

// The hash of a short mixed-material run (child process below).
uint64_t run_hash() {
  MpmConfig cfg;
  cfg.grid = 24;
  cfg.ground = 0.2;
  std::vector<MpmMaterial> mats = one_material(MaterialKind::kJelly, 1e5);
  mats.push_back(mats[0]);
  mats[1].kind = MaterialKind::kSand;
  MpmParticles p;
  add_cube(p, Vector3d(0.4, 0.5, 0.4), 0.12, 1.0 / 48, 0, 1000);
  add_cube(p, Vector3d(0.6, 0.5, 0.3), 0.12, 1.0 / 48, 1, 1000);
  const MpmParticles out = run(cfg, mats, p, 2e-4, 60);
  return hash_vec(out.F, hash_vec(out.v, hash_vec(out.x)));
}

TEST(MpmWorker, WriteHash) {
  const char* out = std::getenv("AG2GS_HASH_OUT");
  if (!out) GTEST_SKIP() << "only run as a child of Mpm.SameBitsAcrossThreadCounts";
  std::ofstream(out) << run_hash() << "\n";
}

TEST(Mpm, SameBitsAcrossThreadCounts) {
  const auto hashes = lines_by_thread_count("MpmWorker.WriteHash");
  EXPECT_EQ(hashes[0], hashes[1]) << "1 thread vs 2 threads";
  EXPECT_EQ(hashes[0], std::to_string(run_hash())) << "child vs this process";
}

}  // namespace
}  // namespace ag2gs
