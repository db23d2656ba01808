// MLS-MPM on the device (kernels/mpm.cl): particles carry mass, velocity, a
// deformation gradient F and an APIC affine matrix C; each substep moves
// their momentum and stress onto a grid, updates the grid velocities, and
// moves the velocities back (docs/design.md, "Physics").
//
// Determinism: a particle never adds into a grid node. The host sorts the
// particles by their base cell (a stable counting sort), and every node
// gathers from the particles of its 27 neighbouring cells in that fixed order,
// so a substep is bit-identical across runs and thread counts; there are no
// atomics in the solver.
//
// Units: the solver works in a box [0, 1]^3 metres with +z up; the grid has
// `grid` cells per side, dx = 1 / grid. The caller maps its world into that
// box (apps/simulation/simulation.h). Particles must stay within the box; the walls
// (3 cells) and the ground plane keep them there.
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include "host/device/cl_runtime.h"

namespace ag2gs {

enum class MaterialKind : int32_t {
  kJelly = 0,       // fixed-corotated elasticity
  kMetal = 1,       // StVK on the Hencky strain, von Mises plasticity
  kSand = 2,        // StVK on the Hencky strain, Drucker-Prager plasticity
  kPlasticine = 3,  // StVK on the Hencky strain, von Mises with softening
};

// "jelly" | "metal" | "sand" | "plasticine"; std::invalid_argument otherwise.
MaterialKind parse_material(const std::string& name);
const char* material_name(MaterialKind kind);

struct MpmMaterial {
  MaterialKind kind = MaterialKind::kJelly;
  double E = 2e6;                           // Young's modulus (Pa)
  double nu = 0.4;                          // Poisson's ratio, in (-1, 0.5)
  double density = 1000;                    // kg / m^3
  double yield_stress = 0;                  // metal, plasticine: von Mises yield (Pa); 0 = E / 100
  double friction_deg = 30;                 // sand: friction angle
  double softening = 1;                     // plasticine: the yield stress is divided by 1 + softening * plastic strain
  std::array<double, 3> force = {0, 0, 0};  // extra acceleration (m/s^2) while forces are on

  double mu() const { return E / (2 * (1 + nu)); }
  double lambda() const { return E * nu / ((1 + nu) * (1 - 2 * nu)); }
  // Speed of the fastest (dilatational) elastic wave, sqrt((lambda + 2 mu) / rho).
  double wave_speed() const;
};

struct MpmConfig {
  int grid = 64;                                 // cells per side of the unit box
  std::array<double, 3> gravity = {0, 0, -9.8};  // m/s^2
  double ground = -1;                            // height of the ground plane (z); < 0 = none
  double friction = 0;                           // Coulomb friction of the ground (0 = it slips)
  double cfl = 0.3;                              // dt <= cfl * dx / (wave speed + |v|max)
  // Viscous drag on the grid's velocities (1/s): each substep divides them by
  // 1 + damping dt. 0 (default) leaves the dynamics undamped; a large value
  // removes inertia, so a collapse creeps to the state a slow release would
  // reach (tests/host/physics/test_mpm.cpp).
  double damping = 0;
};

// The particles, on the host. N = x.size() / 3.
struct MpmParticles {
  std::vector<float> x;           // [N,3] position in the box
  std::vector<float> v;           // [N,3] velocity
  std::vector<float> F;           // [N,9] deformation gradient, row-major
  std::vector<float> C;           // [N,9] APIC affine velocity gradient, row-major
  std::vector<float> volume;      // [N] rest volume (m^3)
  std::vector<float> mass;        // [N] kg
  std::vector<float> plastic;     // [N] accumulated plastic strain (plasticine) or volume correction (sand)
  std::vector<int32_t> material;  // [N] index into the solver's materials

