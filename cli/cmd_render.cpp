// render: a trained model (or a 3DGS .ply) from a scene's COLMAP cameras:
// RGB, depth, alpha, features and instance ids per view.
#include <spdlog/spdlog.h>

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <memory>
#include <sstream>

#include "cli/commands.h"
#include "cli/model_render.h"
#include "cli/render_colours.h"
#include "cli/run_guard.h"
#include "host/device/cl_runtime.h"
#include "host/io/colmap_reader.h"
#include "host/io/image_io.h"
#include "host/io/json_input.h"
#include "host/io/model_ply.h"
#include "host/io/npy_io.h"
#include "host/io/output_set.h"
#include "host/render/sky.h"
#include "host/scene/scene.h"

namespace fs = std::filesystem;

namespace ag2gs::cli {
namespace {

struct RenderArgs {
  std::string model, ply, scene, out, views, outputs = "rgb", bg = "0,0,0", sparse;
  bool bg_given = false;  // --bg on the command line (else a model's sky, when it has one)
  int resolution = 0;  // 0 = the resolution the model was trained at (1 for a bare .ply)
  bool extras = false;
  bool drop_invalid = false;  // --drop-invalid: leave out Gaussians with invalid numbers
  bool force = false;         // --force: replace the renders already in OUT
};

std::array<float, 3> parse_rgb(const std::string& s) {
  std::array<float, 3> v{};
  std::stringstream ss(s);
  std::string item;
  int i = 0;
  while (std::getline(ss, item, ',')) {
    if (i >= 3) throw std::invalid_argument("--bg '" + s + "': more than three numbers; expected R,G,B in [0,1], e.g. 1,1,1");
    try {
      size_t used = 0;
      v[i] = std::stof(item, &used);
      if (used != item.size()) throw std::invalid_argument(item);
    } catch (const std::exception&) {
      throw std::invalid_argument("--bg '" + s + "': '" + item +
                                  "' is not a number; expected R,G,B in [0,1], e.g. 1,1,1");
    }
    if (!(v[i] >= 0.f && v[i] <= 1.f))
      throw std::invalid_argument("--bg '" + s + "': '" + item + "' is outside [0,1]; expected R,G,B in [0,1], e.g. 1,1,1");
    ++i;
  }
  if (i != 3) throw std::invalid_argument("--bg '" + s + "': expected three numbers R,G,B in [0,1], e.g. 1,1,1");
  return v;
}

// --views: train | test (every 8th image in name order, as --eval holds out) | all | names.
std::vector<Camera> pick_views(const std::vector<Camera>& all, const std::string& views) {
  if (views.empty() || views == "all") return all;
  if (views == "train" || views == "test") {
    std::vector<Camera> out;
    for (size_t i = 0; i < all.size(); ++i) {
      if ((i % 8 == 0) == (views == "test")) out.push_back(all[i]);
    }
    return out;
  }
  return select_views(all, views);
}

// The -r to render at and why: an explicit -r, else the one the model was
// trained at (model.ag2gs meta "train"/"resolution", or metrics.json of a
// baseline trained with --eval) in `model_dir`, else 1.
std::pair<int, std::string> render_resolution(int given, const std::string& model_dir) {
  if (given > 0) return {given, "-r " + std::to_string(given) + " given"};
  const fs::path mf = fs::path(model_dir) / "model.ag2gs", metrics = fs::path(model_dir) / "metrics.json";
  // A recorded -r out of range is an error (recorded_resolution); a file that
  // cannot be read at all only loses the record.
  if (!model_dir.empty() && fs::exists(mf)) {
    nlohmann::json train;
    try {
      train = read_model_meta(mf.string()).value("train", nlohmann::json::object());
    } catch (const std::exception& e) {
      spdlog::warn("{}; its training -r is unknown", e.what());
    }
    if (train.contains("resolution")) {
      const int r = recorded_resolution(train, mf.string());
      return {r, "the model was trained at -r " + std::to_string(r) + " (" + mf.string() + "); -r overrides"};
    }
  }
  if (!model_dir.empty() && fs::exists(metrics)) {
    nlohmann::json j;
    try {
      j = read_json_file(metrics.string());
    } catch (const std::exception& e) {
      spdlog::warn("{}: not readable ({}); rendering at full resolution", metrics.string(), e.what());
    }
    if (j.is_object() && j.contains("resolution")) {
      const int r = recorded_resolution(j, metrics.string());
      return {r, "the model was trained at -r " + std::to_string(r) + " (" + metrics.string() + "); -r overrides"};
    }
  }
  return {1, "no record of the training -r beside the Gaussians (-r R divides the cameras by R)"};
}

void cmd_render(const GlobalOptions& global, const RenderArgs& a) {
  if (a.resolution < 0) throw std::invalid_argument("-r must be >= 1 (it divides the camera resolution)");
  std::vector<std::string> outputs = split_list(a.outputs);
  if (a.extras) {
    for (const char* o : {"depth", "alpha"}) {
      if (std::find(outputs.begin(), outputs.end(), o) == outputs.end()) outputs.push_back(o);
    }
  }
  check_render_outputs(outputs, "--outputs");
  auto wants = [&](const char* o) { return std::find(outputs.begin(), outputs.end(), o) != outputs.end(); };
  ModelRenderOptions mo;
  mo.model = a.model;
  mo.ply = a.ply;
  mo.outputs = outputs;
  if (a.bg_given) mo.background = parse_rgb(a.bg);
  mo.drop_invalid = a.drop_invalid;
  // Checks the model or the .ply before the scene, on its own device queue.
  Runtime rt(global.device);
  ModelRender model_render(rt, mo);
  const std::string& ply = model_render.ply();
  if (!fs::is_directory(a.scene))
    throw std::runtime_error(a.scene +
                             ": no such scene directory; --scene names the folder holding the COLMAP model "
                             "(sparse/0/ or sparse/)");
  const std::string sparse = find_colmap_model(a.scene, a.sparse);
  refuse_output_in_inputs(a.out, a.scene, {a.model}, "-o");
  refuse_file_as_output_folder(a.out, "-o");
  finish_interrupted_output_sets(a.out);  // a killed run's last commit, finished
  ColmapModel model = read_colmap_model(sparse);
  std::vector<Camera> cams = pick_views(model.cameras_for_images, a.views);
  if (cams.empty()) throw std::runtime_error(sparse + " has no views to render for --views '" + a.views + "'");
  // A model folder: the one given, or the folder of a --ply written by `ag2gs train`.
  const auto [resolution, why] =
      render_resolution(a.resolution, !a.model.empty() ? a.model : fs::path(ply).parent_path().string());
  spdlog::info("cameras from {}; rendering at 1/{} resolution: {}", sparse, resolution, why);

  spdlog::info("device [{}] {}; {} Gaussians (SH degree {}), {} views", rt.info().index, rt.info().name,
               model_render.gaussians(), model_render.sh_degree(), cams.size());
  if (model_render.has_sky()) spdlog::info("rgb over the model's learned sky; --bg R,G,B for a fixed background");
  fs::path out_dir(a.out);
  std::vector<std::string> names;
  for (const Camera& c : cams) names.push_back(c.name);
  const std::vector<std::string> stems = output_stems(names);
  std::vector<std::string> files;  // what this run writes, inside OUT
  for (const std::string& o : outputs)
    for (const std::string& stem : stems)
      for (const char* ext : {".png", ".npy"}) files.push_back(o + "/" + stem + ext);
  refuse_existing_results("-o", a.out, files, a.force);
  for (const std::string& o : outputs) fs::create_directories(out_dir / o);
  // Every file of this run goes into place at the end, together: a run
  // stopped midway leaves the earlier results (with --force) as they were.
  OutputSet written(a.out);
  auto t0 = std::chrono::steady_clock::now();
  for (size_t i = 0; i < cams.size(); ++i) {
    Camera cam = scale_camera(cams[i], resolution);
    const ModelFrame out = model_render.render(cam);
    const std::string& stem = stems[i];
    const int w = out.width, h = out.height;
    auto file = [&](const char* o, const char* ext) { return (out_dir / o / (stem + ext)).string(); };
    if (wants("rgb")) write_rgb_png(file("rgb", ".png"), out.rgb, w, h);
    if (wants("depth")) {
      write_gray16_png(file("depth", ".png"), out.depth, w, h, 1000.f);
      write_npy(file("depth", ".npy"), out.depth, {h, w});
    }
    if (wants("alpha")) {
      write_gray16_png(file("alpha", ".png"), out.alpha, w, h, 65535.f);
      write_npy(file("alpha", ".npy"), out.alpha, {h, w});
    }
    if (wants("feature")) {
      write_rgb_png(file("feature", ".png"), feature_colours(out.feature, out.alpha), w, h);
      write_npy(file("feature", ".npy"), out.feature, {h, w, 3});
    }
    if (wants("instance")) {
      write_rgb_png(file("instance", ".png"), instance_colours(out.instance), w, h);
      write_npy(file("instance", ".npy"), std::vector<float>(out.instance.begin(), out.instance.end()), {h, w});
    }
    const double el = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    const double eta = el / (i + 1) * (cams.size() - i - 1);
    spdlog::info("[{}/{}] {} {}x{}  {} intersections  {:.1f} s elapsed, ETA {:.1f} s", i + 1, cams.size(), cam.name, w,
                 h, out.intersections, el, eta);
  }
  written.commit();
  const double total = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  spdlog::info("wrote {} views x {} outputs to {} ({:.2f} views/s)", cams.size(), outputs.size(), out_dir.string(),
               cams.size() / std::max(total, 1e-9));
}

}  // namespace

void register_render(CLI::App& app, GlobalOptions& global) {
  auto ra = std::make_shared<RenderArgs>();
  auto* render = app.add_subcommand("render", "Render a trained model (or a 3DGS .ply) from a scene's COLMAP cameras");
  render->add_option("model", ra->model, "Model folder written by `ag2gs train` (uses MODEL_DIR/point_cloud.ply)");
  render->add_option("--ply", ra->ply, "Instead of MODEL_DIR: Gaussians in the standard 3DGS point_cloud.ply layout");
  render->add_option("--scene", ra->scene, "Scene directory holding the COLMAP model (sparse/0/, or sparse/ itself)")
      ->required();
  render->add_option("-o,--out", ra->out, "Output directory: OUT/<output>/<image stem>.png (+ .npy for floats)")
      ->check(output_path())
      ->required();
  render->add_option("--views", ra->views,
                     "train, test (every 8th image, as --eval), all (default), or comma-separated names/stems");
  render->add_option("--outputs", ra->outputs,
                     "Comma-separated: rgb (default), depth, alpha, feature, instance (cluster ids; needs stage 3)");
  render->add_option("--bg", ra->bg,
                     "Fixed background colour R,G,B in [0,1] (default: the model's learned sky when it has one, "
                     "else 0,0,0)");
  render->add_option("-r,--resolution", ra->resolution,
                     "Divide the camera resolution by R (default: the model's training -r, from model.ag2gs or "
                     "metrics.json; 1 for a .ply with neither beside it)")
      ->check(CLI::Range(1, 64));
  render->add_option("--sparse", ra->sparse,
                     "COLMAP model folder inside the scene (default sparse/0/, else sparse/ when it holds the model)");
  render->add_flag("--extras", ra->extras, "Same as adding depth,alpha to --outputs");
  render->add_flag("--force", ra->force,
                   "Replace the renders OUT already holds (default: refused, so a rerun with other settings does not "
                   "overwrite earlier results)");
  render->add_flag("--drop-invalid", ra->drop_invalid,
                   "Leave out Gaussians with non-finite numbers, zero rotations, scales <= 0 or opacities outside "
                   "[0, 1] (default: such a .ply is refused)");
  set_action(render, [&global, ra, render] {
    ra->bg_given = render->count("--bg") > 0;
    cmd_render(global, *ra);
  });

}

}  // namespace ag2gs::cli
