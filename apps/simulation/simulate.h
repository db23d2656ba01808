// Physics of a selected object as one library call (docs/design.md,
// "Physics"): the object's Gaussians (with the kept anchors it hid from every
// photo) become MLS-MPM particles (apps/simulation/simulation.h), a force
// pushes it for some frames, and each frame is rendered from the chosen views
// over the model's backdrop.
//
// `ag2gs simulate` selects the object, calls simulate_object and writes what
// its callbacks hand over (frames/, ply/, simulation.json); the tests call it
// directly. Nothing here writes files.
#pragma once

#include <cstdint>
#include <functional>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "apps/backdrop.h"
#include "apps/simulation/simulation.h"
#include "host/device/cl_runtime.h"
#include "host/io/model_io.h"
#include "host/scene/scene.h"
#include "train/anchors/anchor_model.h"

namespace ag2gs {

struct SimulationRequest {
  ObjectInModel object;      // the model, its scene (at the resolution used) and the selection
  std::vector<int> views;    // scene views rendered every frame (at least one)
  SimulationSettings settings;  // the solver's (settings.force is replaced by the force below)
  // The acceleration on the object during force_frames (m/s^2, world frame);
  // unset: `push` m/s^2 along the first view's right, across up.
  std::optional<Eigen::Vector3d> force;
  double push = 10;
  bool move_hidden = true;   // kept anchors the object hid from every photo move with it
  int frames = 30;           // frame 0, the start, is rendered too
  double fps = 25;           // frames per second of simulated time (sets settings.frame_time)
  std::pair<int, int> force_frames{0, 3};  // the force acts in frames [A, B)
  double max_substeps = 2e6;  // refuse a run that needs more (it would run for hours)
  std::string material = "jelly";  // the object's material's name, for messages
  // Each view's render of frame f (rgb over the backdrop), views in order.
  std::function<void(int frame, size_t view, const RenderOutput& image)> on_render;
  // After each frame's renders (frame 0 included), with the simulation as it stands.
  std::function<void(int frame, Simulation& sim)> on_frame;
  // Called after each frame with what is running; it may throw to stop (Ctrl-C).
  std::function<void(const std::string& during)> check_stop;

  // The settings (not the object, views or callbacks): throws
  // std::invalid_argument naming the `simulate` flag; and as `ag2gs simulate
  // --print-config` prints them.
  void validate() const;
  nlohmann::json to_json() const;
};

struct SimulationResult {
  int substeps = 0;           // over every frame
  double simulate_s = 0;      // wall time in the solver
  // simulation.json's record: the solver's description, the hidden anchors
  // moved, the force frames, the substeps and each frame's statistics
  // (energy, momentum, centre of mass, strain).
  nlohmann::json report;
};

// Throws std::invalid_argument for a request that cannot run (no model, a
// selection of another size, no view, settings the solver refuses, more
// substeps than max_substeps).
SimulationResult simulate_object(Runtime& rt, const SimulationRequest& request);

}  // namespace ag2gs
