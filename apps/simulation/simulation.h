// Physics on a trained scene (docs/design.md, "Physics"): the selected
// object's Gaussians become particles of an MLS-MPM simulation
// (host/physics/mpm.h), its closed volume is filled with more particles so
// that a hollow shell does not collapse, the other Gaussians inside the
// simulation box become a softer background material, and every frame the
// Gaussians follow their particles (position, covariance F Sigma F^T, view
// direction turned by F's rotation) and render like any model.
#pragma once

#include <Eigen/Dense>
#include <array>
#include <memory>
#include <nlohmann/json.hpp>
#include <optional>
#include <vector>

#include "host/core/gaussians.h"
#include "host/device/cl_runtime.h"
#include "host/physics/mpm.h"
#include "host/scene/scene_up.h"

namespace ag2gs {

// The defaults are `ag2gs simulate`'s.
struct SimulationSettings {
  // The selection (material 0). E = 2e6 Pa: the paper's 2e8 needs 5,600
  // substeps per frame at grid 64 (the elastic wave crosses a cell in 7e-6
  // s), 46-66 s a frame, 25-33 minutes for 30 frames on 2 CPU cores; 2e6,
  // the paper's background stiffness, takes about 570 (docs/benchmarks.md,
  // "Physics").
  MpmMaterial object;
  // The other Gaussians inside the box (material 1): von Mises plasticity,
  // the paper's background.
  MpmMaterial background{MaterialKind::kMetal, 2e6, 0.3};
  // The rest of the scene in the box as particles: off by default. On the
  // seed-1 mug it made the thin pole and the box on it sag under gravity
  // (|F - I| up to 2.8): a pole a Gaussian or two thick is too few particles
  // per cell for the solver (docs/benchmarks.md, "Physics").
  bool with_background = false;
  int grid = 64;
  double frame_time = 0.04;                         // s
  double dt = 0;                                    // s; 0 = the largest stable substep
  std::optional<Eigen::Vector3d> gravity;           // world frame, m/s^2; default 9.8 down
  Eigen::Vector3d force = Eigen::Vector3d::Zero();  // world frame, m/s^2, on the object while forces are on
  std::optional<Eigen::Vector3d> up;                // world frame; default from the cameras
  std::optional<double> ground;                     // height along up (world units); default from the SfM points
  double friction = 0.5;                            // Coulomb friction of the ground
  double damping = 0;                               // drag on the grid's velocities, 1/s (0 = none)
  float min_opacity = 0.02f;                        // Gaussians below this opacity stay out of the simulation
  double object_size = 0.4;                         // the object's largest side, in box units (metres)

  // Throws std::invalid_argument naming the flag.
  void validate() const;
};

// The map between the world and the simulation box: box = s A (world - o) + b,
// A a rotation that takes `up` to +z.
struct SimulationFrame {
  Eigen::Matrix3d A = Eigen::Matrix3d::Identity();
  double scale = 1;
  Eigen::Vector3d origin = Eigen::Vector3d::Zero();  // o (world)
  Eigen::Vector3d box = Eigen::Vector3d::Zero();     // b (box)
  Eigen::Vector3d up = Eigen::Vector3d::UnitZ();
  double ground_world = 0;  // height of the ground along up
  double ground_box = 0;    // the same plane's z in the box

