// simulate: select an object as `query` does, let it move in an MLS-MPM
// simulation (apps/simulation/simulate.h) and write the frames each view
// shows, PLYs and simulation.json (docs/design.md, "Physics").

#include <spdlog/spdlog.h>

#include <chrono>
#include <cmath>
#include <filesystem>
#include <memory>
#include <nlohmann/json.hpp>
#include <sstream>
#include <string>

#include "apps/simulation/simulate.h"
#include "apps/simulation/simulation_settings.h"
#include "cli/commands.h"
#include "cli/object_selection.h"
#include "cli/run_driver.h"
#include "cli/run_guard.h"
#include "cli/setting_options.h"
#include "host/device/cl_runtime.h"
#include "host/io/atomic_file.h"
#include "host/io/avi_writer.h"
#include "host/io/image_io.h"
#include "host/io/ply_io.h"
#include "host/scene/scene.h"

namespace fs = std::filesystem;

namespace ag2gs::cli {
namespace {

struct SimulateArgs {
  ObjectArgs obj;
  std::string views;
  int ply_every = 10;
  SimulationRequest req;  // with the library's defaults, which are the program's; flags set its fields
};

// The views to render: --views names (image names or stems), else the
// first training view.
std::vector<int> render_views(const Scene& scene, const std::string& list, const std::string& scene_dir) {
  if (list.empty()) return {scene.train_views().at(0)};
  std::vector<int> views;
  std::stringstream vs(list);
  std::string name;
  while (std::getline(vs, name, ',')) {
    int found = -1;
    for (const SceneView& v : scene.views())
      if (v.name == name || v.stem == name) found = v.index;
    if (found < 0)
      throw std::invalid_argument("--views: no view named '" + name + "' in " + scene_dir +
                                  " (give image names or stems, e.g. " + scene.views()[0].stem + ")");
    views.push_back(found);
  }
  return views;
}

// The request's fields from the flags that are not its own.
void fold_flags(SimulateArgs& a) {
  SimulationSettings& ss = a.req.settings;
  ss.background.density = ss.object.density;  // --density is every material's
  ss.frame_time = 1.0 / a.req.fps;
}

void cmd_simulate(const GlobalOptions& global, SimulateArgs a) {
  const auto t_start = std::chrono::steady_clock::now();
  // ---- everything that can be checked before any work
  check_selection_request(a.obj.request, a.obj.selection);
  a.obj.config.validate();
  fold_flags(a);
  SimulationRequest& req = a.req;
  req.validate();
  const fs::path out = check_new_output_folder(a.obj.out, a.obj.model);

  const OpenedModel opened =
      open_model_and_scene(a.obj.model, a.obj.scene, a.obj.resolution, a.obj.sparse, a.obj.request, a.obj.selection);
  const TrainedModel& tm = opened.tm;
  const Scene* scene = opened.scene.get();
  req.views = render_views(*scene, a.views, a.obj.scene);

  Runtime rt(global.device);
  nlohmann::json report;
  const SelectedObject sel = select_object(rt, opened, a.obj, report, "simulate");
  req.object = object_in_model(opened, sel);

  InterruptGuard interrupts;
  StagedFolder staged(out, a.obj.out);
  const fs::path& tmp = staged.path();
  // a/1.jpg and b/1.jpg: frames/a_1/ and frames/b_1/.
  std::vector<std::string> names;
  for (int v : req.views) names.push_back(scene->views()[v].name);
  const std::vector<std::string> stems = output_stems(names);
  std::vector<std::unique_ptr<MjpegAviWriter>> videos;
  for (size_t i = 0; i < req.views.size(); ++i) {
    const Camera& cam = scene->views()[req.views[i]].camera;
    fs::create_directories(tmp / "frames" / stems[i]);
    videos.push_back(std::make_unique<MjpegAviWriter>((tmp / "frames" / (stems[i] + ".avi")).string(), cam.width,
                                                      cam.height, req.fps));
  }
  if (a.ply_every > 0) fs::create_directories(tmp / "ply");
  char name[32];
  req.on_render = [&](int f, size_t i, const RenderOutput& o) {
    std::snprintf(name, sizeof name, "%04d.png", f);
    write_rgb_png((tmp / "frames" / stems[i] / name).string(), o.rgb, o.width, o.height);
    videos[i]->write_rgb(o.rgb);
  };
  req.on_frame = [&](int f, Simulation& sim) {
    if (a.ply_every > 0 && f % a.ply_every == 0) {
      std::snprintf(name, sizeof name, "frame_%04d.ply", f);
      write_ply((tmp / "ply" / name).string(), sim.gaussians(Eigen::Vector3d::Zero(), false), true,
                PlyValues::activated);
    }
  };
  req.check_stop = [&](const std::string& during) { staged.stop_if_interrupted(during); };
  const SimulationResult result = simulate_object(rt, req);
  for (auto& v : videos) v->close();
  report.update(result.report);
  report["views"] = nlohmann::json::array();
  for (int v : req.views) report["views"].push_back(scene->views()[v].name);
  report["ply_every"] = a.ply_every;
  report["seconds"] = {{"query", sel.query_ms / 1000.0},
                       {"simulation", result.simulate_s},
                       {"total", std::chrono::duration<double>(std::chrono::steady_clock::now() - t_start).count()}};
  AtomicFile jf((tmp / "simulation.json").string());
  jf.write(report.dump(2) + "\n");
  jf.commit();
  staged.commit();
  spdlog::info("wrote {}: frames/ ({} views x {} frames), {}simulation.json ({:.1f} s simulating, {} substeps)",
               a.obj.out, req.views.size(), req.frames + 1, a.ply_every > 0 ? "ply/, " : "", result.simulate_s,
               result.substeps);
}

}  // namespace

void register_simulate(CLI::App& app, GlobalOptions& global) {
  auto a = std::make_shared<SimulateArgs>();
  auto* r = app.add_subcommand("simulate",
                               "Simulate a selected object (by a click or by text) with MLS-MPM and render the scene "
                               "as it moves; writes frames, PLYs and simulation.json to a new folder");
  add_object_options(r, a->obj, "Simulate", "New folder for frames/, ply/ and simulation.json");
  add_setting_options(r, simulation_settings(), a->req);
  r->add_option("--views", a->views,
                "Views to render, comma-separated names or stems (default: the first training view)");
  r->add_option("--ply-every", a->ply_every, "Write ply/frame_NNNN.ply every K frames (default 10; 0 = none)")
      ->check(CLI::Range(0, 100000));
  auto print_config = add_print_config_flag(r, "simulate with");
  set_action(r, [&global, a, print_config] {
    if (*print_config) {
      fold_flags(*a);
      return print_config_json(a->req);
    }
    cmd_simulate(global, *a);
  });
}

}  // namespace ag2gs::cli
