// query: select an object of a trained model by a click or by text
// (queries/query.h) and write its Gaussians, the rest, a JSON summary and
// the selection's masks in the requested views.
#include <spdlog/spdlog.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <memory>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <set>
#include <sstream>
#include <string>

#include "cli/commands.h"
#include "cli/object_selection.h"
#include "cli/run_guard.h"
#include "host/core/timing.h"
#include "host/device/cl_runtime.h"
#include "host/io/atomic_file.h"
#include "host/io/model_io.h"
#include "host/io/npy_io.h"
#include "host/io/output_set.h"
#include "host/io/ply_io.h"
#include "host/io/semantic_io.h"
#include "host/scene/scene.h"
#include "host/scene/scene_up.h"
#include "queries/query.h"
#include "stages/anchor_model.h"
#include "stages/clustering.h"
#include "stages/language.h"

namespace fs = std::filesystem;

namespace ag2gs::cli {
namespace {

struct QueryArgs {
  QueryRequest request;
  std::string model, scene, out, views;
  std::string sparse;  // --sparse; empty = the scene-folder rule (host/scene/scene.h)
  int resolution = 0;  // 0 = the resolution the model was trained at
  QueryConfig config;
  bool force = false;  // --force: replace the results of an earlier query in OUT
};

}  // namespace

// "X,Y" -> two numbers.
static void parse_click(const std::string& s, double* x, double* y) {
  const size_t comma = s.find(',');
  bool ok = comma != std::string::npos;
  if (ok) {
    try {
      size_t u1 = 0, u2 = 0;
      const std::string a = s.substr(0, comma), b = s.substr(comma + 1);
      *x = std::stod(a, &u1);
      *y = std::stod(b, &u2);
      ok = u1 == a.size() && u2 == b.size() && std::isfinite(*x) && std::isfinite(*y);
    } catch (const std::exception&) {
      ok = false;
    }
  }
  if (!ok)
    throw std::invalid_argument("--click '" + s +
                                "': expected X,Y pixel coordinates (column,row), e.g. --click 120,80");
}

// --views: train | test | all | comma-separated names (Scene::find_view).
static std::vector<int> pick_scene_views(const Scene& scene, const std::string& views) {
  if (views.empty()) return {};
  if (views == "all") {
    std::vector<int> v(scene.views().size());
    for (size_t i = 0; i < v.size(); ++i) v[i] = static_cast<int>(i);
    return v;
  }
  if (views == "train") return scene.train_views();
  if (views == "test") return scene.test_views();
  std::vector<int> out;
  for (const std::string& item : split_list(views)) out.push_back(scene.find_view(item));
  return out;
}

std::vector<float> load_query_embedding(const QueryRequest& a, const std::string& model_file, int expected_dim) {
  if (!a.text_embedding.empty()) {
    const NpyArray arr = read_npy(a.text_embedding);
    const bool vec = arr.shape.size() == 1 || (arr.shape.size() == 2 && arr.shape[0] == 1);
    if (!vec || static_cast<int64_t>(arr.size()) != expected_dim) {
      std::string shape = "[";
      for (size_t i = 0; i < arr.shape.size(); ++i) shape += (i ? "," : "") + std::to_string(arr.shape[i]);
      shape += "]";
      throw std::invalid_argument(a.text_embedding + ": the embedding has shape " + shape + ", expected [" +
                                  std::to_string(expected_dim) + "] or [1," + std::to_string(expected_dim) +
                                  "] (the dimension of the language features in " + model_file + ")");
    }
    return arr.data;
  }
  const Vocabulary vocab = read_vocabulary(a.vocab);
  auto it = vocab.phrases.find(a.text);
  if (it == vocab.phrases.end()) {
    std::string some;
    int n = 0;
    for (const auto& [phrase, v] : vocab.phrases) {
      if (n++ == 8) {
        some += ", ...";
        break;
      }
      some += (n > 1 ? ", \"" : "\"") + phrase + "\"";
    }
    throw std::invalid_argument(a.vocab + ": no phrase \"" + a.text + "\" in the vocabulary (" +
                                std::to_string(vocab.phrases.size()) + " phrases: " + some +
                                "); add its CLIP embedding to the file or pass --text-embedding FILE.npy");
  }
  if (vocab.dim != expected_dim)
    throw std::invalid_argument(a.vocab + ": embeddings of " + std::to_string(vocab.dim) +
                                " dimensions, the language features in " + model_file + " have " +
                                std::to_string(expected_dim) + " (use the CLIP model that made the scene's features)");
  return it->second;
}

std::vector<std::vector<float>> load_rival_embeddings(const QueryRequest& a) {
  if (a.text.empty() || a.vocab.empty()) return {};
  return read_vocabulary(a.vocab).others(a.text);
}

std::vector<uint8_t> encode_mask_png(const std::vector<uint8_t>& mask, int width, int height) {
  cv::Mat img(height, width, CV_8UC1);
  for (int y = 0; y < height; ++y)
    for (int x = 0; x < width; ++x) img.at<uint8_t>(y, x) = mask[static_cast<size_t>(y) * width + x] ? 255 : 0;
  std::vector<uint8_t> bytes;
  if (!cv::imencode(".png", img, bytes)) throw std::runtime_error("could not encode the mask as PNG");
  return bytes;
}

void write_mask_png(const std::string& path, const std::vector<uint8_t>& mask, int width, int height) {
  const std::vector<uint8_t> bytes = encode_mask_png(mask, width, height);
  AtomicFile f(path);
  f.write(bytes.data(), bytes.size());
  f.commit();
}

static nlohmann::json finite_or_null(double v) {
  return std::isfinite(v) ? nlohmann::json(v) : nlohmann::json(nullptr);
}

void check_query_request(const QueryRequest& r) {
  if (r.by_click() == r.by_text())
    throw std::invalid_argument(
        "give exactly one query: --view NAME --click X,Y, or --text PHRASE --vocab FILE.json, "
        "or --text-embedding FILE.npy");
  if (r.by_click() && r.view.empty()) throw std::invalid_argument("--click needs --view NAME (the clicked image)");
  if (!r.text.empty() && !r.text_embedding.empty())
    throw std::invalid_argument("give either --text (with --vocab) or --text-embedding, not both");
  if (!r.text.empty() && r.vocab.empty())
    throw std::invalid_argument("--text needs --vocab FILE.json (phrase -> CLIP embedding)");
  if (r.by_click()) {
    double x = 0, y = 0;
    parse_click(r.click, &x, &y);
  }
}

std::vector<int32_t> run_query(QueryEngine& engine, const Scene& scene, const QueryRequest& r,
                               const std::vector<float>& embedding, int resolution, double text_margin,
                               nlohmann::json& j, double* ms) {
  std::vector<int32_t> selected;
  if (r.by_click()) {
    double cx = 0, cy = 0;
    parse_click(r.click, &cx, &cy);
    const int click_view = scene.find_view(r.view);
    // The click is in the pixels of the image file (full resolution); the
    // loaded camera may be smaller (-r): map the clicked pixel's centre.
    const SceneView& cv = scene.views()[click_view];
    const Camera& cam = cv.camera;
    if (!(cx >= 0 && cy >= 0 && cx < cv.full_camera.width && cy < cv.full_camera.height))
      throw std::invalid_argument("--click " + r.click + " is outside the " + std::to_string(cv.full_camera.width) +
                                  "x" + std::to_string(cv.full_camera.height) + " image " + cv.name +
                                  " (x is the column in [0, width), y the row in [0, height))");
    const Eigen::Vector2d px = full_size_click(cv.full_camera, cam, cx, cy);
    ClickResult c;
    try {
      c = engine.click(cam, px.x(), px.y());
    } catch (const std::runtime_error& e) {
      throw std::runtime_error("--click " + r.click + " (full-size pixel; rendered at -r " +
                               std::to_string(resolution) + "): " + e.what());
    }
    selected = c.selected;
    *ms = c.ms;
    j["query"] = {{"type", "click"},
                  {"view", scene.views()[click_view].name},
                  {"x", cx},
                  {"y", cy},
                  {"pixel", {c.pixel_x, c.pixel_y}},
                  {"alpha", c.alpha},
                  {"depth", c.depth},
                  {"point", {c.point.x(), c.point.y(), c.point.z()}},
                  {"seed_distance", c.seed_distance},
                  {"dominant_anchor", c.dominant_anchor},
                  {"dominant_weight", c.dominant_weight}};
    j["seeds"] = {c.seed};
    spdlog::info("click ({}, {}) on {}: alpha {:.3f}, depth {:.4f}, seed anchor {} at {:.4f} from the point", cx, cy,
                 scene.views()[click_view].name, c.alpha, c.depth, c.seed, c.seed_distance);
  } else {
    const std::vector<std::vector<float>> rivals = load_rival_embeddings(r);
    const TextResult t = engine.text(embedding, rivals);
    selected = t.selected;
    *ms = t.ms;
    j["none"] = t.none;
    j["clusters_won"] = t.won;
    j["rival_phrases"] = rivals.size();
    j["query"] = {{"type", "text"}};
    if (!r.text.empty()) {
      j["query"]["text"] = r.text;
      j["query"]["vocab"] = r.vocab;
    } else {
      j["query"]["text_embedding"] = r.text_embedding;
    }
    j["seeds"] = t.seeds;
    j["seed_clusters"] = t.seed_clusters;
    j["best_score"] = t.best;
    nlohmann::json scores = nlohmann::json::array();
    for (double s : t.scores) scores.push_back(finite_or_null(s));
    j["scores"] = scores;
    if (t.none)
      spdlog::warn(
          "text: \"{}\" names nothing here: each cluster is described better by another of the {} phrases of {} "
          "(the phrase's best cosine {:.4f}); nothing is selected",
          r.text, rivals.size(), r.vocab, t.best);
    else
      spdlog::info(
          "text: best cosine {:.4f} of the {} cluster(s) the phrase describes best of {} phrases; {} seed "
          "cluster(s) within {}, {} seed anchors",
          t.best, t.won, rivals.size() + 1, t.seed_clusters.size(), text_margin, t.seeds.size());
  }
  return selected;
}

TrainedModel load_trained_model(const std::string& model_dir, bool with_language) {
  TrainedModel t;
  t.file = (fs::path(model_dir) / "model.ag2gs").string();
  if (!fs::exists(t.file))
    throw std::runtime_error(model_dir + ": no model.ag2gs; give a model folder written by `ag2gs train`");
  return trained_model_from_archive(read_model_archive(t.file), t.file, with_language);
}

TrainedModel trained_model_from_archive(ModelArchive archive, const std::string& file, bool with_language) {
  TrainedModel t;
  t.file = file;
  t.archive = std::move(archive);
  if (t.archive.source.empty()) t.archive.source = file;
  t.model = check_model_archive(t.archive);
  const nlohmann::json train = t.archive.meta.value("train", nlohmann::json::object());
  t.sh_degree = recorded_sh_degree(train, t.model.config().sh_degree, t.file);
  t.resolution = recorded_resolution(train, t.file);
  t.eval_split = train.value("eval_split", true);
  // Stage 3's cluster ids, checked whenever present (remove copies them).
  if (t.archive.meta.contains("clusters") && t.archive.has("clusters/anchor_cluster"))
    t.clustering = clustering_from_archive(t.archive, t.model.size());
  if (with_language) {
    if (!t.archive.meta.contains("clusters") || !t.archive.meta.contains("language"))
      throw std::runtime_error(t.file +
                               " has no clusters/language features, which a text query needs and stage 3 "
                               "attaches: run stages 2 and 3 on it (`ag2gs train SCENE_DIR -o MODEL_DIR --stages "
                               "2,3`), or select by a click");
    t.clustering = clustering_from_archive(t.archive, t.model.size());
    t.language = language_from_archive(t.archive, t.clustering.clusters());
  }
  return t;
}

namespace {

void cmd_query(const GlobalOptions& global, QueryArgs a) {
  check_query_request(a.request);
  const bool by_click = a.request.by_click(), by_text = a.request.by_text();
  a.config.validate();

  const auto t_load = std::chrono::steady_clock::now();
  const TrainedModel tm = load_trained_model(a.model, by_text);
  const std::string& model_file = tm.file;
  const AnchorModel& model = tm.model;
  const int sh_degree = tm.sh_degree;
  const LanguageFeatures& language = tm.language;
  if (a.resolution == 0) a.resolution = tm.resolution;

  SceneOptions so;
  so.resolution = a.resolution;
  so.eval = true;  // test = every 8th view in name order, train = the rest
  so.sparse = a.sparse;
  std::unique_ptr<Scene> scene = Scene::open(a.scene, so);
  refuse_output_in_inputs(a.out, a.scene, {a.model}, "-o");
  refuse_file_as_output_folder(a.out, "-o");
  finish_interrupted_output_sets(a.out);  // a killed run's last commit, finished
  std::vector<std::string> old_masks;     // an earlier selection's, replaced or deleted together with it
  {
    std::vector<std::string> files = {"selection.json", "selection.ply", "remainder.ply"};
    std::error_code ec;
    if (fs::is_directory(fs::path(a.out) / "masks", ec))
      for (const auto& e : fs::directory_iterator(fs::path(a.out) / "masks", ec))
        files.push_back("masks/" + e.path().filename().string());
    refuse_existing_results("-o", a.out, files, a.force);
    old_masks.assign(files.begin() + 3, files.end());
  }
  int click_view = -1;
  if (by_click) click_view = scene->find_view(a.request.view);
  std::vector<int> views = pick_scene_views(*scene, a.views);
  if (by_click && std::find(views.begin(), views.end(), click_view) == views.end())
    views.insert(views.begin(), click_view);
  std::vector<float> embedding;
  if (by_text) embedding = load_query_embedding(a.request, model_file, language.dim);

  Runtime rt(global.device);
  QueryEngine engine(rt, model, a.config);
  if (by_text) engine.set_language(tm.clustering, language);
  nlohmann::json j;
  if (by_click) prepare_click(engine, a.request.click_by, tm.archive.meta, *scene, &j);
  const double load_ms = ms_since(t_load);
  spdlog::info(
      "model {}: {} anchors, {} Gaussians; query graph (cell scale {}) {} edges; loaded and prepared in "
      "{:.0f} ms (graph, k-d tree and upload {:.0f} ms)",
      model_file, model.size(), model.gaussians(), a.config.graph_cell_scale, engine.graph().edges(), load_ms,
      engine.prepare_ms());

  j["model"] = model_file;
  j["anchor_fingerprint"] = anchor_fingerprint(model);
  j["scene"] = a.scene;
  j["resolution"] = a.resolution;
  j["thresholds"] = {{"min_weight", a.config.min_weight},
                     {"tau", a.config.tau},
                     {"equivalent_feature_distance", a.config.equivalent_distance()},
                     {"graph_cell_scale", a.config.graph_cell_scale},
                     {"text_margin", a.config.text_margin},
                     {"min_click_alpha", a.config.min_click_alpha},
                     {"click_candidates", a.config.click_candidates},
                     {"click_dominant", a.config.click_dominant},
                     {"click_front_weight", a.config.click_front_weight},
                     {"mask_threshold", a.config.mask_threshold}};
  double query_ms = 0;
  const std::vector<int32_t> selected =
      run_query(engine, *scene, a.request, embedding, a.resolution, a.config.text_margin, j, &query_ms);
  std::printf("query latency: %.1f ms (after the model was loaded); %zu of %zu anchors selected\n", query_ms,
              selected.size(), model.size());

  // Outputs.
  const auto t_out = std::chrono::steady_clock::now();
  fs::create_directories(fs::path(a.out) / "masks");
  OutputSet written(a.out);  // the selection's files go into place together, at the end
  std::vector<uint8_t> in_sel(model.size(), 0);
  for (int32_t s : selected) in_sel[s] = 1;
  const GaussianSet sel = gaussians_of_anchors(model, sh_degree, in_sel, true);
  const GaussianSet rest = gaussians_of_anchors(model, sh_degree, in_sel, false);
  write_ply((fs::path(a.out) / "selection.ply").string(), sel, true);
  write_ply((fs::path(a.out) / "remainder.ply").string(), rest, true);
  const double ply_ms = ms_since(t_out);
  const auto t_mask = std::chrono::steady_clock::now();
  nlohmann::json masks = nlohmann::json::array();
  std::vector<std::string> names;
  for (int v : views) names.push_back(scene->views()[v].name);
  const std::vector<std::string> stems = output_stems(names);  // a/1.jpg and b/1.jpg: a_1.png, b_1.png
  for (size_t i = 0; i < views.size(); ++i) {
    const SceneView& sv = scene->views()[views[i]];
    const std::vector<uint8_t> m = engine.mask(sv.camera, selected);
    const std::string path = (fs::path(a.out) / "masks" / (stems[i] + ".png")).string();
    write_mask_png(path, m, sv.camera.width, sv.camera.height);
    size_t on = 0;
    for (uint8_t b : m) on += b;
    masks.push_back({{"view", sv.name}, {"file", "masks/" + stems[i] + ".png"}, {"pixels", on}});
  }
  const double mask_ms = ms_since(t_mask);

  j["anchors"] = selected;
  j["anchor_count"] = selected.size();
  j["gaussian_count"] = sel.size();
  j["remainder_anchor_count"] = model.size() - selected.size();
  j["remainder_gaussian_count"] = rest.size();
  j["masks"] = masks;
  j["timing_ms"] = {{"load_and_prepare", load_ms},
                    {"prepare", engine.prepare_ms()},
                    {"query", query_ms},
                    {"ply", ply_ms},
                    {"masks", mask_ms},
                    {"mask_views", views.size()}};
  AtomicFile f((fs::path(a.out) / "selection.json").string());
  f.write(j.dump(2) + "\n");
  f.commit();
  for (const std::string& m : old_masks)
    if (std::find_if(masks.begin(), masks.end(), [&](const nlohmann::json& x) { return x["file"] == m; }) ==
        masks.end())
      written.remove_at_commit((fs::path(a.out) / m).string());
  written.commit();
  spdlog::info("wrote {}: selection.ply ({} Gaussians), remainder.ply ({}), selection.json, {} mask(s) in {:.0f} ms",
               a.out, sel.size(), rest.size(), views.size(), mask_ms);
}

}  // namespace

void add_query_config_options(CLI::App* sub, QueryConfig& c) {
  sub->add_option("--min-weight", c.min_weight,
                  "Grow along edges with exp(-|fi-fj|^2/(2 tau^2)) above this (default 0.9)")
      ->check(finite_range(1e-6, 0.999999));
  sub->add_option("--tau", c.tau, "Bilateral weight scale tau (default 0.05)")->check(finite_range(1e-6, 1e6));
  sub->add_option("--text-margin", c.text_margin, "Text seeds: clusters within this of the best score (0.1)")
      ->check(finite_range(0, 2));
  sub->add_option("--graph-scale", c.graph_cell_scale, "Query graph neighbourhood in top voxels (default 2)")
      ->check(CLI::Range(1, 1024));
  sub->add_option("--click-candidates", c.click_candidates,
                  "Click seed: of this many anchors nearest the clicked point, the one whose feature is closest to "
                  "the pixel's rendered feature (default 8; 1 = the nearest anchor)")
      ->check(CLI::Range(1, 4096));
  sub->add_flag("--click-dominant,!--click-mean", c.click_dominant,
                "Click depth and feature: of the feature group of anchors holding the most blending weight at the "
                "pixel (default), "
                "or --click-mean: the ray's mean depth and rendered feature");
  sub->add_option("--click-front-weight", c.click_front_weight,
                  "With --click-dominant: the nearest feature group along the ray holding at least this much of the "
                  "pixel's blending weight instead of the heaviest (default 0.3; 0 = the heaviest)")
      ->check(finite_range(0.0, 0.999));
}

void add_query_request_options(CLI::App* sub, QueryRequest& r) {
  sub->add_option("--view", r.view, "Click query: the clicked image (name, name without extension or stem)");
  sub->add_option("--click", r.click, "Click query: X,Y pixel (column,row) of the full-size image file");
  sub->add_option("--text", r.text, "Text query: a phrase of the --vocab file")
      ->check(CLI::Validator(
          [](std::string& v) {
            return v.find_first_not_of(" \t") == std::string::npos
                       ? std::string("the phrase is empty; give one listed in the --vocab file, e.g. --text "
                                     "\"red mug\"")
                       : std::string();
          },
          "PHRASE"));
  sub->add_option("--vocab", r.vocab, "Text vocabulary JSON {\"phrase\": [D floats], ...}");
  sub->add_option("--text-embedding", r.text_embedding, "Text query by a float vector .npy of shape [D] or [1,D]");
  sub->add_option("--click-by", r.click_by,
                  "How a click selects: features (grow over trained features), support (what stands on the "
                  "scene's main plane, for models trained without SAM masks), auto (support when the model has "
                  "no trained features)")
      ->check(CLI::IsMember({"auto", "features", "support"}));
}

void prepare_click(QueryEngine& engine, const std::string& click_by, const nlohmann::json& model_meta,
                   const Scene& scene, nlohmann::json* j) {
  int stage = 2;  // a model without a training record: assume trained features
  if (model_meta.contains("train") && model_meta["train"].contains("stage") &&
      model_meta["train"]["stage"].is_number_integer())
    stage = model_meta["train"]["stage"].get<int>();
  const bool untrained = stage < 2;
  if (click_by == "features" || (click_by == "auto" && !untrained)) {
    if (untrained)
      spdlog::warn(
          "the model's features were never trained (stage {}): a click grows over most of the scene; "
          "--click-by support selects what stands on the floor or table instead",
          stage);
    (*j)["click_by"] = "features";
    return;
  }
  std::vector<Camera> cameras;
  for (int v : scene.train_views()) cameras.push_back(scene.views()[v].camera);
  SceneUp up;
  try {
    up = scene_up(cameras, scene.points());
  } catch (const std::runtime_error&) {  // no plane, and cameras that disagree on up: no plane either way
    up.from_plane = false;
  }
  if (!up.from_plane) {
    if (click_by == "support")
      throw std::runtime_error(
          "--click-by support: the SfM points of the scene show no floor or table plane under "
          "the cameras; select by --selection FILE, or train with SAM masks and click by "
          "features");
    spdlog::warn(
        "the model's features were never trained and the scene shows no floor plane: the click grows over "
        "the features, which select most of the scene");
    (*j)["click_by"] = "features";
    return;
  }
  engine.set_support(*up.plane);
  (*j)["click_by"] = "support";
  (*j)["support_plane"] = {{"normal", {up.up(0), up.up(1), up.up(2)}},
                           {"offset", up.plane->offset},
                           {"points", up.plane->inliers},
                           {"tolerance", up.plane->tolerance},
                           {"image_axis", up.image_axis}};
  spdlog::info("click by the support plane{}: {}; the selection is what stands on it, joined to the clicked point",
               untrained ? " (the model's features were never trained: no SAM masks)" : "", up.describe());
}

void register_query(CLI::App& app, GlobalOptions& global) {
  auto a = std::make_shared<QueryArgs>();
  auto* q = app.add_subcommand("query", "Select an object by a click or by text; write its Gaussians and masks");
  q->add_option("model", a->model, "Model folder written by `ag2gs train` (MODEL_DIR/model.ag2gs)")->required();
  q->add_option("--scene", a->scene, "Scene directory (images/, sparse/0/) the model was trained on")->required();
  q->add_option("-o,--out", a->out, "Output folder: selection.ply, remainder.ply, selection.json, masks/")
      ->check(output_path())
      ->required();
  add_query_request_options(q, a->request);
  q->add_flag("--force", a->force,
              "Replace the results of an earlier query in OUT (default: refused, so a second query does not "
              "overwrite the first)");
  q->add_option("--views", a->views,
                "Also write masks for: train, test (every 8th image in name order), all, or comma-separated names");
  q->add_option("--sparse", a->sparse,
                "COLMAP model folder inside the scene (default: sparse/0/, else sparse/ when it holds the model)");
  q->add_option("-r,--resolution", a->resolution, "Divide the cameras by R (default: the model's training -r)")
      ->check(CLI::Range(1, 64));
  add_query_config_options(q, a->config);
  auto print_config = add_print_config_flag(q, "query");
  set_action(q, [&global, a, print_config] {
    if (*print_config) return print_config_json(a->config);
    cmd_query(global, *a);
  });
}

}  // namespace ag2gs::cli
