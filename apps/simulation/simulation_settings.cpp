#include "apps/simulation/simulation_settings.h"

#include <optional>
#include <sstream>
#include <stdexcept>

#include "apps/simulation/simulate.h"

namespace ag2gs {

Eigen::Vector3d parse_vector(const std::string& text, const std::string& flag) {
  std::stringstream ss(text);
  Eigen::Vector3d v;
  char comma = 0;
  if (!(ss >> v(0) >> comma) || comma != ',' || !(ss >> v(1) >> comma) || comma != ',' || !(ss >> v(2)) || !ss.eof() ||
      !v.allFinite())
    throw std::invalid_argument(flag + " " + text + ": give three numbers as X,Y,Z");
  return v;
}

std::pair<int, int> parse_frames(const std::string& text) {
  const size_t c = text.find(':');
  try {
    if (c == std::string::npos) throw std::invalid_argument("");
    size_t used = 0;
    const int a = std::stoi(text.substr(0, c), &used);
    if (used != c) throw std::invalid_argument("");
    const int b = std::stoi(text.substr(c + 1), &used);
    if (used != text.size() - c - 1 || a < 0 || b < a) throw std::invalid_argument("");
    return {a, b};
  } catch (const std::exception&) {
    throw std::invalid_argument("--force-frames " + text + ": give A:B with 0 <= A <= B (frames A to B-1)");
  }
}

namespace {

template <class T>
constexpr auto field = &SimulationSetting::of<T>;  // a row's field from a lambda
using C = SimulationRequest;
using Vec = std::optional<Eigen::Vector3d>;
using nlohmann::json;

// An optional vector in JSON: [x, y, z] or null (unset: the default rule).
json vector_json(const Vec& v) { return v ? json::array({(*v)(0), (*v)(1), (*v)(2)}) : json(nullptr); }
Vec vector_from_json(const json& j, const std::string& flag) {
  if (j.is_null()) return std::nullopt;
  const std::vector<double> v = j.get<std::vector<double>>();
  if (v.size() != 3) throw std::invalid_argument(flag + ": give three numbers as X,Y,Z");
  const Eigen::Vector3d out(v[0], v[1], v[2]);
  if (!out.allFinite()) throw std::invalid_argument(flag + ": give three finite numbers");
  return out;
}

// --material: the object's material by name; the request keeps the name
// for its messages.
void set_material(C& c, const std::string& name) {
  c.settings.object.kind = parse_material(name);
  c.material = name;
}

void add_material_rows(SettingRows<C>& add) {
  add(SimulationSetting::Custom{[](const C& c) { return json(c.material); },
                                [](C& c, const json& v) { set_material(c, v.get<std::string>()); }, set_material},
      "material", "--material", "The object's material: jelly (default), metal, sand or plasticine")
      .one_of({"jelly", "metal", "sand", "plasticine"});
  add(field<double>([](C& c) -> double& { return c.settings.object.E; }), "settings.object.E", "--E",
      "The object's Young's modulus in Pa (default 2e6; the paper's 2e8 is 100x stiffer and takes 10x the substeps)")
      .positive();
  add(field<double>([](C& c) -> double& { return c.settings.object.nu; }), "settings.object.nu", "--nu",
      "The object's Poisson's ratio (default 0.4)");
  add(field<double>([](C& c) -> double& { return c.settings.object.density; }), "settings.object.density",
      "--density", "Density in kg/m^3 of every material (default 1000)")
      .range(0.1, 100000);
  add(field<double>([](C& c) -> double& { return c.settings.background.E; }), "settings.background.E",
      "--background-E", "Young's modulus of the other Gaussians inside the simulation box (default 2e6; von Mises)")
      .positive();
  add(field<double>([](C& c) -> double& { return c.settings.background.nu; }), "settings.background.nu",
      "--background-nu", "Their Poisson's ratio (default 0.3)");
  add(field<bool>([](C& c) -> bool& { return c.settings.with_background; }), "settings.with_background",
      "--background,!--no-background",
      "Also simulate the other Gaussians inside the simulation box above the ground, as --background-E material (the "
      "paper's setting; default off: the rest of the scene stays still)");
  add(field<bool>([](C& c) -> bool& { return c.move_hidden; }), "move_hidden", "!--keep-hidden",
      "Leave in place the kept anchors inside the object that the training views saw only through it (by default "
      "they move with it, as `remove` takes them with it)");
}

void add_time_rows(SettingRows<C>& add) {
  add(field<int>([](C& c) -> int& { return c.frames; }), "frames", "--frames",
      "Frames to simulate (default 30; frame 0, the start, is written too)")
      .range(1, 100000);
  add(field<double>([](C& c) -> double& { return c.fps; }), "fps", "--fps",
      "Frames per second of simulated time (default 25)")
      .positive();
  add(field<double>([](C& c) -> double& { return c.max_substeps; }), "max_substeps", "--max-substeps",
      "Refuse a run that needs more substeps than this (default 2e6; the cup's defaults take ~18k)")
      .positive();
  add(field<double>([](C& c) -> double& { return c.settings.dt; }), "settings.dt", "--dt",
      "Substep in s (default: the largest stable one at the current speed; a value above the stable substep is "
      "refused)")
      .non_negative();
  add(field<int>([](C& c) -> int& { return c.settings.grid; }), "settings.grid", "--grid",
      "Grid cells per side of the simulation box (default 64)")
      .range(16, 512);
}

void add_force_rows(SettingRows<C>& add) {
  add(SimulationSetting::Custom{
          [](const C& c) { return vector_json(c.settings.gravity); },
          [](C& c, const json& v) { c.settings.gravity = vector_from_json(v, "--gravity"); },
          [](C& c, const std::string& t) { c.settings.gravity = parse_vector(t, "--gravity"); }},
      "settings.gravity", "--gravity", "Gravity X,Y,Z in the world frame, m/s^2 (default 9.8 against --up)");
  add(SimulationSetting::Custom{[](const C& c) { return vector_json(c.force); },
                                [](C& c, const json& v) { c.force = vector_from_json(v, "--force"); },
                                [](C& c, const std::string& t) { c.force = parse_vector(t, "--force"); }},
      "force", "--force",
      "Acceleration X,Y,Z (m/s^2, world frame) on the object during --force-frames (default: --push along the first "
      "view's right, across up)");
  add(field<double>([](C& c) -> double& { return c.push; }), "push", "--push",
      "Size of the default force in m/s^2 (default 10; 0 = none)")
      .non_negative();
  add(SimulationSetting::Custom{
          [](const C& c) { return json::array({c.force_frames.first, c.force_frames.second}); },
          [](C& c, const json& v) {
            const std::vector<int> f = v.get<std::vector<int>>();
            if (f.size() != 2 || f[0] < 0 || f[1] < f[0])
              throw std::invalid_argument("--force-frames: give A:B with 0 <= A <= B (frames A to B-1)");
            c.force_frames = {f[0], f[1]};
          },
          [](C& c, const std::string& t) { c.force_frames = parse_frames(t); }},
      "force_frames", "--force-frames", "Frames A:B (A to B-1) during which the force acts (default 0:3)");
}

void add_ground_rows(SettingRows<C>& add) {
  add(SimulationSetting::Custom{[](const C& c) { return vector_json(c.settings.up); },
                                [](C& c, const json& v) { c.settings.up = vector_from_json(v, "--up"); },
                                [](C& c, const std::string& t) { c.settings.up = parse_vector(t, "--up"); }},
      "settings.up", "--up", "Up direction X,Y,Z in the world (default: the cameras' mean up)");
  add(SimulationSetting::Custom{
          [](const C& c) { return c.settings.ground ? json(*c.settings.ground) : json(nullptr); },
          [](C& c, const json& v) {
            c.settings.ground = v.is_null() ? std::nullopt : std::optional<double>(v.get<double>());
          },
          [](C& c, const std::string& t) { c.settings.ground = std::stod(t); }},  // the flag's check read it
      "settings.ground", "--ground",
      "Height of the ground plane along up, world units (default: the surface the SfM points show under the object)")
      .range(-1e9, 1e9)
      .shown_as("FLOAT");
  add(field<double>([](C& c) -> double& { return c.settings.friction; }), "settings.friction", "--friction",
      "Coulomb friction of the ground plane (default 0.5; 0: things slide on it freely)")
      .non_negative();
  add(field<double>([](C& c) -> double& { return c.settings.damping; }), "settings.damping", "--damping",
      "Drag on the motion, per second (default 0: none; e.g. 30 lets a pile creep to rest without inertia)")
      .non_negative();
  add(field<double>([](C& c) -> double& { return c.settings.object_size; }), "settings.object_size", "--object-size",
      "The object's largest side in the simulation's metres (default 0.4; the box is 1 m across)")
      .range(1e-6, 0.8);
  add(field<float>([](C& c) -> float& { return c.settings.min_opacity; }), "settings.min_opacity", "--min-opacity",
      "Gaussians at or below this opacity stay out of the simulation (default 0.02)")
      .range(0, 0.999999);
}

// The materials' other constants and the frame time: no flag (--density
// sets both densities, --fps the frame time).
void add_library_rows(SettingRows<C>& add) {
  add(field<double>([](C& c) -> double& { return c.settings.frame_time; }), "settings.frame_time", "",
      "Simulated seconds per frame (1 / fps)")
      .positive();
  add(SimulationSetting::Custom{
          [](const C& c) { return json(material_name(c.settings.object.kind)); },
          [](C& c, const json& v) { c.settings.object.kind = parse_material(v.get<std::string>()); }, nullptr},
      "settings.object.kind", "", "The object's material (--material)");
  add(SimulationSetting::Custom{
          [](const C& c) { return json(material_name(c.settings.background.kind)); },
          [](C& c, const json& v) { c.settings.background.kind = parse_material(v.get<std::string>()); }, nullptr},
      "settings.background.kind", "", "The other Gaussians' material (metal: von Mises plasticity)");
  add(field<double>([](C& c) -> double& { return c.settings.background.density; }), "settings.background.density",
      "", "The other Gaussians' density, kg/m^3 (--density)")
      .positive();
  add(field<double>([](C& c) -> double& { return c.settings.object.yield_stress; }), "settings.object.yield_stress",
      "", "Metal, plasticine: von Mises yield stress in Pa (0 = E / 100)")
      .non_negative();
  add(field<double>([](C& c) -> double& { return c.settings.background.yield_stress; }),
      "settings.background.yield_stress", "", "The same for the other Gaussians")
      .non_negative();
  add(field<double>([](C& c) -> double& { return c.settings.object.friction_deg; }), "settings.object.friction_deg",
      "", "Sand: the friction angle in degrees")
      .range(0, 89);
  add(field<double>([](C& c) -> double& { return c.settings.background.friction_deg; }),
      "settings.background.friction_deg", "", "The same for the other Gaussians")
      .range(0, 89);
  add(field<double>([](C& c) -> double& { return c.settings.object.softening; }), "settings.object.softening", "",
      "Plasticine: the yield stress is divided by 1 + softening * plastic strain")
      .non_negative();
  add(field<double>([](C& c) -> double& { return c.settings.background.softening; }),
      "settings.background.softening", "", "The same for the other Gaussians")
      .non_negative();
}

std::vector<SimulationSetting> build_table() {
  SettingRows<C> add;
  add_material_rows(add);
  add_time_rows(add);
  add_force_rows(add);
  add_ground_rows(add);
  add_library_rows(add);
  return add.t;
}

}  // namespace

const std::vector<SimulationSetting>& simulation_settings() {
  static const std::vector<SimulationSetting> table = build_table();
  return table;
}

}  // namespace ag2gs
