// remove: select an object as `query` does, delete its anchors, find in every
// training view the hole it leaves (stages/removal_holes.h) and the target
// that would fill it (classical inpainting, or an external inpainter's
// images), add fill anchors where the holes' rays meet the surfaces around
// them and fine-tune those and their neighbours (stages/removal_fill.h), and
// write the model without the object as a complete model folder
// (docs/design.md section 15).
#include <spdlog/spdlog.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <memory>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <system_error>

#include "cli/commands.h"
#include "cli/object_selection.h"
#include "cli/run_driver.h"
#include "cli/run_guard.h"
#include "host/device/cl_runtime.h"
#include "host/io/atomic_file.h"
#include "host/io/image_io.h"
#include "host/io/model_io.h"
#include "host/io/model_ply.h"
#include "host/io/ply_io.h"
#include "host/render/renderer.h"
#include "host/scene/scene.h"
#include "queries/query.h"
#include "stages/anchor_model.h"
#include "stages/clustering.h"
#include "stages/language.h"
#include "stages/removal_fill.h"
#include "stages/removal_holes.h"
#include "stages/train_common.h"
#include "stages/train_config.h"

namespace fs = std::filesystem;

namespace ag2gs::cli {
namespace {

struct RemoveArgs {
  QueryRequest request;
  std::string model, scene, selection, out, inpaint = "telea", inpainted, sparse;
  int iters = -1;  // -1: kDefaultFillIters
  bool no_fill = false;
  bool clear_stray = true;
  bool clear_hidden = true;
  double hidden_fraction = 0.1;
  std::string tune_targets = "inpainted";
  float stray_colour = 0.2f;
  int stray_reach = 3;
  FillSettings fill;
  int resolution = 0;  // 0 = the model's training -r
  uint64_t seed = 1;
  HoleSettings holes;
  QueryConfig config;
};

// Fine-tuning iterations by default, measured on the removal benchmark
// (docs/benchmarks.md, "Object removal: fill and fine-tune"): the fill's
// colours, each taken from the inpainted targets of the views that see its
// voxel (then their mean; now an upper quantile by brightness), score
// higher at the test views than the same fill tuned to the per-view targets
// (100 or 300 iterations), which differ from view to view. An inpainter that
// agrees across views is what a fine-tune needs.
constexpr int kDefaultFillIters = 0;

// The opacity logit of a cleared child: sigmoid(-30) ~ 1e-13, below
// what the renderer draws.
constexpr float kClearedLogit = -30.f;

double seconds_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

// The image an external inpainter wrote for `view`: DIR/<stem>.png (`stem`:
// the view's name in holes/ and targets/, output_stems), exactly the size the
// view is rendered at. Returns [H,W,3] in 0..1.
std::vector<float> read_inpainted(const std::string& dir, const SceneView& view, const std::string& stem) {
  const fs::path path = fs::path(dir) / (stem + ".png");
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

// The file names of the training views' holes/ and targets/ images.
std::vector<std::string> train_view_stems(const Scene& scene) {
  std::vector<std::string> names;
  for (int v : scene.train_views()) names.push_back(scene.views()[v].name);
  return output_stems(names);
}

// The archive of the model after the removal: the anchors, the training
// record, and stage 3's clusters and language features, where anchor r of
// `result` takes the cluster of the old anchor source[r] (a kept anchor its
// own, a fill anchor the one it was initialised from; cluster ids and
// language rows keep their numbers, a cluster may become empty). The
// stage-2 graph is left out: it described the old anchors, and stage 3 or a
// query rebuilds what it needs.
ModelArchive archive_after(const ModelArchive& in, const AnchorModel& result, const std::vector<int>& source) {
  ModelArchive out;
  result.to_archive(out);
  if (in.meta.contains("train")) out.meta["train"] = in.meta["train"];
  if (in.has("sky/sh")) out.put_tensor("sky/sh", in.tensor("sky/sh"));
  if (in.meta.contains("clusters") && in.has("clusters/anchor_cluster")) {
    const std::vector<int32_t> ids = in.get<int32_t>("clusters/anchor_cluster");
    std::vector<int32_t> size = in.get<int32_t>("clusters/size");
    std::vector<int32_t> kept_ids;
    size_t skipped = 0;
    std::fill(size.begin(), size.end(), 0);
    for (int a : source) {
      const int32_t id = ids.at(a);
      kept_ids.push_back(id);
      if (id >= 0)
        ++size[id];
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
  check_selection_request(a.request, a.selection);
  a.holes.validate();
  const InpaintMethod method = parse_inpaint_method(a.inpaint);
  a.fill.validate();
  if (a.no_fill && a.iters > 0)
    throw std::invalid_argument("--no-fill deletes only; --iters " + std::to_string(a.iters) +
                                " would fine-tune a fill it does not place (leave one of them out)");
  if (a.iters < 0) a.iters = a.no_fill ? 0 : kDefaultFillIters;
  a.config.validate();
  const fs::path out = check_new_output_folder(a.out, a.model);
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
  // The training views' names in holes/, targets/ and --inpainted (a/1.jpg
  // and b/1.jpg: a_1.png and b_1.png).
  const std::vector<std::string> stems = train_view_stems(*scene);
  if (!a.inpainted.empty())
    for (size_t i = 0; i < stems.size(); ++i)  // all present, right size
      read_inpainted(a.inpainted, scene->views()[scene->train_views()[i]], stems[i]);

  // ---- selection
  Runtime rt(global.device);
  nlohmann::json report;
  report["model"] = model_file;
  report["scene"] = a.scene;
  report["resolution"] = a.resolution;
  const SelectedObject sel =
      select_object(rt, tm, *scene, a.request, a.selection, a.config, embedding, a.resolution, report, "remove");
  const std::vector<uint8_t>& in_sel = sel.anchors;
  const size_t n_sel = sel.count;
  const double query_ms = sel.query_ms;
  if (n_sel == model.size())
    throw std::runtime_error("the query selected all " + std::to_string(model.size()) +
                             " anchors: removing them would leave an empty model");
  spdlog::info("selected {} of {} anchors ({} Gaussians) to remove", n_sel, model.size(),
               n_sel * static_cast<size_t>(model.children()));

  // The training settings the fine-tune continues with (the model's own
  // when its archive records them).
  TrainConfig tc;
  if (archive.meta.contains("train") && archive.meta["train"].contains("config")) {
    try {
      tc = TrainConfig::from_json(archive.meta["train"]["config"]);
    } catch (const std::exception& e) {
      spdlog::warn("{}: its training config cannot be read ({}); the fine-tune uses the default rates", model_file,
                   e.what());
    }
  }
  InterruptGuard interrupts;

  // ---- holes and targets, written into a folder beside OUT_DIR first
  StagedFolder staged(out, a.out);
  const fs::path& tmp = staged.path();
  {
    fs::create_directories(tmp / "holes");
    fs::create_directories(tmp / "targets");
    Renderer renderer(rt);
    // The model's sky shows in the renders after deletion, as in training.
    Sky sky(rt);
    const std::optional<std::vector<float>> sky_coefficients = sky_from_archive(tm.archive);
    if (sky_coefficients) sky.set(sky_degree_for(sky_coefficients->size()), *sky_coefficients);
    RenderSettings render_settings;
    const float bg = tc.white_background && !sky.enabled() ? 1.f : 0.f;
    render_settings.background = {bg, bg, bg};
    const std::vector<int> train_views = scene->train_views();
    // Anchors the object hid from every photo go with it; children of kept
    // anchors that show the object are cleared (opacity 0).
    std::vector<int> hidden;
    const auto t_hidden = std::chrono::steady_clock::now();
    if (a.clear_hidden) {
      std::vector<Camera> cameras;
      for (int v : train_views) cameras.push_back(scene->views()[v].camera);
      spdlog::info("which kept anchors near the object do the {} training views see? (two renders a view)",
                   cameras.size());
      hidden = hidden_anchors(renderer, model, sh_degree, in_sel, cameras, render_settings, a.stray_reach,
                              a.hidden_fraction);
      spdlog::info("{} kept anchors near the object are seen only through it: removed with it ({:.1f} s)",
                   hidden.size(), seconds_since(t_hidden));
    }
    const double hidden_s = seconds_since(t_hidden);
    std::vector<uint8_t> gone = in_sel;
    for (int h : hidden) gone[h] = 1;
    const size_t n_gone = n_sel + hidden.size();
    AnchorModel cleaned = model;
    std::vector<size_t> strays;
    if (a.clear_stray) strays = stray_children(model, gone, a.stray_colour, a.stray_reach);
    for (size_t g : strays) cleaned.opacity_logit()[g] = kClearedLogit;
    if (!strays.empty())
      spdlog::info("{} children of kept anchors sit among the object's Gaussians with its colour: cleared",
                   strays.size());
    const GaussianSet removed = gaussians_of_anchors(model, sh_degree, in_sel, true);
    const GaussianSet kept = gaussians_of_anchors(cleaned, sh_degree, gone, false);
    HoleFinder holes(kept, removed);
    std::vector<uint8_t> keep(model.size());
    for (size_t k = 0; k < keep.size(); ++k) keep[k] = !gone[k];
    AnchorModel result = cleaned;
    std::vector<int> source = result.remove_anchors(keep);  // new id -> old id
    HoleFootprint footprint(result.grid(), holes.diameter(), a.holes.behind, a.fill.max_alpha);
    // Per training view, the fine-tune's target: the inpainted image in the
    // hole, the render after deletion on the object's other pixels (the
    // model already shows what lies behind there), the photo elsewhere.
    std::vector<std::pair<Camera, std::vector<float>>> tune_targets;
    std::vector<std::vector<uint8_t>> tune_holes;
    nlohmann::json views = nlohmann::json::array();
    size_t hole_total = 0;
    const auto t_holes = std::chrono::steady_clock::now();
    for (size_t i = 0; i < train_views.size(); ++i) {
      const SceneView& sv = scene->views()[train_views[i]];
      const ViewHole h = holes.find(renderer, sv.camera, a.holes, render_settings, sky.enabled() ? &sky : nullptr);
      const std::vector<float> target = a.inpainted.empty()
                                            ? inpaint_hole(h.rgb_after, h.hole, h.width, h.height, method)
                                            : read_inpainted(a.inpainted, sv, stems[i]);
      write_mask_png((tmp / "holes" / (stems[i] + ".png")).string(), h.hole, h.width, h.height);
      write_rgb_png((tmp / "targets" / (stems[i] + ".png")).string(), target, h.width, h.height);
      if (!a.no_fill) footprint.add_view(sv.camera, h, target);
      if (a.iters > 0) {
        const std::vector<uint8_t> around = dilate_mask(h.object, h.width, h.height, a.holes.dilate);
        const std::shared_ptr<const Image> photo = scene->image(train_views[i]);
        std::vector<float> t = photo->rgb;
        const size_t npix = h.hole.size();
        for (size_t p = 0; p < npix; ++p) {
          const std::vector<float>* from = h.hole[p] ? &target : around[p] ? &h.rgb_after : nullptr;
          if (from)
            for (int c = 0; c < 3; ++c) t[3 * p + c] = (*from)[3 * p + c];
        }
        tune_targets.emplace_back(sv.camera, std::move(t));
        tune_holes.push_back(h.hole);
      }
      hole_total += h.hole_pixels;
      views.push_back({{"view", sv.name},
                       {"object_pixels", h.object_pixels},
                       {"hole_pixels", h.hole_pixels},
                       {"hole_pixels_undilated", h.undilated_hole_pixels}});
      const double el = seconds_since(t_holes);
      spdlog::info("[{}/{}] {}: object {} px, hole {} px  {:.1f} s elapsed, ETA {:.1f} s", i + 1, train_views.size(),
                   sv.name, h.object_pixels, h.hole_pixels, el, el / (i + 1) * (train_views.size() - i - 1));
      staged.stop_if_interrupted("the hole search");
    }
    const double holes_s = seconds_since(t_holes);

    // ---- fill anchors and the fine-tune
    const auto t_fill = std::chrono::steady_clock::now();
    const size_t kept_anchors = result.size();
    FillResult fill;
    fill.trainable.assign(result.size(), 0);
    if (!a.no_fill) {
      fill = add_fill_anchors(result, footprint, a.fill, n_gone, a.seed);
      for (int p : fill.parent) source.push_back(source[p]);
      spdlog::info(
          "fill: {} anchors ({} Gaussians) where {} hole pixels of {} views meet the surfaces around them "
          "({} voxels with enough views); {} kept anchors lie near them",
          fill.added.size(), fill.added.size() * static_cast<size_t>(result.children()), footprint.points(),
          footprint.views_with_holes(), fill.candidates, fill.trainable_kept);
    }
    size_t trainable = 0;
    for (uint8_t t : fill.trainable) trainable += t;
    int iterations_done = 0;
    double final_psnr = 0;
    if (a.iters > 0 && trainable > 0) {
      FineTuneConfig fc;
      fc.iterations = a.iters;
      fc.seed = a.seed;
      fc.sh_degree = sh_degree;
      fc.background = render_settings.background;
      fc.lambda_ssim = tc.lambda_ssim;
      const double extent =
          scene->bounds().camera_radius > 0 ? scene->bounds().camera_radius : scene->bounds().longest_extent();
      fc.offset_lr = tc.offset_lr_final * (tc.offset_lr_extent ? extent : 1.0);
      fc.scaling_lr = tc.scaling_lr;
      fc.rotation_lr = tc.rotation_lr;
      fc.opacity_lr = tc.opacity_lr;
      fc.sh_dc_lr = tc.sh_dc_lr;
      fc.sh_rest_lr = tc.sh_rest_lr;
      if (a.tune_targets == "fill") {
        // The holes' targets are the filled model's own render: one colour
        // per voxel, agreed by the views, so the fine-tune fits the seams
        // around the holes to the photos without undoing the fill.
        const GaussianSet filled = expand_reference(result, sh_degree);
        for (size_t i = 0; i < tune_targets.size(); ++i) {
          auto& [cam, t] = tune_targets[i];
          RenderOutput o = renderer.render(filled, cam, render_settings);
          if (sky.enabled()) composite_sky(renderer, sky, cam, o);
          for (size_t p = 0; p < tune_holes[i].size(); ++p)
            if (tune_holes[i][p])
              for (int c = 0; c < 3; ++c) t[3 * p + c] = o.rgb[3 * p + c];
        }
      }
      FillTuner tuner(rt, result, fill.trainable, fc, sky_coefficients ? &*sky_coefficients : nullptr);
      for (auto& [cam, t] : tune_targets) tuner.add_target(cam, std::move(t));
      tune_targets.clear();
      const auto t_tune = std::chrono::steady_clock::now();
      const int every = std::max(1, std::min(100, a.iters / 5));
      double psnr_sum = 0;
      int psnr_n = 0;
      for (int it = 1; it <= a.iters; ++it) {
        const FillTuner::Step st = tuner.step();
        psnr_sum += st.psnr;
        ++psnr_n;
        iterations_done = it;
        if (it % every == 0 || it == a.iters) {
          const double el = seconds_since(t_tune);
          final_psnr = psnr_sum / psnr_n;
          spdlog::info(
              "fine-tune it {:5d}/{}  loss {:.5f}  PSNR {:.2f} dB (against the targets, mean of the last {})  "
              "{:.1f} s elapsed, ETA {}",
              it, a.iters, st.loss, final_psnr, psnr_n, el, fmt_duration(el / it * (a.iters - it)));
          psnr_sum = 0;
          psnr_n = 0;
        }
        staged.stop_if_interrupted("the fine-tune");
      }
      result = tuner.model();
    } else if (a.iters > 0) {
      spdlog::info("fine-tune: nothing to tune (no fill anchor and no kept anchor near the holes)");
    }
    // Fill anchors that found nothing to show go again.
    size_t fill_kept = fill.added.size();
    if (!fill.added.empty()) {
      std::vector<uint8_t> keep_fill(result.size(), 1);
      const int K = result.children();
      for (int id : fill.added) {
        double mean = 0;
        for (int i = 0; i < K; ++i)
          mean += 1.0 / (1.0 + std::exp(-result.opacity_logit()[static_cast<size_t>(id) * K + i]));
        if (a.fill.prune_opacity > 0 && mean / K < a.fill.prune_opacity) {
          keep_fill[id] = 0;
          --fill_kept;
        }
      }
      if (fill_kept != fill.added.size()) {
        const std::vector<int> rows = result.remove_anchors(keep_fill);
        std::vector<int> src;
        for (int r : rows) src.push_back(source[r]);
        source = std::move(src);
      }
    }
    const double fill_s = seconds_since(t_fill);

    // ---- the model after the removal
    write_model_archive((tmp / "model.ag2gs").string(), archive_after(archive, result, source));
    {
      // As train writes it: with the model's sky baked in when it has one.
      std::vector<Camera> all_cameras;
      for (const SceneView& sv : scene->views()) all_cameras.push_back(sv.camera);
      write_model_plys(tmp.string(), expand_reference(result, sh_degree), sky_coefficients, all_cameras);
    }

    // The kept anchors the fine-tune may change (their ids in the new model;
    // every other kept anchor has its bytes from the input model).
    std::vector<int> tuned_ids;
    if (iterations_done > 0)
      for (size_t k = 0; k < kept_anchors; ++k)
        if (fill.trainable[k]) tuned_ids.push_back(static_cast<int>(k));
    {
      // The cleared children as (anchor id in the new model, child).
      std::vector<int> new_id(model.size(), -1);
      for (size_t r = 0; r < kept_anchors; ++r) new_id[source[r]] = static_cast<int>(r);
      nlohmann::json cleared = nlohmann::json::array();
      for (size_t g : strays) cleared.push_back({new_id[g / model.children()], static_cast<int>(g % model.children())});
      report["stray_children_cleared"] = cleared;
    }
    report["hidden_anchors_removed"] = hidden;  // ids in the input model
    report["anchors_removed"] = n_gone;
    report["gaussians_removed"] = n_gone * static_cast<size_t>(model.children());
    report["anchors_kept"] = kept_anchors;
    report["gaussians_kept"] = kept_anchors * static_cast<size_t>(result.children());
    report["anchors_added"] = fill_kept;
    report["gaussians_added"] = fill_kept * static_cast<size_t>(result.children());
    report["anchors"] = result.size();
    report["gaussians"] = result.gaussians();
    report["iterations"] = iterations_done;
    report["seed"] = a.seed;
    report["inpaint"] = a.inpainted.empty() ? a.inpaint : "external: " + a.inpainted;
    report["fill"] = {{"enabled", !a.no_fill},
                      {"footprint_points", footprint.points()},
                      {"footprint_views", footprint.views_with_holes()},
                      {"candidates", fill.candidates},
                      {"anchors_placed", fill.added.size()},
                      {"anchors_pruned", fill.added.size() - fill_kept},
                      {"kept_anchors_near", fill.trainable_kept},
                      {"kept_anchors_tuned", tuned_ids.size()},
                      {"kept_anchors_tuned_ids", tuned_ids},
                      {"min_views", a.fill.min_views},
                      {"near_voxels", a.fill.near},
                      {"start_opacity", a.fill.opacity},
                      {"max_alpha", a.fill.max_alpha},
                      {"colour_quantile", a.fill.colour_quantile},
                      {"stray_colour", a.clear_stray ? nlohmann::json(a.stray_colour) : nlohmann::json(nullptr)},
                      {"stray_reach", a.clear_stray ? nlohmann::json(a.stray_reach) : nlohmann::json(nullptr)},
                      {"hidden_fraction", a.clear_hidden ? nlohmann::json(a.hidden_fraction) : nlohmann::json(nullptr)},
                      {"tune_targets", a.tune_targets},
                      {"final_target_psnr", final_psnr}};
    report["holes"] = {{"object_weight", a.holes.object_weight},
                       {"alpha_min", a.holes.alpha_min},
                       {"behind_diameters", a.holes.behind},
                       {"object_diameter", holes.diameter()},
                       {"dilate", a.holes.dilate},
                       {"pixels", hole_total},
                       {"views", views}};
    report["seconds"] = {{"query", query_ms / 1000.0},
                         {"hidden", hidden_s},
                         {"holes", holes_s},
                         {"fill_and_fine_tune", fill_s},
                         {"total", seconds_since(t_start)}};
    AtomicFile f((tmp / "removal.json").string());
    f.write(report.dump(2) + "\n");
    f.commit();
    staged.commit();
    spdlog::info(
        "wrote {}: model.ag2gs and point_cloud.ply without the object ({} anchors kept, {} added, {} "
        "Gaussians), holes/ and targets/ for {} training views, removal.json ({:.1f} s)",
        a.out, kept_anchors, fill_kept, result.gaussians(), train_views.size(), seconds_since(t_start));
  }
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
      ->check(output_path())
      ->required();
  add_query_request_options(r, a->request);
  r->add_option("--selection", a->selection, "Remove the anchors of a selection.json written by `ag2gs query`");
  r->add_option("--inpaint", a->inpaint,
                "Fill the holes of the targets by telea (default), ns (Navier-Stokes) or none");
  r->add_option("--inpainted", a->inpainted,
                "Folder of targets from an external inpainter: <view stem>.png per training view, at the size the "
                "view is rendered at (used as they are)");
  r->add_option("--dilate", a->holes.dilate,
                "Grow each hole by this many pixels (default 5: the object's blurred rim and contact shadow)")
      ->check(CLI::Range(0, 64));
  r->add_option("--iters", a->iters,
                "Fine-tune the fill and the anchors near it for N iterations against the photos outside the object "
                "and the inpainted targets in the holes (default " +
                    std::to_string(kDefaultFillIters) +
                    ": the fill as placed, measured better with per-view inpainting)")
      ->check(CLI::Range(0, 100000000));
  r->add_option("--fill-views", a->fill.min_views,
                "A fill anchor needs hole pixels of this many views in its voxel (default 2)")
      ->check(CLI::Range(1, 1000000));
  r->add_option("--fill-alpha", a->fill.max_alpha,
                "Hole pixels the model without the object still covers with this alpha or more get no fill "
                "(default 0.5; 1: every hole pixel)");
  r->add_option("--fill-quantile", a->fill.colour_quantile,
                "The fill's colour: of the views' colour estimates at a fill voxel, ranked by brightness, the one at "
                "this quantile (default 0.75: shadows only darken; 0.5 the median)");
  r->add_option("--fill-opacity", a->fill.opacity, "Opacity of the fill's children (default 0.3)")
      ->check(finite_range(1e-4, 0.9999));
  r->add_option("--fill-near", a->fill.near,
                "Kept anchors within this many of their voxel edges of the holes' 3D footprint are fine-tuned "
                "with the fill (default 1.5; 0: the fill alone)")
      ->check(finite_range(0, 1000));
  r->add_flag("!--keep-stray", a->clear_stray,
              "Keep the children of kept anchors that sit among the object's Gaussians with its colour (by default "
              "they are cleared with it)");
  r->add_option("--stray-colour", a->stray_colour,
                "A kept child near the object's Gaussians is the object's when its colour is within this of theirs "
                "(mean absolute difference, 0..1) and nearer to it than to the kept Gaussians' there (default 0.2)")
      ->check(finite_range(0.0, 1.0));
  r->add_option("--stray-reach", a->stray_reach,
                "How near: finest-layer voxels within this many of a kept child's own along each axis (default 3; 0: "
                "its own voxel)")
      ->check(CLI::Range(0, 16));
  r->add_flag("!--keep-hidden", a->clear_hidden,
              "Keep the kept anchors near the object (within --stray-reach) that the training views saw only through "
              "it (by default they are removed with it, and the fill may take their voxels)");
  r->add_option("--hidden-fraction", a->hidden_fraction,
                "Such an anchor is hidden when, for each of its visible children, the views saw less than this "
                "fraction of it outside the object's silhouette (default 0.1)")
      ->check(finite_range(0.0, 1.0));
  r->add_option("--tune-targets", a->tune_targets,
                "What the fine-tune fits inside the holes: inpainted (the targets/ images) or fill (the filled "
                "model's own render, so only the seams around the holes move)")
      ->check(CLI::IsMember({"inpainted", "fill"}));
  r->add_flag("--no-fill", a->no_fill, "Delete only: no fill anchors and no fine-tune");
  r->add_option("-r,--resolution", a->resolution, "Divide the cameras by R (default: the model's training -r)")
      ->check(CLI::Range(1, 64));
  r->add_option("--seed", a->seed, "Random seed of the fill (default 1)")->check(seed_number());
  r->add_option("--sparse", a->sparse,
                "COLMAP model folder inside the scene (default: sparse/0/, else sparse/ when it holds the model)");
  add_query_config_options(r, a->config);
  set_action(r, [&global, a] { cmd_remove(global, *a); });
}

}  // namespace ag2gs::cli