  size_t size() const { return mass.size(); }
  // Appends a particle at rest (F = I, C = 0) of `volume` and material `m`,
  // its mass from that material's density.
  void add(const std::array<float, 3>& pos, float volume, int32_t m, double density);
};

// Whole-system quantities of a particle set, summed in double in index order.
struct MpmDiagnostics {
  double kinetic = 0;                // sum m |v|^2 / 2 (APIC's C term left out)
  std::array<double, 3> momentum{};  // sum m v
  std::array<double, 3> angular{};   // about the origin: sum m x cross v + APIC's spin, m dx^2 / 4 eps : C^T
  double max_strain = 0;             // max |F - I| (Frobenius)
  bool finite = true;                // every x, v, F finite
};
// `dx`: the grid's cell (APIC's spin term); `of_material` >= 0: only that
// material's particles.
MpmDiagnostics diagnose(const MpmParticles& p, double dx, int of_material = -1);
// Mass-weighted centre of the particles of `of_material` (-1 = all).
std::array<double, 3> centre_of_mass(const MpmParticles& p, int of_material = -1);

// The shape of a pile standing on the ground at height `ground`, centred on
// the vertical axis through (cx, cy): its surface is the highest particle in
// each dx-by-dx column of cells, and its flank's slope the least-squares
// line of that height against the column's distance from the axis, over the
// columns standing between 20% and 80% of the summit (all of them, so no
// single column, a corner's say, sets it).
struct PileShape {
  double summit = 0;      // highest particle above the ground
  double flank_deg = 0;   // slope of the flank in degrees (NaN with fewer than 3 columns)
  int flank_columns = 0;  // columns the fit used
};
PileShape measure_pile(const MpmParticles& p, double dx, double ground, double cx, double cy);

class MpmSolver {
 public:
  // Materials are indexed by MpmParticles::material. Throws
  // std::invalid_argument for a bad grid (8..512), a material with E <= 0,
  // nu outside (-1, 0.5), density <= 0, or no materials.
  MpmSolver(Runtime& rt, const MpmConfig& config, std::vector<MpmMaterial> materials);

  // Particles outside [3 dx, 1 - 3 dx] on any axis are refused
  // (std::invalid_argument naming the first).
  void upload(const MpmParticles& particles);
  void download(MpmParticles& particles) const;  // every array
  size_t particles() const { return n_; }

  // The largest stable substep for particles moving at most `max_speed`.
  double max_stable_dt(double max_speed = 0) const;
  // One substep of `dt` seconds; the materials' forces apply when `forces_on`.
  void step(double dt, bool forces_on);

  // The particles' positions [N,3] and deformation gradients [N,9] on the
  // device, in the caller's order (for kernels that read them).
  const DeviceBuffer& positions() const { return x_; }
  const DeviceBuffer& deformation() const { return F_; }
  const MpmConfig& config() const { return config_; }
  const std::vector<MpmMaterial>& materials() const { return materials_; }

 private:
  void sort_by_cell();

  Runtime& rt_;
  MpmConfig config_;
  std::vector<MpmMaterial> materials_;
  size_t n_ = 0;
  DeviceBuffer x_, v_, F_, C_, volume_, mass_, plastic_, material_;
  DeviceBuffer mat_params_;  // [M,8] per material: kind, mu, lambda, yield, alpha, softening, (unused) x2
  DeviceBuffer keys_;        // [N] base cell of each particle
  DeviceBuffer order_;       // [N] particles sorted by cell (stable)
  DeviceBuffer cell_start_;  // [cells+1] into order_
  DeviceBuffer active_;      // [active nodes] node ids the particles reach
  DeviceBuffer pdata_;       // [N,16] per sorted particle: x, m, m v (+ forces), affine Q (9)
  DeviceBuffer grid_v_;      // [cells,4] velocity, mass
  std::vector<int32_t> keys_host_, order_host_, start_host_, active_host_;
  std::vector<uint8_t> active_mark_;
  std::array<int, 3> lo_{}, hi_{};  // the cells the particles occupy (inclusive), for the grid pass
};

}  // namespace ag2gs
