// Every setting of a simulation (SimulationRequest, apps/simulation/simulate.h,
// with its SimulationSettings) declared once, as the training settings are
// (host/core/settings.h): its field, its key in `simulate --print-config` and
// simulation.json, its flag and help, and the range it must lie in. The
// request's to_json and validate and `simulate`'s flags loop over this
// table; the default of each field is its initialiser. Vectors, the frame
// range, the material's name and the optional ground are Custom rows.
#pragma once

#include <Eigen/Core>
#include <string>
#include <utility>
#include <vector>

#include "host/core/settings.h"

namespace ag2gs {

struct SimulationRequest;
using SimulationSetting = Setting<SimulationRequest>;

// The table, in --help's order.
const std::vector<SimulationSetting>& simulation_settings();

// "X,Y,Z" -> a finite vector; throws std::invalid_argument naming `flag`.
Eigen::Vector3d parse_vector(const std::string& text, const std::string& flag);
// "A:B" -> [A, B) with 0 <= A <= B: the frames the force acts in; throws
// std::invalid_argument naming --force-frames.
std::pair<int, int> parse_frames(const std::string& text);

}  // namespace ag2gs
