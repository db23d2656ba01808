// ag2gs_bench_mpm: speed of the MLS-MPM solver (host/physics/mpm.h) against
// its error.
// 1. Accuracy, for jelly cubes of 2 particles per cell and axis at each grid:
//    time per substep (median of 3 runs) and per kernel, the free-fall error
//    against the parabola (the scheme's exact error is dt / t of the drop, so
//    what is reported beyond that is the solver's), and the energy of an
//    elastic bounce (never above the start; what it lost is numerical
//    dissipation).
// 2. Scale: a cube of N particles (--particles, default 100k and 1M) at each
//    grid, time per substep, and time per frame at 25 frames/s for the
//    defaults of `simulate` (E = 2e6, nu 0.4, 1000 kg/m^3).
// 3. Sand piles: round columns of sand (as tall as 1.2 radii) released slowly
//    (`--damping`) at grid 48 for friction angles of 30 and 40: the flank's
//    slope (measure_pile) against the angle, and the wall time. The flank
//    needs cells: the error falls as the column grows.
#include <CLI/CLI.hpp>
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <map>
#include <vector>

#include "host/device/cl_runtime.h"
#include "host/physics/mpm.h"

using namespace ag2gs;

namespace {

MpmParticles cube(double cx, double cy, double cz, double side, double spacing) {
  MpmParticles p;
  const int k = static_cast<int>(std::lround(side / spacing));
  for (int i = 0; i < k; ++i)
    for (int j = 0; j < k; ++j)
      for (int l = 0; l < k; ++l)
        p.add({static_cast<float>(cx + (i + 0.5 - k / 2.0) * spacing),
               static_cast<float>(cy + (j + 0.5 - k / 2.0) * spacing),
               static_cast<float>(cz + (l + 0.5 - k / 2.0) * spacing)},
              static_cast<float>(spacing * spacing * spacing), 0, 1000);
  return p;
}

double total_energy(const MpmParticles& q, double dx, const MpmMaterial& m) {
  double e = diagnose(q, dx).kinetic;
  for (size_t i = 0; i < q.size(); ++i) {
    e += q.mass[i] * 9.8 * q.x[3 * i + 2];
    // Fixed-corotated energy for small strains: mu |F - I|_sym^2 + lambda / 2 tr^2 (enough to rank).
    double tr = 0, s = 0;
    for (int a = 0; a < 3; ++a) {
      tr += q.F[9 * i + 4 * a] - 1;
      for (int b = 0; b < 3; ++b) {
        const double eab = 0.5 * (q.F[9 * i + 3 * a + b] + q.F[9 * i + 3 * b + a]) - (a == b);
        s += eab * eab;
      }
    }
    e += q.volume[i] * (m.mu() * s + 0.5 * m.lambda() * tr * tr);
  }
  return e;
}

// A round column of sand of radius r and height 1.2 r centred on (0.5, 0.5)
// on the ground at 0.1, 2 particles per cell and axis.
MpmParticles sand_column(double r, double dx) {
  MpmParticles p;
  const double h = dx / 2;
  for (double x = 0.5 - r + h / 2; x < 0.5 + r; x += h)
    for (double y = 0.5 - r + h / 2; y < 0.5 + r; y += h) {
      if (std::hypot(x - 0.5, y - 0.5) >= r) continue;
      for (double z = 0.1 + h / 2; z < 0.1 + 1.2 * r; z += h)
        p.add({static_cast<float>(x), static_cast<float>(y), static_cast<float>(z)}, static_cast<float>(h * h * h), 0,
              1600);
    }
  return p;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"ag2gs_bench_mpm: MLS-MPM speed against error"};
  int device = -1;
  double seconds = 0.05;
  std::vector<int> grids = {32, 64, 128};
  app.add_option("--device", device, "OpenCL device index (default: the first)");
  app.add_option("--seconds", seconds, "Simulated time per case (default 0.05)");
  app.add_option("--grids", grids, "Grid sizes (default 32 64 128)");
  std::vector<int> counts = {100000, 1000000};
  int scale_steps = 3;
  app.add_option("--particles", counts, "Particle counts of the scale table (default 100000 1000000)");
  app.add_option("--scale-steps", scale_steps, "Substeps timed per scale case (default 3)");
  std::vector<double> sand_radii = {0.1, 0.15, 0.2};
  double sand_seconds = 1.5, sand_damping = 15;
  bool no_sand = false;
  app.add_option("--sand-radii", sand_radii, "Radii of the sand columns (default 0.1 0.15 0.2)");
  app.add_option("--sand-seconds", sand_seconds, "Simulated time of each sand column (default 1.5)");
  app.add_option("--sand-damping", sand_damping, "Damping of the sand columns, per second (default 15)");
  app.add_flag("--no-sand", no_sand, "Skip the sand piles (minutes on 2 CPU cores)");
  CLI11_PARSE(app, argc, argv);
  Runtime rt(device);
  std::printf("device: %s\n\n", rt.info().name.c_str());
  std::printf(
      "| grid | particles | dt (s) | substeps | ms / substep | particles / s | free-fall error - dt/t | bounce energy "
      "max / start, end / start | sort / stress / grid / g2p (ms) |\n");
  std::printf("| --- | ---: | ---: | ---: | ---: | ---: | ---: | --- | --- |\n");
  for (int g : grids) {
    MpmMaterial m;
    m.E = 1e5;
    m.nu = 0.3;
    MpmConfig cfg;
    cfg.grid = g;
    const double dx = 1.0 / g;
    // Free fall (uniform motion: F stays I) timed, then a bounce on the ground.
    MpmParticles p = cube(0.5, 0.5, 0.7, 0.25, dx / 2);
    MpmSolver s(rt, cfg, {m});
    const double dt = s.max_stable_dt(3.0);
    const int steps = std::max(1, static_cast<int>(std::ceil(seconds / dt)));
    std::vector<double> ms;
    double err = 0;
    std::map<std::string, double> kernels;
    for (int rep = 0; rep < 3; ++rep) {
      s.upload(p);
      rt.set_profiling(rep == 2);
      rt.take_timings();
      rt.queue().finish();
      const auto t0 = std::chrono::steady_clock::now();
      for (int k = 0; k < steps; ++k) s.step(dt, false);
      rt.queue().finish();
      ms.push_back(std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count() / steps);
      if (rep == 2) kernels = rt.take_timings();
      rt.set_profiling(false);
      MpmParticles q;
      s.download(q);
      const double t = steps * dt, drop = 9.8 * t * t / 2;
      err = ((centre_of_mass(p)[2] - drop) - centre_of_mass(q)[2]) / drop - dt / t;
    }
    std::sort(ms.begin(), ms.end());
    MpmConfig bc = cfg;
    bc.ground = 0.2;
    MpmParticles b = cube(0.5, 0.5, 0.35, 0.12, dx / 2);
    MpmSolver bs(rt, bc, {m});
    bs.upload(b);
    const double e0 = total_energy(b, dx, m);
    double emax = e0, eend = e0;
    const int bsteps = static_cast<int>(std::ceil(0.5 / bs.max_stable_dt(4.0)));
    const double bdt = 0.5 / bsteps;
    MpmParticles q;
    for (int k = 1; k <= bsteps; ++k) {
      bs.step(bdt, false);
      if (k % std::max(1, bsteps / 50) && k != bsteps) continue;
      bs.download(q);
      eend = total_energy(q, dx, m);
      emax = std::max(emax, eend);
    }
    auto km = [&](const char* k) { return kernels.count(k) ? kernels[k] / steps : 0.0; };
    std::printf("| %d | %zu | %.2e | %d | %.3f | %.3g | %.1e | %.4f, %.4f | %.3f / %.3f / %.3f / %.3f |\n", g, p.size(),
                dt, steps, ms[1], p.size() / (ms[1] / 1000), err, emax / e0, eend / e0, km("mpm_keys"),
                km("mpm_particle_stress"), km("mpm_grid"), km("mpm_g2p"));
    std::fflush(stdout);
  }
  std::printf("\n| grid | particles | ms / substep | substeps / frame (E 2e6, 25 fps) | s / frame |\n");
  std::printf("| --- | ---: | ---: | ---: | ---: |\n");
  for (int g : grids) {
    if (g < 64) continue;
    for (int n : counts) {
      const double dx = 1.0 / g;
      // n particles in a cube at 2 per cell and axis, or denser when that
      // cube would not fit inside the walls.
      double spacing = dx / 2;
      if (std::cbrt(static_cast<double>(n)) * spacing > 1 - 10 * dx)
        spacing = (1 - 10 * dx) / std::cbrt(static_cast<double>(n));
      const double side = std::cbrt(static_cast<double>(n)) * spacing;
      MpmParticles p = cube(0.5, 0.5, 0.5, side, spacing);
      MpmMaterial m;
      m.E = 2e6;
      m.nu = 0.4;
      MpmConfig cfg;
      cfg.grid = g;
      cfg.ground = 0.5 - side / 2 - dx;
      MpmSolver s(rt, cfg, {m});
      s.upload(p);
      s.step(1e-5, false);  // warm-up: kernel builds, buffers
      rt.queue().finish();
      const auto t0 = std::chrono::steady_clock::now();
      for (int k = 0; k < scale_steps; ++k) s.step(1e-5, false);
      rt.queue().finish();
      const double ms =
          std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count() / scale_steps;
      const int per_frame = static_cast<int>(std::ceil(0.04 / s.max_stable_dt(1.0)));
      std::printf("| %d | %zu | %.1f | %d | %.1f |\n", g, p.size(), ms, per_frame, ms * per_frame / 1000);
      std::fflush(stdout);
    }
  }
  if (no_sand) return 0;
  std::printf("\n| column radius (cells) | friction angle | particles | substeps | s | flank (degrees) | error |\n");
  std::printf("| --- | ---: | ---: | ---: | ---: | ---: | ---: |\n");
  for (double r : sand_radii)
    for (double phi : {30.0, 40.0}) {
      MpmConfig cfg;
      cfg.grid = 48;
      cfg.ground = 0.1;
      cfg.friction = 1;
      cfg.damping = sand_damping;
      MpmMaterial m;
      m.kind = MaterialKind::kSand;
      m.E = 1e5;
      m.nu = 0.3;
      m.density = 1600;
      m.friction_deg = phi;
      const MpmParticles p = sand_column(r, 1.0 / cfg.grid);
      MpmSolver s(rt, cfg, {m});
      s.upload(p);
      const int steps = static_cast<int>(std::ceil(sand_seconds / s.max_stable_dt(3)));
      const auto t0 = std::chrono::steady_clock::now();
      for (int k = 0; k < steps; ++k) s.step(sand_seconds / steps, true);
      MpmParticles q;
      s.download(q);
      const double sec = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
      const PileShape pile = measure_pile(q, 1.0 / cfg.grid, cfg.ground, 0.5, 0.5);
      std::printf("| %.3g (%.1f) | %.0f | %zu | %d | %.1f | %.1f | %+.1f |\n", r, r * cfg.grid, phi, p.size(), steps,
                  sec, pile.flank_deg, pile.flank_deg - phi);
      std::fflush(stdout);
    }
  return 0;
}
