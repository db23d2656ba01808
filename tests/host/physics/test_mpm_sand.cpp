// Sand (Drucker-Prager, host/physics/mpm.h) against what a cohesionless
// material must do: a pile released slowly rests at its friction angle, a
// free collapse spreads flatter, an infinite slope stands below the angle and
// slides above it. The measurements behind the bounds: docs/design.md,
// section 16.

#include <gtest/gtest.h>

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <functional>
#include <numeric>
#include <vector>

#include "host/physics/mpm.h"
#include "tests/test_util.h"

namespace ag2gs {
namespace {

using namespace test;
using Eigen::Vector3d;

constexpr double kDensity = 1600;

// Sand (E 1e5, nu 0.3, density 1600) filling the box [lo, hi) on the ground
// at lo.z where `inside(x, y)` holds, 8 particles a cell, simulated for
// `seconds` in equal substeps no longer than the solver's stable dt. Returns
// the particles before and after.
std::pair<MpmParticles, MpmParticles> run_sand(const MpmConfig& cfg, double friction_deg, const Vector3d& lo,
                                               const Vector3d& hi, double seconds,
                                               const std::function<bool(double, double)>& inside = nullptr) {
  MpmMaterial sand;
  sand.kind = MaterialKind::kSand;
  sand.E = 1e5;
  sand.nu = 0.3;
  sand.density = kDensity;
  sand.friction_deg = friction_deg;
  MpmParticles p;
  const double dx = 1.0 / cfg.grid, h = dx / 2;
  for (double x = lo.x() + h / 2; x < hi.x(); x += h)
    for (double y = lo.y() + h / 2; y < hi.y(); y += h) {
      if (inside && !inside(x, y)) continue;
      for (double z = lo.z() + h / 2; z < hi.z(); z += h)
        p.add({static_cast<float>(x), static_cast<float>(y), static_cast<float>(z)}, static_cast<float>(h * h * h), 0,
              kDensity);
    }
  MpmSolver solver(runtime(), cfg, {sand});
  solver.upload(p);
  const int steps = static_cast<int>(std::ceil(seconds / solver.max_stable_dt(3)));
  for (int s = 0; s < steps; ++s) solver.step(seconds / steps, true);
  MpmParticles q;
  solver.download(q);
  EXPECT_TRUE(diagnose(q, dx).finite);
  return {std::move(p), std::move(q)};
}

TEST(Sand, ThePileFitReadsTheSlopeOfACone) {
  // A cone of slope 35 degrees (apex 0.2 above the ground), cut flat at
  // 0.15: each column of cells holds particles up to the cone's height at
  // the column's centre, so the fit must give the cone's slope, and the
  // flat top (above 80% of the summit) must not enter it.
  const double dx = 1.0 / 48, ground = 0.1, slope = std::tan(35 * M_PI / 180);
  MpmParticles p;
  for (int a = 0; a < 48; ++a)
    for (int b = 0; b < 48; ++b) {
      const double x = (a + 0.5) * dx, y = (b + 0.5) * dx;
      const double h = std::min(0.15, 0.2 - slope * std::hypot(x - 0.5, y - 0.5));
      for (double z = ground + dx / 4; z < ground + h; z += dx / 2)
        p.add({static_cast<float>(x), static_cast<float>(y), static_cast<float>(z)}, 1e-6f, 0, kDensity);
      if (h > 0)
        p.add({static_cast<float>(x), static_cast<float>(y), static_cast<float>(ground + h)}, 1e-6f, 0, kDensity);
    }
  const PileShape s = measure_pile(p, dx, ground, 0.5, 0.5);
  EXPECT_NEAR(s.summit, 0.15, 1e-6);
  EXPECT_NEAR(s.flank_deg, 35.0, 1e-3);
  EXPECT_GT(s.flank_columns, 100);
  EXPECT_TRUE(std::isnan(measure_pile(MpmParticles(), dx, ground, 0.5, 0.5).flank_deg));
}

struct Pile {
  PileShape shape;       // summit and flank (host/physics/mpm.h)
  double rms_speed = 0;  // sqrt(2 kinetic / mass): m/s
};

// A round column of sand 0.24 high and 0.4 across (11.5 cells by 19 at grid
// 48) on a ground of friction 1, left for `seconds` with the grid's
// velocities damped at `damping` per second (0: none).
Pile sand_column(double friction_deg, double damping, double seconds) {
  MpmConfig cfg;
  cfg.grid = 48;
  cfg.ground = 0.1;
  cfg.friction = 1.0;
  cfg.damping = damping;
  const double radius = 0.2;
  const auto round = [radius](double x, double y) { return std::hypot(x - 0.5, y - 0.5) < radius; };
  const MpmParticles q =
      run_sand(cfg, friction_deg, Vector3d(0.3, 0.3, 0.1), Vector3d(0.7, 0.7, 0.34), seconds, round).second;
  Pile pile;
  pile.shape = measure_pile(q, 1.0 / cfg.grid, cfg.ground, 0.5, 0.5);
  EXPECT_GE(pile.shape.flank_columns, 100) << "no flank to fit";
  const double mass = std::accumulate(q.mass.begin(), q.mass.end(), 0.0);
  pile.rms_speed = std::sqrt(2 * diagnose(q, 1.0 / cfg.grid).kinetic / mass);
  std::printf(
      "sand column, damping %.0f/s, friction angle %.0f, %.2f s: summit %.3f (column 0.24), flank %.1f "
      "degrees, rms speed %.4f m/s\n",
      damping, friction_deg, seconds, pile.shape.summit, pile.shape.flank_deg, pile.rms_speed);
  return pile;
}

TEST(Sand, AColumnReleasedSlowlyRestsAtItsFrictionAngle) {
  // Without inertia a cohesionless pile comes to rest where its flank can
  // just stand: at the friction angle. Damping the grid's velocities at 15
  // per second (terminal speed g / 15 = 0.65 m/s) turns the collapse into a
  // creep. Measured (1.5 s): flanks of 32.6 and 37.8 degrees for friction
  // angles of 30 and 40, summits 0.192 and 0.202, rms speeds 0.005 and
  // 0.003 m/s. The same column damped at 30/s for 2.5 s: 33.8 and 38.3; at
  // 10/s for 1.5 s: 31.7 and 36.5. A column half as large (radius 4.8
  // cells) gives 29.5 and 32.7 (ag2gs_bench_mpm's sand table): the flank
  // needs about ten cells to show a steep angle.
  const Pile p30 = sand_column(30, 15, 1.5);
  const Pile p40 = sand_column(40, 15, 1.5);
  EXPECT_LT(p30.rms_speed, 0.01) << "still moving";
  EXPECT_LT(p40.rms_speed, 0.01) << "still moving";
  EXPECT_NEAR(p30.shape.flank_deg, 30.0, 4.0);
  EXPECT_NEAR(p40.shape.flank_deg, 40.0, 4.0);
  EXPECT_GT(p40.shape.flank_deg, p30.shape.flank_deg + 3.0);
}

TEST(Sand, AColumnCollapsingFreelySpreadsFlatterThanItsFrictionAngle) {
  // Undamped, the collapsing sand carries its momentum past the angle at
  // which it could stand (granular column collapse: the deposit is set by
  // the column's aspect ratio, flatter than a slowly built pile). Measured
  // (0.6 s): flanks of 23.4 and 27.7 degrees, summits 0.169 and 0.183.
  // Bounds: below the friction angle by 3 degrees or more, above 60% of it,
  // and steeper for more friction.
  const Pile p30 = sand_column(30, 0, 0.6);
  const Pile p40 = sand_column(40, 0, 0.6);
  EXPECT_LT(p30.rms_speed, 0.01) << "still moving";
  EXPECT_LT(p40.rms_speed, 0.01) << "still moving";
  EXPECT_GT(p30.shape.flank_deg, 0.6 * 30);
  EXPECT_LT(p30.shape.flank_deg, 30.0 - 3.0);
  EXPECT_GT(p40.shape.flank_deg, 0.6 * 40);
  EXPECT_LT(p40.shape.flank_deg, 40.0 - 3.0);
  EXPECT_GT(p40.shape.flank_deg, p30.shape.flank_deg + 2.0);
}

// A sand layer 0.1 thick on a ground tilted by theta (gravity turned by
// theta about y, a ground friction of 2 so that the sand fails inside itself):
// for a cohesionless material an infinite slope stands while theta is below
// its friction angle and slides beyond it. Returns the mean downslope
// displacement and velocity after 0.4 s of the particles of the upslope
// interior, away from the layer's free faces (which slump at any tilt).
std::pair<double, double> tilted_layer(double friction_deg, double tilt_deg) {
  MpmConfig cfg;
  cfg.grid = 48;
  cfg.ground = 0.1;
  cfg.friction = 2.0;
  const double t = tilt_deg * M_PI / 180;
  cfg.gravity = {9.8 * std::sin(t), 0.0, -9.8 * std::cos(t)};
  const auto [p, q] = run_sand(cfg, friction_deg, Vector3d(0.15, 0.3, 0.1), Vector3d(0.85, 0.7, 0.2), 0.4);
  double moved = 0, speed = 0;
  int n = 0;
  for (size_t i = 0; i < q.size(); ++i)
    if (p.x[3 * i] > 0.25 && p.x[3 * i] < 0.45 && std::abs(p.x[3 * i + 1] - 0.5) < 0.1) {
      moved += q.x[3 * i] - p.x[3 * i];
      speed += q.v[3 * i];
      ++n;
    }
  moved /= n;
  speed /= n;
  std::printf("sand layer, friction angle %.0f, tilt %.0f: interior moved %.4f, moving at %.4f m/s\n", friction_deg,
              tilt_deg, moved, speed);
  return {moved, speed};
}

TEST(Sand, ALayerStandsBelowItsFrictionAngleAndSlidesAbove) {
  // Measured: tilt 25 for a friction angle of 30, moved 0.0042 and moving
  // at 0.0040 m/s (settled); tilt 35, moved 0.036 and moving at 0.12 m/s
  // (a rigid block on a plane of friction 30 degrees would be at 0.40 m/s:
  // the layer shears over a band, not a plane). So the material's friction
  // angle in this quasi-static test is within 5 degrees of the one asked for.
  const auto [moved_below, speed_below] = tilted_layer(30, 25);
  const auto [moved_above, speed_above] = tilted_layer(30, 35);
  EXPECT_LT(std::abs(speed_below), 0.01);
  EXPECT_LT(std::abs(moved_below), 0.01);
  EXPECT_GT(speed_above, 0.05);
  EXPECT_GT(moved_above, 0.02);
}

}  // namespace
}  // namespace ag2gs
