// simulate: select an object as `query` does, let it move in an MLS-MPM
// simulation (apps/simulation/simulate.h) and write the frames each view
// shows, PLYs and simulation.json (docs/design.md, "Physics").

#include <spdlog/spdlog.h>

#include <chrono>
#include <cmath>
#include <filesystem>
#include <memory>
#include <nlohmann/json.hpp>
#include <opencv2/imgproc.hpp>
#include <opencv2/videoio.hpp>
#include <sstream>
#include <string>

#include "apps/simulation/simulate.h"
#include "cli/commands.h"
#include "cli/object_selection.h"
#include "cli/run_driver.h"
#include "cli/run_guard.h"
#include "host/device/cl_runtime.h"
#include "host/io/atomic_file.h"
#include "host/io/image_io.h"
#include "host/io/ply_io.h"
#include "host/scene/scene.h"

namespace fs = std::filesystem;

namespace ag2gs::cli {
namespace {

struct SimulateArgs {
  QueryRequest request;
  QueryConfig config;
  std::string model, scene, selection, out, sparse;
  std::string material = "jelly";
  // E: the paper's 2e8 needs 5,600 substeps per frame at grid 64 (the
  // elastic wave crosses a cell in 7e-6 s): 46-66 s a frame, 25-33 minutes
  // for 30 frames on 2 CPU cores. 2e6, the paper's background stiffness,
  // takes about 570 substeps (docs/benchmarks.md, "Physics").
  double E = 2e6, nu = 0.4, density = 1000;
  double background_E = 2e6, background_nu = 0.3;
  // The rest of the scene in the box as particles: off by default. On the
  // seed-1 mug it made the thin pole and the box on it sag under gravity
  // (|F - I| up to 2.8): a pole a Gaussian or two thick is too few
  // particles per cell for the solver (docs/benchmarks.md, "Physics").
  bool background = false;
  bool move_hidden = true;  // kept anchors the object hid from every photo move with it
  int frames = 30;
  double fps = 25;
  double max_substeps = 2e6;  // refused above: a stiffness whose stable substep is tiny runs for days
  double dt = 0;
  int grid = 64;
  std::string gravity, force, force_frames = "0:3", up;
  std::optional<double> ground;
  double object_size = 0.4;
  double friction = 0.5;
  double damping = 0;
  double push = 10;
  std::string views;
  int ply_every = 10;
  int resolution = 0;
  float min_opacity = 0.02f;
};

// "X,Y,Z" -> a vector; throws naming the flag.
Eigen::Vector3d parse_vector(const std::string& text, const std::string& flag) {
  std::stringstream ss(text);
  Eigen::Vector3d v;
  char comma = 0;
  if (!(ss >> v(0) >> comma) || comma != ',' || !(ss >> v(1) >> comma) || comma != ',' || !(ss >> v(2)) || !ss.eof() ||
      !v.allFinite())
    throw std::invalid_argument(flag + " " + text + ": give three numbers as X,Y,Z");
  return v;
}

// "A:B" -> [A, B): the frames whose substeps the force acts in.
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

// The views to render: --views names (image names or stems), else the
// first training view.
std::vector<int> render_views(const Scene& scene, const std::string& list, const std::string& scene_dir) {
  std::vector<int> views;
  if (list.empty()) return {scene.train_views().at(0)};
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

void cmd_simulate(const GlobalOptions& global, SimulateArgs a) {
  const auto t_start = std::chrono::steady_clock::now();
  // ---- everything that can be checked before any work
  check_selection_request(a.request, a.selection);
  a.config.validate();
  SimulationRequest req;
  SimulationSettings& ss = req.settings;
  ss.object.kind = parse_material(a.material);
  ss.object.E = a.E;
  ss.object.nu = a.nu;
  ss.object.density = a.density;
  ss.background.kind = MaterialKind::kMetal;  // von Mises plasticity (the paper's background)
  ss.background.E = a.background_E;
  ss.background.nu = a.background_nu;
  ss.background.density = a.density;
  ss.with_background = a.background;
  ss.grid = a.grid;
  ss.frame_time = 1.0 / a.fps;
  ss.dt = a.dt;
  if (!a.gravity.empty()) ss.gravity = parse_vector(a.gravity, "--gravity");
  if (!a.up.empty()) ss.up = parse_vector(a.up, "--up");
  ss.ground = a.ground;
  ss.object_size = a.object_size;
  ss.friction = a.friction;
  ss.damping = a.damping;
  ss.min_opacity = a.min_opacity;
  if (!a.force.empty()) req.force = parse_vector(a.force, "--force");
  req.force_frames = parse_frames(a.force_frames);
  if (!(a.fps > 0) || !std::isfinite(a.fps)) throw std::invalid_argument("--fps must be a number > 0");
  ss.validate();
  const fs::path out = check_new_output_folder(a.out, a.model);

  const OpenedModel opened = open_model_and_scene(a.model, a.scene, a.resolution, a.sparse, a.request, a.selection);
  const TrainedModel& tm = opened.tm;
  const Scene* scene = opened.scene.get();
  req.views = render_views(*scene, a.views, a.scene);

  Runtime rt(global.device);
  nlohmann::json report;
  report["model"] = tm.file;
  report["scene"] = a.scene;
  report["resolution"] = a.resolution;
  const SelectedObject sel = select_object(rt, tm, *scene, a.request, a.selection, a.config, opened.embedding,
                                           a.resolution, report, "simulate");
  req.object = object_in_model(opened, sel);
  req.push = a.push;
  req.move_hidden = a.move_hidden;
  req.frames = a.frames;
  req.fps = a.fps;
  req.max_substeps = a.max_substeps;
  req.material = a.material;

  InterruptGuard interrupts;
  StagedFolder staged(out, a.out);
  const fs::path& tmp = staged.path();
  // a/1.jpg and b/1.jpg: frames/a_1/ and frames/b_1/.
  std::vector<std::string> names;
  for (int v : req.views) names.push_back(scene->views()[v].name);
  const std::vector<std::string> stems = output_stems(names);
  std::vector<std::unique_ptr<cv::VideoWriter>> videos;
  for (size_t i = 0; i < req.views.size(); ++i) {
    const Camera& cam = scene->views()[req.views[i]].camera;
    fs::create_directories(tmp / "frames" / stems[i]);
    auto w = std::make_unique<cv::VideoWriter>();
    w->open((tmp / "frames" / (stems[i] + ".avi")).string(), cv::CAP_OPENCV_MJPEG,
            cv::VideoWriter::fourcc('M', 'J', 'P', 'G'), a.fps, cv::Size(cam.width, cam.height));
    if (!w->isOpened()) {
      spdlog::warn("OpenCV cannot write a video here; the frames are PNG only");
      w.reset();
    }
    videos.push_back(std::move(w));
  }
  if (a.ply_every > 0) fs::create_directories(tmp / "ply");
  char name[32];
  req.on_render = [&](int f, size_t i, const RenderOutput& o) {
    std::snprintf(name, sizeof name, "%04d.png", f);
    write_rgb_png((tmp / "frames" / stems[i] / name).string(), o.rgb, o.width, o.height);
    if (videos[i]) {
      cv::Mat img(o.height, o.width, CV_32FC3, const_cast<float*>(o.rgb.data()));
      cv::Mat bgr;
      img.convertTo(bgr, CV_8UC3, 255.0);
      cv::cvtColor(bgr, bgr, cv::COLOR_RGB2BGR);
      videos[i]->write(bgr);
    }
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
  for (auto& v : videos)
    if (v) v->release();
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
  spdlog::info("wrote {}: frames/ ({} views x {} frames), {}simulation.json ({:.1f} s simulating, {} substeps)", a.out,
               req.views.size(), a.frames + 1, a.ply_every > 0 ? "ply/, " : "", result.simulate_s, result.substeps);
}

}  // namespace

void register_simulate(CLI::App& app, GlobalOptions& global) {
  auto a = std::make_shared<SimulateArgs>();
  auto* r = app.add_subcommand("simulate",
                               "Simulate a selected object (by a click or by text) with MLS-MPM and render the scene "
                               "as it moves; writes frames, PLYs and simulation.json to a new folder");
  r->add_option("model", a->model, "Model folder written by `ag2gs train` (MODEL_DIR/model.ag2gs)")->required();
  r->add_option("--scene", a->scene, "Scene directory (images/, sparse/0/) the model was trained on")->required();
  r->add_option("-o,--out", a->out, "New folder for frames/, ply/ and simulation.json")
      ->check(output_path())
      ->required();
  add_query_request_options(r, a->request);
  r->add_option("--selection", a->selection, "Simulate the anchors of a selection.json written by `ag2gs query`");
  r->add_option("--material", a->material, "The object's material: jelly (default), metal, sand or plasticine")
      ->check(CLI::IsMember({"jelly", "metal", "sand", "plasticine"}));
  r->add_option("--E", a->E,
                "The object's Young's modulus in Pa (default 2e6; the paper's 2e8 is 100x stiffer and takes 10x "
                "the substeps)")
      ->check(positive_number());
  r->add_option("--nu", a->nu, "The object's Poisson's ratio (default 0.4)");
  r->add_option("--density", a->density, "Density in kg/m^3 of every material (default 1000)")
      ->check(finite_range(0.1, 1e5));
  r->add_option("--background-E", a->background_E,
                "Young's modulus of the other Gaussians inside the simulation box (default 2e6; von Mises)")
      ->check(positive_number());
  r->add_option("--background-nu", a->background_nu, "Their Poisson's ratio (default 0.3)");
  r->add_flag("--background,!--no-background", a->background,
              "Also simulate the other Gaussians inside the simulation box above the ground, as --background-E "
              "material (the paper's setting; default off: the rest of the scene stays still)");
  r->add_flag("!--keep-hidden", a->move_hidden,
              "Leave in place the kept anchors inside the object that the training views saw only through it (by "
              "default they move with it, as `remove` takes them with it)");
  r->add_option("--frames", a->frames, "Frames to simulate (default 30; frame 0, the start, is written too)")
      ->check(CLI::Range(1, 100000));
  r->add_option("--fps", a->fps, "Frames per second of simulated time (default 25)")->check(positive_number());
  r->add_option("--max-substeps", a->max_substeps,
                "Refuse a run that needs more substeps than this (default 2e6; the cup's defaults take ~18k)")
      ->check(positive_number());
  r->add_option("--dt", a->dt,
                "Substep in s (default: the largest stable one at the current speed; a value above the stable "
                "substep is refused)")
      ->check(non_negative_number());
  r->add_option("--grid", a->grid, "Grid cells per side of the simulation box (default 64)")
      ->check(CLI::Range(16, 512));
  r->add_option("--gravity", a->gravity, "Gravity X,Y,Z in the world frame, m/s^2 (default 9.8 against --up)");
  r->add_option("--force", a->force,
                "Acceleration X,Y,Z (m/s^2, world frame) on the object during --force-frames (default: --push "
                "along the first view's right, across up)");
  r->add_option("--push", a->push, "Size of the default force in m/s^2 (default 10; 0 = none)")
      ->check(non_negative_number());
  r->add_option("--force-frames", a->force_frames, "Frames A:B (A to B-1) during which the force acts (default 0:3)");
  r->add_option("--up", a->up, "Up direction X,Y,Z in the world (default: the cameras' mean up)");
  r->add_option("--ground", a->ground,
                "Height of the ground plane along up, world units (default: the surface the SfM points show under "
                "the object)")
      ->check(finite_range(-1e9, 1e9));
  r->add_option("--friction", a->friction,
                "Coulomb friction of the ground plane (default 0.5; 0: things slide on it freely)")
      ->check(non_negative_number());
  r->add_option("--damping", a->damping,
                "Drag on the motion, per second (default 0: none; e.g. 30 lets a pile creep to rest without "
                "inertia)")
      ->check(non_negative_number());
  r->add_option("--object-size", a->object_size,
                "The object's largest side in the simulation's metres (default 0.4; the box is 1 m across)");
  r->add_option("--min-opacity", a->min_opacity,
                "Gaussians at or below this opacity stay out of the simulation (default 0.02)");
  r->add_option("--views", a->views,
                "Views to render, comma-separated names or stems (default: the first training view)");
  r->add_option("--ply-every", a->ply_every, "Write ply/frame_NNNN.ply every K frames (default 10; 0 = none)")
      ->check(CLI::Range(0, 100000));
  r->add_option("-r,--resolution", a->resolution, "Divide the cameras by R (default: the model's training -r)")
      ->check(CLI::Range(1, 64));
  r->add_option("--sparse", a->sparse,
                "COLMAP model folder inside the scene (default: sparse/0/, else sparse/ when it holds the model)");
  add_query_config_options(r, a->config);
  set_action(r, [&global, a] { cmd_simulate(global, *a); });
}

}  // namespace ag2gs::cli
