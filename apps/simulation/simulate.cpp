#include "apps/simulation/simulate.h"

#include <spdlog/spdlog.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <optional>
#include <stdexcept>

#include "apps/backdrop.h"
#include "apps/removal/fill.h"  // hidden_anchors
#include "apps/simulation/simulation_settings.h"
#include "host/core/timing.h"
#include "host/render/renderer.h"
#include "host/scene/scene_up.h"
#include "train/train_common.h"

namespace ag2gs {
namespace {

// The default push: along the first rendered view's right, across up; for a
// photo stored sideways (its x axis nearer up than its y axis), the right of
// the photo turned upright: forward x up.
std::optional<Eigen::Vector3d> default_push(const SimulationRequest& req, const std::vector<Camera>& cameras) {
  const Scene& scene = *req.object.scene;
  const std::optional<Eigen::Vector3d>& given_up = req.settings.up;
  const Eigen::Vector3d up = given_up ? given_up->normalized() : scene_up(cameras, scene.points()).up;
  const Camera& cam = scene.views()[req.views[0]].camera;
  const Eigen::Vector3d right = cam.R.row(0).transpose(), down = cam.R.row(1).transpose();
  const Eigen::Vector3d across = std::abs(right.dot(up)) <= std::abs(down.dot(up))
                                     ? Eigen::Vector3d(right - right.dot(up) * up)
                                     : Eigen::Vector3d(cam.R.row(2).transpose().cross(up));
  if (across.norm() > 1e-6) return req.push * across.normalized();
  return std::nullopt;
}

nlohmann::json frame_json(const SimFrameStats& s) {
  auto arr = [](const std::array<double, 3>& v) { return nlohmann::json::array({v[0], v[1], v[2]}); };
  return nlohmann::json{{"frame", s.frame},
                        {"time", s.time},
                        {"substeps", s.substeps},
                        {"wall_seconds", s.wall_s},
                        {"kinetic_energy", s.all.kinetic},
                        {"momentum", arr(s.all.momentum)},
                        {"object_kinetic_energy", s.object.kinetic},
                        {"object_momentum", arr(s.object.momentum)},
                        {"object_centre_of_mass", arr(s.object_centre)},
                        {"max_strain", s.all.max_strain},
                        {"object_max_strain", s.object.max_strain}};
}

void check_request(const SimulationRequest& req) {
  req.object.check("simulate_object");
  if (req.views.empty()) throw std::invalid_argument("simulate_object: no view to render");
  for (int v : req.views)
    if (v < 0 || static_cast<size_t>(v) >= req.object.scene->views().size())
      throw std::invalid_argument("simulate_object: view index " + std::to_string(v) + " out of range");
  req.validate();
}

}  // namespace

void SimulationRequest::validate() const {
  if (const std::string p = settings_problem(simulation_settings(), *this); !p.empty()) throw std::invalid_argument(p);
  if (force_frames.first < 0 || force_frames.second < force_frames.first)
    throw std::invalid_argument("--force-frames: give A:B with 0 <= A <= B (frames A to B-1)");
  SimulationSettings ss = settings;
  ss.frame_time = 1.0 / fps;
  ss.validate();
}

nlohmann::json SimulationRequest::to_json() const {
  return settings_to_json(simulation_settings(), *this);
}

SimulationResult simulate_object(Runtime& rt, const SimulationRequest& req) {
  check_request(req);
  const Scene& scene = *req.object.scene;
  const int K = req.object.model->children();
  const GaussianSet gaussians = expand_reference(*req.object.model, req.object.sh_degree);
  std::vector<Camera> cameras;
  for (int v : scene.train_views()) cameras.push_back(scene.views()[v].camera);
  SimulationResult out;
  nlohmann::json& report = out.report;
  // Kept anchors inside the object that the photos saw only through it (as
  // `remove` takes them): left in place they would show where the object
  // stood once it moves.
  std::vector<int> hidden;
  if (req.move_hidden) {
    Renderer seen_renderer(rt);
    hidden = hidden_anchors(seen_renderer, *req.object.model, req.object.sh_degree, req.object.selected, cameras,
                            RenderSettings{});
    if (!hidden.empty())
      spdlog::info("{} kept anchors inside the object are seen only through it: they move with it", hidden.size());
  }
  report["hidden_anchors_moved"] = hidden;
  std::vector<uint8_t> in_object = req.object.selected;
  for (int h : hidden) in_object[h] = 1;
  std::vector<uint8_t> selected(gaussians.size(), 0);
  for (size_t g = 0; g < selected.size(); ++g) selected[g] = in_object[g / K];
  SimulationSettings ss = req.settings;
  ss.frame_time = 1.0 / req.fps;
  if (req.force) {
    ss.force = *req.force;
  } else if (const std::optional<Eigen::Vector3d> push = default_push(req, cameras)) {
    ss.force = *push;
  }
  const size_t count =
      static_cast<size_t>(std::count(req.object.selected.begin(), req.object.selected.end(), uint8_t{1}));
  spdlog::info("selected {} of {} anchors ({} Gaussians) to simulate as {}", count, req.object.model->size(),
               count * static_cast<size_t>(K), req.material);
  Simulation sim(rt, gaussians, selected, cameras, scene.points(), ss);
  const double dt_rest = sim.describe()["max_stable_dt_at_rest"].get<double>();
  spdlog::info(
      "simulation: {} particles ({} of the object's Gaussians, {} filling its solid, {}), grid {}^3, up ({:.3f}, "
      "{:.3f}, {:.3f}), ground at {:.4g}; stable substep at rest {:.3g} s",
      sim.particles(), sim.object_gaussians(), sim.fill_particles(),
      ss.with_background ? fmt::format("{} background Gaussians", sim.background_gaussians())
                         : std::string("the rest of the scene still"),
      ss.grid, sim.frame().up(0), sim.frame().up(1), sim.frame().up(2), sim.frame().ground_world, dt_rest);
  // The substeps the run needs at least (the stable substep only shrinks as
  // things move): refuse up front what would run for hours or days.
  const double fps = req.fps;
  const double step = sim.dt() > 0 ? sim.dt() : dt_rest;
  const double least = req.frames / fps / step;
  if (!(least <= req.max_substeps))
    throw std::invalid_argument(fmt::format(
        "simulate: {} frames at {} fps need at least {:.3g} substeps of {:.3g} s (the stable substep of --E {:g} "
        "on a grid of {}); more than --max-substeps {:g}: lower --E, simulate fewer --frames, use a coarser "
        "--grid, or raise --max-substeps",
        req.frames, fps, least, step, ss.object.E, ss.grid, req.max_substeps));

  ModelBackdrop look(rt, *req.object.archive, req.object.model_file, "rendering over a black background");
  RenderSettings rs = look.settings;
  rs.features = false;
  Renderer renderer(rt);
  auto render_frame = [&](int f) {
    for (size_t i = 0; i < req.views.size(); ++i) {
      const Camera& cam = scene.views()[req.views[i]].camera;
      const GaussianSet g = sim.gaussians(cam.center());
      RenderOutput o = renderer.render(g, cam, rs);
      if (look.sky.enabled()) composite_sky(renderer, look.sky, cam, o);
      if (req.on_render) req.on_render(f, i, o);
    }
    if (req.on_frame) req.on_frame(f, sim);
  };
  nlohmann::json frames = nlohmann::json::array();
  frames.push_back(frame_json(sim.stats()));
  render_frame(0);
  for (int f = 1; f <= req.frames; ++f) {
    // Frame f covers the substeps from frame f-1 to f: the force acts in
    // frames [A, B) of force_frames.
    const bool forces_on = f - 1 >= req.force_frames.first && f - 1 < req.force_frames.second;
    const SimFrameStats st = sim.advance(forces_on);
    out.simulate_s += st.wall_s;
    out.substeps += st.substeps;
    render_frame(f);
    frames.push_back(frame_json(st));
    spdlog::info(
        "frame {:3d}/{}  {} substeps of {:.3g} s{}  kinetic {:.4g} J  object centre ({:.4g}, {:.4g}, {:.4g})  max "
        "|F - I| {:.3g}  {:.2f} s  ETA {}",
        f, req.frames, st.substeps, sim.dt(), forces_on ? "  force on" : "", st.all.kinetic, st.object_centre[0],
        st.object_centre[1], st.object_centre[2], st.all.max_strain, st.wall_s,
        fmt_duration(out.simulate_s / f * (req.frames - f)));
    if (req.check_stop) req.check_stop("the simulation");
  }
  report["simulation"] = sim.describe();
  report["material"] = req.material;
  report["frames"] = req.frames;
  report["fps"] = fps;
  report["force_frames"] = {req.force_frames.first, req.force_frames.second};
  report["dt"] = ss.dt > 0 ? nlohmann::json(ss.dt) : nlohmann::json("automatic");
  report["substeps"] = out.substeps;
  report["per_frame"] = frames;
  return out;
}

}  // namespace ag2gs
