#include "apps/selection/selection.h"

#include <spdlog/spdlog.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <stdexcept>
#include <string>

#include "host/core/text.h"
#include "host/core/timing.h"
#include "host/io/npy_io.h"
#include "host/io/semantic_io.h"
#include "host/scene/scene_up.h"
#include "train/graph/anchor_graph.h"
#include "train/model_check.h"

namespace fs = std::filesystem;

namespace ag2gs {

namespace {

nlohmann::json finite_or_null(double v) {
  return std::isfinite(v) ? nlohmann::json(v) : nlohmann::json(nullptr);
}

}  // namespace

void parse_click(const std::string& s, double* x, double* y) {
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
    if (t.none && t.best < engine.config().text_threshold)
      spdlog::warn(
          "text: \"{}\" names nothing here: its best cosine {:.4f} is below --text-threshold {}; nothing "
          "is selected",
          r.text, t.best, engine.config().text_threshold);
    else if (t.none)
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

std::string anchor_fingerprint(const AnchorModel& model) {
  const uint64_t h = AnchorGraph::anchor_fingerprint(model);  // the graph's own tie to its anchors
  char hex[17];
  std::snprintf(hex, sizeof hex, "%016llx", static_cast<unsigned long long>(h));
  return hex;
}

std::vector<int> pick_scene_views(const Scene& scene, const std::string& views) {
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

SelectionResult select_object(Runtime& rt, const SelectionRequest& r) {
  check_query_request(r.query);
  r.config.validate();
  const bool by_click = r.query.by_click(), by_text = r.query.by_text();
  const auto t_load = std::chrono::steady_clock::now();
  const TrainedModel tm = load_trained_model(r.model, by_text);
  SelectionResult out;
  out.model_file = tm.file;
  out.model_anchors = tm.model.size();
  out.resolution = r.resolution > 0 ? r.resolution : tm.resolution;
  SceneOptions so;
  so.resolution = out.resolution;
  so.eval = true;  // test = every 8th view in name order, train = the rest
  so.sparse = r.sparse;
  std::unique_ptr<Scene> scene = Scene::open(r.scene, so);
  std::vector<int> views = pick_scene_views(*scene, r.mask_views);
  if (by_click) {
    const int click_view = scene->find_view(r.query.view);
    if (std::find(views.begin(), views.end(), click_view) == views.end()) views.insert(views.begin(), click_view);
  }
  std::vector<float> embedding;
  if (by_text) embedding = load_query_embedding(r.query, tm.file, tm.language.dim);

  QueryEngine engine(rt, tm.model, r.config);
  if (by_text) engine.set_language(tm.clustering, tm.language);
  nlohmann::json& j = out.record;
  if (by_click) prepare_click(engine, r.query.click_by, tm.archive.meta, *scene, &j);
  const double load_ms = ms_since(t_load);
  spdlog::info(
      "model {}: {} anchors, {} Gaussians; query graph (cell scale {}) {} edges; loaded and prepared in "
      "{:.0f} ms (graph, k-d tree and upload {:.0f} ms)",
      tm.file, tm.model.size(), tm.model.gaussians(), r.config.graph_cell_scale, engine.graph().edges(), load_ms,
      engine.prepare_ms());
  j["model"] = tm.file;
  j["anchor_fingerprint"] = anchor_fingerprint(tm.model);
  j["scene"] = r.scene;
  j["resolution"] = out.resolution;
  j["thresholds"] = {{"min_weight", r.config.min_weight},
                     {"tau", r.config.tau},
                     {"equivalent_feature_distance", r.config.equivalent_distance()},
                     {"graph_cell_scale", r.config.graph_cell_scale},
                     {"text_margin", r.config.text_margin},
                     {"text_threshold", r.config.text_threshold},
                     {"min_click_alpha", r.config.min_click_alpha},
                     {"click_candidates", r.config.click_candidates},
                     {"click_dominant", r.config.click_dominant},
                     {"click_front_weight", r.config.click_front_weight},
                     {"mask_threshold", r.config.mask_threshold}};
  out.anchors = run_query(engine, *scene, r.query, embedding, out.resolution, r.config.text_margin, j, &out.query_ms);

  std::vector<uint8_t> in_sel(tm.model.size(), 0);
  for (int32_t s : out.anchors) in_sel[s] = 1;
  out.selection = gaussians_of_anchors(tm.model, tm.sh_degree, in_sel, true);
  out.remainder = gaussians_of_anchors(tm.model, tm.sh_degree, in_sel, false);
  const auto t_mask = std::chrono::steady_clock::now();
  for (int v : views) {
    const SceneView& sv = scene->views()[v];
    SelectionResult::Mask m;
    m.view = sv.name;
    m.width = sv.camera.width;
    m.height = sv.camera.height;
    m.pixels = engine.mask(sv.camera, out.anchors);
    for (uint8_t p : m.pixels) m.on += p;
    out.masks.push_back(std::move(m));
  }
  j["anchors"] = out.anchors;
  j["anchor_count"] = out.anchors.size();
  j["gaussian_count"] = out.selection.size();
  j["remainder_anchor_count"] = tm.model.size() - out.anchors.size();
  j["remainder_gaussian_count"] = out.remainder.size();
  j["timing_ms"] = {{"load_and_prepare", load_ms},
                    {"prepare", engine.prepare_ms()},
                    {"query", out.query_ms},
                    {"masks", ms_since(t_mask)},
                    {"mask_views", views.size()}};
  return out;
}

}  // namespace ag2gs
