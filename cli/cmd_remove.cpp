// remove: select an object as `query` does, delete its anchors, find in every
// training view the hole it leaves (stages/removal_holes.h) and the target
// that would fill it (classical inpainting, or an external inpainter's
// images), and write the model without the object as a complete model folder
// (docs/design.md section 15).
#include <spdlog/spdlog.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <fstream>
#include <filesystem>
#include <memory>
#include <nlohmann/json.hpp>
#include <string>
#include <system_error>

#include "cli/commands.h"
#include "host/device/cl_runtime.h"
#include "host/io/atomic_file.h"
#include "host/io/image_io.h"
#include "host/io/model_io.h"
#include "host/io/ply_io.h"
#include "host/render/renderer.h"
#include "host/scene/scene.h"
#include "queries/query.h"
#include "stages/anchor_model.h"
#include "stages/clustering.h"
#include "stages/language.h"
#include "stages/removal_holes.h"

namespace fs = std::filesystem;

namespace ag2gs::cli {
namespace {

struct RemoveArgs {
  QueryRequest request;
  std::string model, scene, selection, out, inpaint = "telea", inpainted, sparse;
  int iters = 0;
  int resolution = 0;  // 0 = the model's training -r
  uint64_t seed = 1;
  HoleSettings holes;
  QueryConfig config;
};

double seconds_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

// The anchors listed in a `query` selection.json.
std::vector<int32_t> read_selection_file(const std::string& path, size_t anchors) {
  std::ifstream f(path);
  if (!f) throw std::runtime_error(path + ": cannot be read (give the selection.json that `ag2gs query` wrote)");
  nlohmann::json j;
  try {
    j = nlohmann::json::parse(f);
  } catch (const nlohmann::json::exception& e) {
    throw std::runtime_error(path + ": not valid JSON (" + e.what() + ")");
  }
  if (!j.contains("anchors") || !j["anchors"].is_array())
    throw std::runtime_error(path + ": no \"anchors\" list; give the selection.json that `ag2gs query` wrote");
  std::vector<int32_t> out;
  for (const auto& v : j["anchors"]) {
    if (!v.is_number_integer() || v.get<int64_t>() < 0 || v.get<int64_t>() >= static_cast<int64_t>(anchors))
      throw std::runtime_error(path + ": anchor id " + v.dump() + " is not one of the model's " +
                               std::to_string(anchors) + " anchors (was the selection made on another model?)");
    out.push_back(v.get<int32_t>());
  }
  return out;
}

// The image an external inpainter wrote for `view`: DIR/<stem>.png, exactly
// the size the view is rendered at. Returns [H,W,3] in 0..1.
std::vector<float> read_inpainted(const std::string& dir, const SceneView& view) {
  const fs::path path = fs::path(dir) / (view.stem + ".png");
  if (!fs::exists(path))
    throw std::runtime_error("--inpainted " + dir + ": " + path.filename().string() + " is missing (one " +
                             std::to_string(view.camera.width) + "x" + std::to_string(view.camera.height) +
                             " PNG per training view, named after the view)");
  int width = 0, height = 0;
  std::vector<float> rgb = read_rgb(path.string(), width, height);
  if (width != view.camera.width || height != view.camera.height)
    throw std::runtime_error(path.string() + ": " + std::to_string(width) + "x" + std::to_string(height) +
                             ", expected " + std::to_string(view.camera.width) + "x" +
                             std::to_string(view.camera.height) + " (the view at the model's -r; use -r to match)");
  return rgb;
}


// The archive of the model without the removed anchors: the anchors, the
// training record, and stage 3's clusters and language features with the
// removed anchors taken out (cluster ids and language rows keep their
// numbers; a cluster may become empty). The stage-2 graph is left out: it
// described the old anchors, and stage 3 or a query rebuilds what it needs.
ModelArchive archive_without(const ModelArchive& in, const AnchorModel& kept_model, const std::vector<uint8_t>& keep) {
  ModelArchive out;
  kept_model.to_archive(out);
  if (in.meta.contains("train")) out.meta["train"] = in.meta["train"];
  if (in.has("sky/sh")) out.put_tensor("sky/sh", in.tensor("sky/sh"));
  if (in.meta.contains("clusters") && in.has("clusters/anchor_cluster")) {
    const std::vector<int32_t> ids = in.get<int32_t>("clusters/anchor_cluster");
    std::vector<int32_t> size = in.get<int32_t>("clusters/size");
    std::vector<int32_t> kept_ids;
    size_t skipped = 0;
    std::fill(size.begin(), size.end(), 0);
    for (size_t a = 0; a < ids.size(); ++a) {
      if (!keep[a]) continue;
      kept_ids.push_back(ids[a]);
      if (ids[a] >= 0)
        ++size[ids[a]];
      else
        ++skipped;
    }
    out.put("clusters/anchor_cluster", kept_ids, {static_cast<int64_t>(kept_ids.size())});
    out.put("clusters/size", size, {static_cast<int64_t>(size.size())});
    out.meta["clusters"] = in.meta["clusters"];
    out.meta["clusters"]["skipped_anchors"] = skipped;
    for (const char* name : {"clusters/language", "clusters/language_matches"})
      if (in.has(name)) out.put_tensor(name, in.tensor(name));
    if (in.meta.contains("language")) out.meta["language"] = in.meta["language"];
  }
  return out;
}

void cmd_remove(const GlobalOptions& global, RemoveArgs a) {
  const auto t_start = std::chrono::steady_clock::now();
  // ---- everything that can be checked before any work
  const bool by_selection = !a.selection.empty();
  if (by_selection && (a.request.by_click() || a.request.by_text()))
    throw std::invalid_argument("give either --selection FILE or a query (--click / --text), not both");
  if (!by_selection) check_query_request(a.request);
  a.holes.validate();
  const InpaintMethod method = parse_inpaint_method(a.inpaint);
  if (a.iters > 0)
    throw std::invalid_argument(
        "--iters " + std::to_string(a.iters) +
        ": fine-tuning the fill is not built yet; `remove` deletes the object and writes the holes and "
        "inpainted targets (--iters 0)");
  a.config.validate();
  std::error_code ec;
  // "out/", "out/." and "out" are one folder; it must lie outside the model folder.
  fs::path out = fs::absolute(a.out).lexically_normal();
  if (!out.has_filename()) out = out.parent_path();
  const fs::path model_dir = fs::weakly_canonical(fs::absolute(a.model));
  const fs::path out_real = fs::weakly_canonical(out);
  for (fs::path p = out_real; !p.empty(); p = p.parent_path()) {
    if (p == model_dir)
      throw std::invalid_argument("-o " + a.out + (p == out_real ? " is the model folder itself" : " lies inside the model folder") +
                                  "; write the result to a new folder outside it");
    if (p == p.parent_path()) break;
  }
  if (fs::exists(out) && !(fs::is_directory(out) && fs::is_empty(out)))
    throw std::invalid_argument("-o " + a.out + " exists and is not empty; give a new folder (nothing was written)");
  if (by_selection && !(a.request.view.empty() && a.request.vocab.empty()))
    throw std::invalid_argument("--view and --vocab belong to a click or text query, not to --selection");
  if (!a.inpainted.empty() && !fs::is_directory(a.inpainted))
    throw std::invalid_argument("--inpainted " + a.inpainted + " is not a folder");

  const bool by_text = !by_selection && a.request.by_text();
  const TrainedModel tm = load_trained_model(a.model, by_text);
  const std::string& model_file = tm.file;
  const ModelArchive& archive = tm.archive;
  const AnchorModel& model = tm.model;
  const int sh_degree = tm.sh_degree;
  const LanguageFeatures& language = tm.language;
  if (a.resolution == 0) a.resolution = tm.resolution;
  SceneOptions so;
  so.resolution = a.resolution;
  so.eval = tm.eval_split;
  so.sparse = a.sparse;
  std::unique_ptr<Scene> scene = Scene::open(a.scene, so);
  std::vector<float> embedding;
  if (by_text) embedding = load_query_embedding(a.request, model_file, language.dim);
  if (!a.inpainted.empty())
    for (int v : scene->train_views()) read_inpainted(a.inpainted, scene->views()[v]);  // all present, right size

  // ---- selection
  Runtime rt(global.device);
  nlohmann::json report;
  report["model"] = model_file;
  report["scene"] = a.scene;
  report["resolution"] = a.resolution;
  std::vector<int32_t> selected;
  double query_ms = 0;
  if (by_selection) {
    selected = read_selection_file(a.selection, model.size());
    report["query"] = {{"type", "selection"}, {"file", a.selection}};
  } else {
    QueryEngine engine(rt, model, a.config);
    if (by_text) engine.set_language(tm.clustering, language);
    selected = run_query(engine, *scene, a.request, embedding, a.resolution, a.config.text_margin, report, &query_ms);
  }
  std::vector<uint8_t> in_sel(model.size(), 0);
  for (int32_t s : selected) in_sel[s] = 1;
  size_t n_sel = 0;
  for (uint8_t b : in_sel) n_sel += b;
  if (n_sel == 0)
    throw std::runtime_error("the query selected no anchor: nothing to remove (try another click or phrase; "
                             "`ag2gs query` shows what a query selects)");
  if (n_sel == model.size())
    throw std::runtime_error("the query selected all " + std::to_string(model.size()) +
                             " anchors: removing them would leave an empty model");
  spdlog::info("selected {} of {} anchors ({} Gaussians) to remove", n_sel, model.size(),
               n_sel * static_cast<size_t>(model.children()));

  // ---- holes and targets, written into a folder beside OUT_DIR first
  const fs::path tmp = out.parent_path() / (out.filename().string() + ".partial." + std::to_string(::getpid()));
  fs::remove_all(tmp, ec);
  try {
    fs::create_directories(tmp / "holes");
    fs::create_directories(tmp / "targets");
    const GaussianSet removed = gaussians_of_anchors(model, sh_degree, in_sel, true);
    const GaussianSet kept = gaussians_of_anchors(model, sh_degree, in_sel, false);
    HoleFinder holes(kept, removed);
    Renderer renderer(rt);
    // The model's sky shows in the renders after deletion, as in training.
    Sky sky(rt);
    if (const auto coefficients = sky_from_archive(tm.archive))
      sky.set(sky_degree_for(coefficients->size()), *coefficients);
    nlohmann::json views = nlohmann::json::array();
    size_t hole_total = 0;
    const std::vector<int> train_views = scene->train_views();
    const auto t_holes = std::chrono::steady_clock::now();
    for (size_t i = 0; i < train_views.size(); ++i) {
      const SceneView& sv = scene->views()[train_views[i]];
      const ViewHole h = holes.find(renderer, sv.camera, a.holes, {}, sky.enabled() ? &sky : nullptr);
      const std::vector<float> target =
          a.inpainted.empty() ? inpaint_hole(h.rgb_after, h.hole, h.width, h.height, method)
                              : read_inpainted(a.inpainted, sv);
      write_mask_png((tmp / "holes" / (sv.stem + ".png")).string(), h.hole, h.width, h.height);
      write_rgb_png((tmp / "targets" / (sv.stem + ".png")).string(), target, h.width, h.height);
      hole_total += h.hole_pixels;
      views.push_back({{"view", sv.name},
                       {"object_pixels", h.object_pixels},
                       {"hole_pixels", h.hole_pixels},
                       {"hole_pixels_undilated", h.undilated_hole_pixels}});
      const double el = seconds_since(t_holes);
      spdlog::info("[{}/{}] {}: object {} px, hole {} px  {:.1f} s elapsed, ETA {:.1f} s", i + 1, train_views.size(),
                   sv.name, h.object_pixels, h.hole_pixels, el, el / (i + 1) * (train_views.size() - i - 1));
    }

    // ---- the model without the object
    std::vector<uint8_t> keep(model.size());
    for (size_t k = 0; k < keep.size(); ++k) keep[k] = !in_sel[k];
    AnchorModel kept_model = model;
    kept_model.remove_anchors(keep);
    write_model_archive((tmp / "model.ag2gs").string(), archive_without(archive, kept_model, keep));
    write_ply((tmp / "point_cloud.ply").string(), expand_reference(kept_model, sh_degree), true,
              PlyValues::activated);

    report["anchors_removed"] = n_sel;
    report["gaussians_removed"] = removed.size();
    report["anchors_kept"] = kept_model.size();
    report["gaussians_kept"] = kept_model.gaussians();
    report["anchors_added"] = 0;
    report["gaussians_added"] = 0;
    report["iterations"] = 0;
    report["seed"] = a.seed;
    report["inpaint"] = a.inpainted.empty() ? a.inpaint : "external: " + a.inpainted;
    report["holes"] = {{"object_weight", a.holes.object_weight},
                       {"alpha_min", a.holes.alpha_min},
                       {"behind_diameters", a.holes.behind},
                       {"object_diameter", holes.diameter()},
                       {"dilate", a.holes.dilate},
                       {"pixels", hole_total},
                       {"views", views}};
    report["seconds"] = {{"query", query_ms / 1000.0}, {"total", seconds_since(t_start)}};
    AtomicFile f((tmp / "removal.json").string());
    f.write(report.dump(2) + "\n");
    f.commit();
    if (fs::exists(out)) fs::remove(out);  // an empty folder (checked above)
    fs::rename(tmp, out);
  } catch (...) {
    fs::remove_all(tmp, ec);
    throw;
  }
  spdlog::info("wrote {}: model.ag2gs and point_cloud.ply without the object ({} anchors, {} Gaussians kept), "
               "holes/ and targets/ for {} training views, removal.json ({:.1f} s)",
               a.out, model.size() - n_sel, (model.size() - n_sel) * static_cast<size_t>(model.children()),
               scene->train_views().size(), seconds_since(t_start));
}

}  // namespace

void register_remove(CLI::App& app, GlobalOptions& global) {
  auto a = std::make_shared<RemoveArgs>();
  auto* r = app.add_subcommand("remove",
                               "Remove an object selected by a click or by text: delete its anchors, find the holes it "
                               "leaves and their inpainted targets; writes a new model folder");
  r->add_option("model", a->model, "Model folder written by `ag2gs train` (MODEL_DIR/model.ag2gs)")->required();
  r->add_option("--scene", a->scene, "Scene directory (images/, sparse/0/) the model was trained on")->required();
  r->add_option("-o,--out", a->out,
                "New folder for the model without the object: model.ag2gs, point_cloud.ply, holes/, targets/, "
                "removal.json")
      ->required();
  add_query_request_options(r, a->request);
  r->add_option("--selection", a->selection, "Remove the anchors of a selection.json written by `ag2gs query`");
  r->add_option("--inpaint", a->inpaint, "Fill the holes of the targets by telea (default), ns (Navier-Stokes) or none");
  r->add_option("--inpainted", a->inpainted,
                "Folder of targets from an external inpainter: <view stem>.png per training view, at the size the "
                "view is rendered at (used as they are)");
  r->add_option("--dilate", a->holes.dilate, "Grow each hole by this many pixels (default 2)")->check(CLI::Range(0, 64));
  r->add_option("--iters", a->iters, "Fine-tuning iterations (not built yet: 0, the default)")
      ->check(CLI::Range(0, 100000000));
  r->add_option("-r,--resolution", a->resolution, "Divide the cameras by R (default: the model's training -r)")
      ->check(CLI::Range(1, 64));
  r->add_option("--seed", a->seed, "Random seed of the fill (default 1)")->check(seed_number());
  r->add_option("--sparse", a->sparse,
                "COLMAP model folder inside the scene (default: sparse/0/, else sparse/ when it holds the model)");
  add_query_config_options(r, a->config);
  set_action(r, [&global, a] { cmd_remove(global, *a); });
}

}  // namespace ag2gs::cli