  Eigen::Vector3d to_box(const Eigen::Vector3d& w) const { return scale * (A * (w - origin)) + box; }
  Eigen::Vector3d to_world(const Eigen::Vector3d& x) const { return A.transpose() * (x - box) / scale + origin; }
  // A world-frame vector (an acceleration) in box units: s A v.
  Eigen::Vector3d vector_to_box(const Eigen::Vector3d& v) const { return scale * (A * v); }
};

// The surface an object rests on: the SfM points within 1.5 radii of the
// object's centre (across up; 3 or 6 when fewer than 10 lie there) and below
// its lowest tenth, their highest tenth (a table top, a floor). Without 10
// such points, the object's own lowest Gaussian. Heights are along `up`.
double ground_below(const std::vector<Eigen::Vector3d>& points, const std::vector<Eigen::Vector3d>& object,
                    const Eigen::Vector3d& up);

// The ground under an object: the scene's main plane `floor` (scene_up's,
// with its normal along `up`) when the object's lowest Gaussians (the 2nd
// percentile of their heights) lie within a tenth of the object's height
// (2nd to 98th percentile) of it: the object stands on it. Else
// ground_below(). Without the plane, the SfM points near a cup standing on
// a table put the ground at their highest tenth under the cup's lowest tenth,
// which includes the cup's own lower part (0.54 units above the table).
double support_height(const std::vector<Eigen::Vector3d>& points, const std::vector<Eigen::Vector3d>& object,
                      const Eigen::Vector3d& up, const std::optional<Plane>& floor);

// The cells of the solid an object's Gaussians (`surface`, positions in
// [0, 1]^3) bound, on a grid of cell `cell`: the occupied cells, closed by
// one cell (a dilation, so that Gaussians a cell or two apart still make a
// wall), every cell that rays along all six axis directions from it meet a
// wall cell, and then eroded by one cell again (the occupied cells always
// stay). Returns the cells' centres.
std::vector<Eigen::Vector3d> fill_solid(const std::vector<Eigen::Vector3d>& surface, double cell);

struct SimFrameStats {
  int frame = 0;
  double time = 0;        // s, simulated
  double wall_s = 0;      // s, to simulate it
  int substeps = 0;       // of dt() each: the frame time over the stable substep at the last frame's top speed
  MpmDiagnostics all;     // every particle
  MpmDiagnostics object;  // material 0
  std::array<double, 3> object_centre{};  // world frame
};

class Simulation {
 public:
  // `scene`: every Gaussian of the model; `selected[g]`: Gaussian g belongs to
  // the object; `cameras` give the up direction, `points` the ground.
  Simulation(Runtime& rt, const GaussianSet& scene, const std::vector<uint8_t>& selected,
             const std::vector<Camera>& cameras, const std::vector<Eigen::Vector3d>& points,
             const SimulationSettings& settings);

  const SimulationFrame& frame() const { return frame_; }
  // The substep of the last frame (the first: at the speed gravity and the
  // force can give in one frame).
  double dt() const { return dt_; }
  size_t object_gaussians() const { return object_gaussians_; }
  size_t fill_particles() const { return fill_particles_; }
  size_t background_gaussians() const { return background_gaussians_; }
  size_t particles() const { return particles_.size(); }

  // Simulates one frame, the object's force on when `forces_on`. The
  // substep is --dt when given (refused by the constructor when unstable at
  // rest), else the largest stable one at the particles' top speed so far.
  SimFrameStats advance(bool forces_on);
  // Stats of the current state without simulating (frame 0).
  SimFrameStats stats() const;

  // The scene as it stands now, for a camera at `campos` (colours baked for
  // that view; the PLY export passes the trained SH instead: bake = false).
  GaussianSet gaussians(const Eigen::Vector3d& campos, bool bake = true);

  nlohmann::json describe() const;
  // The solver, for tests and tools that set particle states directly.
  MpmSolver& solver() { return *solver_; }

 private:
  // The constructor's steps: the box around `object` (world points), the
  // particles (returns the materials in use), the solver, the trained
  // Gaussians of the particles on the device.
  void place_box(const std::vector<Eigen::Vector3d>& object, const std::vector<Camera>& cameras,
                 const std::vector<Eigen::Vector3d>& points);
  std::vector<MpmMaterial> add_particles(const std::vector<uint8_t>& selected);
  void start_solver(const std::vector<MpmMaterial>& materials);
  void upload_gaussians();

  Runtime& rt_;
  SimulationSettings settings_;
  SimulationFrame frame_;
  GaussianSet scene_;
  std::unique_ptr<MpmSolver> solver_;
  MpmParticles particles_;
  std::vector<int32_t> moving_;    // Gaussians that follow a particle
  std::vector<int32_t> particle_;  // [moving] their particles
  size_t object_gaussians_ = 0, fill_particles_ = 0, background_gaussians_ = 0, support_gaussians_ = 0;
  double dt_ = 0;
  int frames_done_ = 0;
  double max_speed_ = 0;   // top particle speed expected in the next frame
  double speed_gain_ = 0;  // what gravity and the force can add in one frame
  DeviceBuffer d_particle_, d_scales0_, d_quats0_, d_sh0_, d_frame_, d_means_, d_scales_, d_quats_, d_sh_;
};

}  // namespace ag2gs
