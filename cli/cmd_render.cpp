// render: a trained model (or a 3DGS .ply) from a scene's COLMAP cameras:
// RGB, depth, alpha, features and instance ids per view.
#include <spdlog/spdlog.h>

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <map>
#include <memory>
#include <optional>
#include <set>
#include <sstream>

#include "cli/commands.h"
#include "cli/render_colours.h"
#include "cli/run_guard.h"
#include "host/device/cl_runtime.h"
#include "host/io/colmap_reader.h"
#include "host/io/image_io.h"
#include "host/io/json_input.h"
#include "host/io/model_io.h"
#include "host/io/model_ply.h"
#include "host/io/npy_io.h"
#include "host/io/output_set.h"
#include "host/io/ply_io.h"
#include "host/render/renderer.h"
#include "host/render/sky.h"
#include "host/scene/scene.h"
#include "stages/anchor_model.h"
#include "stages/clustering.h"
#include "stages/instance_map.h"
#include "stages/train_common.h"

namespace fs = std::filesystem;

namespace ag2gs::cli {
namespace {

void refuse_ply_of_another_model(const std::string& ply, const GaussianSet& set, const ModelArchive& archive) {
  const AnchorModel am = AnchorModel::from_archive(archive);
  const std::string& mf = archive.source;
  const std::string fix = "; move it aside and train again, or render the file alone with --ply " + ply;
  if (set.size() != am.gaussians())
    throw std::runtime_error(ply + " holds " + std::to_string(set.size()) + " Gaussians where " + mf + " has " +
                             std::to_string(am.gaussians()) + ": it was not written from this model" + fix);
  // point_cloud(_objects).ply holds the model's expanded Gaussians row for
  // row; their means are a function of the anchors and offsets alone.
  const GaussianSet mine = expand_reference(am, 0);
  for (size_t i = 0; i < mine.means.size(); ++i)
    if (mine.means[i] != set.means[i])
      throw std::runtime_error(ply + ": Gaussian " + std::to_string(i / 3) + " lies elsewhere than in " + mf +
                               ": the file was not written from this model" + fix);
}

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

std::vector<std::string> split_list(const std::string& s) {
  std::vector<std::string> out;
  std::stringstream ss(s);
  std::string item;
  while (std::getline(ss, item, ',')) {
    item.erase(0, item.find_first_not_of(" \t"));
    item.erase(item.find_last_not_of(" \t") + 1);
    if (!item.empty()) out.push_back(item);
  }
  return out;
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
  for (const std::string& o : outputs) {
    if (o != "rgb" && o != "depth" && o != "alpha" && o != "feature" && o != "instance") {
      throw std::invalid_argument("--outputs: unknown output '" + o +
                                  "'; choose from rgb,depth,alpha,feature,instance");
    }
  }
  if (outputs.empty()) throw std::invalid_argument("--outputs is empty; choose from rgb,depth,alpha,feature,instance");
  auto wants = [&](const char* o) { return std::find(outputs.begin(), outputs.end(), o) != outputs.end(); };

  std::string ply = a.ply;
  if (!a.model.empty()) {
    if (!ply.empty()) throw std::invalid_argument("give either MODEL_DIR or --ply, not both");
    const fs::path candidate = fs::path(a.model) / "point_cloud.ply";
    if (!fs::is_directory(a.model)) {
      throw std::runtime_error(a.model + ": no such model folder (a folder written by `ag2gs train`)");
    }
    if (!fs::exists(candidate) && !wants("instance")) {
      throw std::runtime_error(a.model + ": has no point_cloud.ply; is it a model folder written by `ag2gs train`?");
    }
    // A model with a sky: its Gaussians alone, the sky composited below
    // (point_cloud.ply also holds the sky baked into Gaussians).
    ply = model_objects_ply(a.model);
  }
  if (ply.empty()) throw std::invalid_argument("give a model folder (MODEL_DIR) or a Gaussian file (--ply FILE)");

  RenderSettings settings;
  settings.background = parse_rgb(a.bg);
  // A model trained with a sky (host/render/sky.h) renders its rgb over
  // it, as training saw it, unless --bg asks for a fixed background.
  std::optional<std::vector<float>> sky_coefficients;
  std::optional<ModelArchive> model_archive;
  if (!a.model.empty() && fs::exists(fs::path(a.model) / "model.ag2gs"))
    model_archive = read_model_archive((fs::path(a.model) / "model.ag2gs").string());
  if (model_archive) check_model_archive(*model_archive);
  if (model_archive && !a.bg_given) sky_coefficients = sky_from_archive(*model_archive);
  GaussianSet set;
  // Instance maps need the anchors' clusters: the model's Gaussians are then
  // expanded from model.ag2gs (row g = anchor g / K, the same Gaussians as
  // its point_cloud.ply) instead of read from the PLY.
  std::vector<int32_t> anchor_cluster;
  int children = 0;
  if (wants("instance")) {
    if (a.model.empty())
      throw std::invalid_argument("--outputs instance needs a model folder with clusters (stage 3), not --ply");
    const std::string mf = (fs::path(a.model) / "model.ag2gs").string();
    if (!model_archive) throw std::runtime_error(a.model + ": no model.ag2gs, which --outputs instance needs");
    const ModelArchive& archive = *model_archive;
    if (!archive.meta.contains("clusters"))
      throw std::runtime_error(mf +
                               " has no clusters, which --outputs instance needs: run stage 3 "
                               "(`ag2gs train SCENE_DIR -o MODEL_DIR --stages 3`)");
    const AnchorModel am = AnchorModel::from_archive(archive);
    const nlohmann::json tr = archive.meta.value("train", nlohmann::json::object());
    const int sh = recorded_sh_degree(tr, am.config().sh_degree, mf);
    set = expand_reference(am, sh);
    anchor_cluster = clustering_from_archive(archive, am.size()).anchor_cluster;
    children = am.config().children;
  } else {
    size_t dropped = 0;
    set = read_ply(ply, PlyValues::activated, a.drop_invalid ? InvalidGaussians::drop : InvalidGaussians::reject,
                   &dropped);
    if (dropped > 0) spdlog::warn("{}: left out {} Gaussians with invalid numbers (--drop-invalid)", ply, dropped);
    // The folder's PLY must be its model's: a file copied in from another
    // model, or left from an earlier one, would render another scene under
    // this model's name (and over its sky).
    if (model_archive && dropped == 0) refuse_ply_of_another_model(ply, set, *model_archive);
  }
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

  Runtime rt(global.device);
  spdlog::info("device [{}] {}; {} Gaussians (SH degree {}), {} views", rt.info().index, rt.info().name, set.size(),
               set.sh_degree, cams.size());
  Renderer renderer(rt);
  DeviceGaussians dg(rt);
  dg.upload(set);
  Sky sky(rt);
  if (sky_coefficients) {
    sky.set(sky_degree_for(sky_coefficients->size()), *sky_coefficients);
    settings.background = {0.f, 0.f, 0.f};
    spdlog::info("rgb over the model's learned sky (SH degree {}); --bg R,G,B for a fixed background", sky.degree());
  }
  InstanceMapper mapper(rt);
  if (wants("instance")) mapper.set_clusters(anchor_cluster, children);
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
    renderer.forward(dg, cam, settings);
    RenderOutput out = renderer.download_output();
    if (sky.enabled() && wants("rgb")) composite_sky(renderer, sky, cam, out);
    const std::string& stem = stems[i];
    const int w = out.width, h = out.height;
    auto file = [&](const char* o, const char* ext) { return (out_dir / o / (stem + ext)).string(); };
    if (wants("rgb")) write_rgb_png(file("rgb", ".png"), out.rgb, w, h);
    if (wants("depth")) {
      // Mean depth along the ray (sum w z / alpha; 0 where nothing was hit).
      std::vector<float> depth(out.depth.size());
      for (size_t p = 0; p < depth.size(); ++p) depth[p] = out.alpha[p] > 1e-6f ? out.depth[p] / out.alpha[p] : 0.f;
      write_gray16_png(file("depth", ".png"), depth, w, h, 1000.f);
      write_npy(file("depth", ".npy"), depth, {h, w});
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
      // Cluster ids (-1 = none): the pixels where one cluster holds more
      // than half of the blending weight (stages/instance_map.h).
      mapper.compute(renderer);
      const InstanceMap im = mapper.download();
      write_rgb_png(file("instance", ".png"), instance_colours(im.ids), w, h);
      write_npy(file("instance", ".npy"), std::vector<float>(im.ids.begin(), im.ids.end()), {h, w});
    }
    const double el = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    const double eta = el / (i + 1) * (cams.size() - i - 1);
    spdlog::info("[{}/{}] {} {}x{}  {} intersections  {:.1f} s elapsed, ETA {:.1f} s", i + 1, cams.size(), cam.name, w,
                 h, renderer.stats().n_intersections, el, eta);
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
