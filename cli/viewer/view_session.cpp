#include "cli/viewer/view_session.h"

#include <spdlog/spdlog.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "cli/render_colours.h"
#include "host/core/timing.h"
#include "host/io/colmap_reader.h"
#include "host/io/ply_io.h"
#include "host/io/semantic_io.h"
#include "host/scene/scene_up.h"
#include "train/train_common.h"

namespace fs = std::filesystem;

namespace ag2gs::cli {
namespace {

// The selection's highlight: an orange tint inside, a solid outline.
constexpr float kTint[3] = {1.0f, 0.55f, 0.1f};
constexpr float kTintWeight = 0.55f;

std::string format_click(double x, double y) {
  char buf[96];
  std::snprintf(buf, sizeof buf, "%.17g,%.17g", x, y);
  return buf;
}

}  // namespace

ViewMode parse_view_mode(const std::string& s) {
  if (s == "rgb") return ViewMode::rgb;
  if (s == "depth") return ViewMode::depth;
  if (s == "feature") return ViewMode::feature;
  if (s == "instance") return ViewMode::instance;
  if (s == "selection") return ViewMode::selection;
  throw std::invalid_argument("mode '" + s + "': choose rgb, depth, feature, instance or selection");
}

Visibility parse_visibility(const std::string& s) {
  if (s == "show") return Visibility::show;
  if (s == "hide") return Visibility::hide;
  if (s == "only") return Visibility::only;
  throw std::invalid_argument("selection '" + s + "': choose show, hide or only");
}

const char* visibility_name(Visibility v) {
  switch (v) {
    case Visibility::hide: return "hide";
    case Visibility::only: return "only";
    default: return "show";
  }
}

ViewSession::ViewSession(Runtime& rt, const ViewOptions& options)
    : ViewSession(rt, options, load_trained_model(options.model, false)) {}

ViewSession::ViewSession(Runtime& rt, const ViewOptions& options, TrainedModel trained)
    : rt_(rt), options_(options), trained_(std::move(trained)), renderer_(rt), shown_(rt), sky_(rt) {
  const AnchorModel& model = trained_.model;
  if (model.size() == 0) throw std::runtime_error(trained_.file + " holds no anchors; there is nothing to view");
  const nlohmann::json& meta = trained_.archive.meta;
  const bool has_clusters = meta.contains("clusters");
  if (has_clusters) {
    trained_.clustering = clustering_from_archive(trained_.archive, model.size());
    instances_ = std::make_unique<InstanceMapper>(rt);
    instances_->set_clusters(trained_.clustering.anchor_cluster, model.children());
  }
  resolution_ = options.resolution > 0 ? options.resolution : trained_.resolution;

  if (!options.scene.empty()) {
    SceneOptions so;
    so.resolution = resolution_;
    so.eval = trained_.eval_split;
    so.sparse = options.sparse;
    scene_ = Scene::open(options.scene, so);
  }
  if (!options.training) engine_ = std::make_unique<QueryEngine>(rt, model, QueryConfig{});
  if (!options.vocab.empty() && !options.training) {
    if (!has_clusters || !meta.contains("language"))
      throw std::runtime_error(trained_.file +
                               " has no clusters/language features, which text queries need (--vocab): run stages "
                               "2 and 3 on it (`ag2gs train SCENE_DIR -o MODEL_DIR --stages 2,3`), or view it "
                               "without --vocab and select by clicking");
    trained_.language = language_from_archive(trained_.archive, trained_.clustering.clusters());
    vocab_ = read_vocabulary(options.vocab);
    if (vocab_.dim != trained_.language.dim)
      throw std::runtime_error(options.vocab + ": embeddings of " + std::to_string(vocab_.dim) +
                               " dimensions, the language features in " + trained_.file + " have " +
                               std::to_string(trained_.language.dim) +
                               " (use the CLIP model that made the scene's features)");
    engine_->set_language(trained_.clustering, trained_.language);
    text_ready_ = true;
  }

  if (scene_ && engine_) {  // clicks as `ag2gs query --click-by auto` makes them
    nlohmann::json how;
    prepare_click(*engine_, "auto", meta, *scene_, &how);
  }

  colours_ = expand_reference(model, trained_.sh_degree);
  if (const auto sky = sky_from_archive(trained_.archive)) sky_.set(sky_degree_for(sky->size()), *sky);
  in_selection_.assign(model.size(), 0);

  // The scene's centre and radius for an orbiting camera: the anchors'
  // per-axis median and the 90th percentile of their distances to it
  // (robust to a few far anchors).
  const std::vector<float>& pos = model.pos();
  const size_t n = model.size();
  for (int c = 0; c < 3; ++c) {
    std::vector<float> v(n);
    for (size_t a = 0; a < n; ++a) v[a] = pos[3 * a + c];
    std::nth_element(v.begin(), v.begin() + n / 2, v.end());
    centre_[c] = v[n / 2];
  }
  std::vector<double> d(n);
  for (size_t a = 0; a < n; ++a)
    d[a] = (Eigen::Vector3d(pos[3 * a], pos[3 * a + 1], pos[3 * a + 2]) - centre_).norm();
  const size_t k = std::min(n - 1, n * 9 / 10);
  std::nth_element(d.begin(), d.begin() + k, d.end());
  radius_ = std::max(d[k], 1e-6);

  // The scene's up, for an orbit that keeps the horizon level: the floor
  // plane's normal or the cameras' mean up (host/scene/scene_up.h).
  if (scene_ && !scene_->views().empty()) {
    std::vector<Camera> cameras;
    for (const SceneView& v : scene_->views()) cameras.push_back(v.camera);
    std::vector<Eigen::Vector3d> points(n);
    for (size_t a = 0; a < n; ++a) points[a] = Eigen::Vector3d(pos[3 * a], pos[3 * a + 1], pos[3 * a + 2]);
    try {
      up_ = scene_up(cameras, points).up;
    } catch (const std::runtime_error& e) {
      spdlog::info("view: no scene up ({}); orbiting about the first view's up", e.what());
    }
  }
}

nlohmann::json ViewSession::info() const {
  const AnchorModel& model = trained_.model;
  nlohmann::json j;
  j["model"] = trained_.file;
  j["anchors"] = model.size();
  j["gaussians"] = model.gaussians();
  j["children"] = model.children();
  j["sh_degree"] = trained_.sh_degree;
  j["resolution"] = resolution_;
  j["clusters"] = trained_.clustering.clusters();
  j["instance_maps"] = instances_ != nullptr;
  j["text_queries"] = text_ready_;
  j["queries"] = engine_ != nullptr;
  nlohmann::json phrases = nlohmann::json::array();
  for (const auto& [phrase, v] : vocab_.phrases) phrases.push_back(phrase);
  j["phrases"] = phrases;
  j["sky"] = sky_.enabled();
  j["centre"] = {centre_.x(), centre_.y(), centre_.z()};
  j["radius"] = radius_;
  if (up_) j["up"] = {up_->x(), up_->y(), up_->z()};
  j["selection"] = {{"anchors", selected_.size()}, {"gaussians", selected_.size() * model.children()}};
  j["visibility"] = visibility_name(visibility_);
  j["modes"] = {"rgb", "depth", "feature", "instance", "selection"};
  nlohmann::json views = nlohmann::json::array();
  if (scene_) {
    for (const SceneView& v : scene_->views()) {
      const Camera& c = v.camera;
      nlohmann::json R = nlohmann::json::array();
      for (int r = 0; r < 3; ++r)
        for (int col = 0; col < 3; ++col) R.push_back(c.R(r, col));
      views.push_back({{"name", v.name},
                       {"stem", v.stem},
                       {"width", c.width},
                       {"height", c.height},
                       {"full_width", v.full_camera.width},
                       {"full_height", v.full_camera.height},
                       {"fx", c.fx},
                       {"fy", c.fy},
                       {"cx", c.cx},
                       {"cy", c.cy},
                       {"R", R},
                       {"t", {c.t.x(), c.t.y(), c.t.z()}},
                       {"test", v.test}});
    }
  }
  j["views"] = views;
  return j;
}

Camera ViewSession::view_camera(const std::string& name) const {
  if (!scene_)
    throw std::invalid_argument("view '" + name + "': the viewer was started without --scene, so it has no views");
  try {
    return scene_->views()[scene_->find_view(name)].camera;
  } catch (const std::exception& e) {
    throw std::invalid_argument(e.what());
  }
}

namespace {
void check_view_size(int width, int height) {
  if (width < 1 || height < 1 || width > kMaxViewSide || height > kMaxViewSide)
    throw std::invalid_argument("w, h: each from 1 to " + std::to_string(kMaxViewSide) + ", not " +
                                std::to_string(width) + "x" + std::to_string(height));
  if (static_cast<int64_t>(width) * height > kMaxViewPixels)
    throw std::invalid_argument("w x h: at most " + std::to_string(kMaxViewPixels) + " pixels (3840x2160), not " +
                                std::to_string(width) + "x" + std::to_string(height) + "; ask for a smaller picture");
}
}  // namespace

Camera ViewSession::resized(const Camera& camera, int width, int height) {
  check_view_size(width, height);
  return resize_camera(camera, width, height);
}

Camera ViewSession::pose_camera(const std::vector<double>& p, double fx, double fy, double cx, double cy, int width,
                                int height) {
  if (p.size() != 12)
    throw std::invalid_argument("pose: expected 12 numbers (R11,R12,...,R33,t1,t2,t3: world to camera), got " +
                                std::to_string(p.size()));
  for (double v : p)
    if (!std::isfinite(v)) throw std::invalid_argument("pose: every number must be finite");
  check_view_size(width, height);
  if (!(std::isfinite(fx) && std::isfinite(fy) && fx > 0 && fy > 0 && std::isfinite(cx) && std::isfinite(cy)))
    throw std::invalid_argument("fx, fy must be finite and > 0, cx, cy finite");
  Camera c;
  for (int r = 0; r < 3; ++r)
    for (int col = 0; col < 3; ++col) c.R(r, col) = p[3 * r + col];
  c.t = Eigen::Vector3d(p[9], p[10], p[11]);
  const double off = (c.R.transpose() * c.R - Eigen::Matrix3d::Identity()).cwiseAbs().maxCoeff();
  if (off > 1e-3 || c.R.determinant() < 0)
    throw std::invalid_argument("pose: R is not a rotation (|R^T R - I| = " + std::to_string(off) +
                                ", det " + std::to_string(c.R.determinant()) + ")");
  c.fx = fx;
  c.fy = fy;
  c.cx = cx;
  c.cy = cy;
  c.width = width;
  c.height = height;
  c.name = "pose";
  return c;
}

void ViewSession::upload_shown() {
  if (!shown_dirty_) return;
  if (visibility_ == Visibility::show) {
    shown_.upload(colours_);
  } else {
    // Hidden Gaussians keep their rows with opacity 0, so the set stays
    // [A*K] as the instance maps need.
    GaussianSet g = colours_;
    const int k = trained_.model.children();
    const bool keep_selected = visibility_ == Visibility::only;
    for (size_t a = 0; a < in_selection_.size(); ++a)
      if ((in_selection_[a] != 0) != keep_selected)
        for (int i = 0; i < k; ++i) g.opacities[a * k + i] = 0.f;
    shown_.upload(g);
  }
  shown_dirty_ = false;
}

std::vector<uint8_t> ViewSession::render_image(const Camera& camera, ViewMode mode, int quality, bool png, double* ms) {
  if (quality < 1 || quality > 100) throw std::invalid_argument("quality: from 1 to 100");
  if (mode == ViewMode::instance && !instances_)
    throw std::invalid_argument(trained_.file + " has no clusters (stage 3), which mode=instance needs");
  const auto t0 = std::chrono::steady_clock::now();
  upload_shown();
  RenderSettings settings;
  settings.features = mode == ViewMode::feature;
  renderer_.forward(shown_, camera, settings);
  RenderOutput out = renderer_.download_output();
  const int w = out.width, h = out.height;
  const size_t pixels = static_cast<size_t>(w) * h;
  std::vector<float> rgb;
  switch (mode) {
    case ViewMode::rgb:
    case ViewMode::selection:
      if (sky_.enabled()) composite_sky(renderer_, sky_, camera, out);
      rgb = std::move(out.rgb);
      break;
    case ViewMode::feature:
      rgb = feature_colours(out.feature, out.alpha);
      break;
    case ViewMode::instance:
      instances_->compute(renderer_);
      rgb = instance_colours(instances_->download().ids);
      break;
    case ViewMode::depth: {
      // Inverse mean depth, stretched between its 2nd and 98th percentiles
      // over the covered pixels; black where nothing was hit.
      std::vector<float> inv(pixels, 0.f), valid;
      for (size_t p = 0; p < pixels; ++p)
        if (out.alpha[p] > 0.05f && out.depth[p] > 0) {
          inv[p] = out.alpha[p] / out.depth[p];
          valid.push_back(inv[p]);
        }
      float lo = 0, hi = 1;
      if (!valid.empty()) {
        std::sort(valid.begin(), valid.end());
        lo = valid[valid.size() * 2 / 100];
        hi = valid[valid.size() * 98 / 100];
        if (!(hi > lo)) hi = lo + 1e-6f;
      }
      cv::Mat grey(h, w, CV_8UC1), colour;
      for (size_t p = 0; p < pixels; ++p)
        grey.data[p] = static_cast<uint8_t>(std::lround(255.f * std::clamp((inv[p] - lo) / (hi - lo), 0.f, 1.f)));
      cv::applyColorMap(grey, colour, cv::COLORMAP_TURBO);
      rgb.assign(3 * pixels, 0.f);
      for (size_t p = 0; p < pixels; ++p) {
        if (inv[p] == 0.f) continue;
        for (int c = 0; c < 3; ++c) rgb[3 * p + c] = colour.data[3 * p + 2 - c] / 255.f;
      }
      break;
    }
  }
  // Hidden, the selection is not drawn, so the highlight would paint over
  // what the removal preview shows in its place.
  if (mode == ViewMode::selection && !selected_.empty() && visibility_ != Visibility::hide) {
    const std::vector<uint8_t> m = engine().mask(camera, selected_);
    for (int y = 0; y < h; ++y)
      for (int x = 0; x < w; ++x) {
        const size_t p = static_cast<size_t>(y) * w + x;
        if (!m[p]) continue;
        const bool edge = x == 0 || y == 0 || x == w - 1 || y == h - 1 || !m[p - 1] || !m[p + 1] || !m[p - w] ||
                          !m[p + w];
        for (int c = 0; c < 3; ++c)
          rgb[3 * p + c] = edge ? kTint[c] : (1 - kTintWeight) * rgb[3 * p + c] + kTintWeight * kTint[c];
      }
  }
  cv::Mat bgr(h, w, CV_8UC3);
  for (size_t p = 0; p < pixels; ++p)
    for (int c = 0; c < 3; ++c) {
      const float v = rgb[3 * p + c];
      bgr.data[3 * p + 2 - c] = static_cast<uint8_t>(std::lround(std::clamp(std::isfinite(v) ? v : 0.f, 0.f, 1.f) * 255));
    }
  std::vector<uint8_t> bytes;
  if (png ? !cv::imencode(".png", bgr, bytes) : !cv::imencode(".jpg", bgr, bytes, {cv::IMWRITE_JPEG_QUALITY, quality}))
    throw std::runtime_error(std::string("could not encode the picture as ") + (png ? "PNG" : "JPEG"));
  if (ms) *ms = ms_since(t0);
  return bytes;
}

nlohmann::json ViewSession::finish_query(std::vector<int32_t> selected, double ms, nlohmann::json detail) {
  selected_ = std::move(selected);
  std::fill(in_selection_.begin(), in_selection_.end(), 0);
  for (int32_t a : selected_) in_selection_[a] = 1;
  if (visibility_ != Visibility::show) shown_dirty_ = true;
  detail["anchors"] = selected_.size();
  detail["gaussians"] = selected_.size() * trained_.model.children();
  detail["ms"] = ms;
  return detail;
}

nlohmann::json ViewSession::click_view(const std::string& view, double x, double y) {
  if (!scene_)
    throw std::invalid_argument("a click in a training view needs the scene: start the viewer with --scene SCENE_DIR");
  QueryRequest r;
  r.view = view;
  r.click = format_click(x, y);
  try {
    (void)scene_->find_view(view);
  } catch (const std::exception& e) {
    throw std::invalid_argument(e.what());
  }
  nlohmann::json j;
  double ms = 0;
  std::vector<int32_t> selected;
  try {
    selected = run_query(engine(), *scene_, r, {}, resolution_, engine().config().text_margin, j, &ms);
  } catch (const std::runtime_error& e) {
    throw std::invalid_argument(e.what());  // the click hit the background
  }
  return finish_query(std::move(selected), ms, {{"query", j["query"]}});
}

nlohmann::json ViewSession::click_camera(const Camera& camera, double x, double y) {
  ClickResult c;
  try {
    c = engine().click(camera, x, y);
  } catch (const std::runtime_error& e) {
    throw std::invalid_argument(e.what());
  }
  nlohmann::json q = {{"type", "click"}, {"x", x}, {"y", y}, {"alpha", c.alpha}, {"depth", c.depth},
                      {"seed", c.seed}};
  return finish_query(std::move(c.selected), c.ms, {{"query", q}});
}

nlohmann::json ViewSession::text(const std::string& phrase) {
  if (!text_ready_)
    throw std::invalid_argument("text queries need a vocabulary: start the viewer with --vocab FILE.json (phrase -> "
                                "CLIP embedding) on a model with stage 3");
  if (phrase.find_first_not_of(" \t") == std::string::npos)
    throw std::invalid_argument("the phrase is empty; give one of the vocabulary's phrases");
  QueryRequest r;
  r.text = phrase;
  r.vocab = options_.vocab;
  const std::vector<float> embedding = load_query_embedding(r, trained_.file, trained_.language.dim);
  // As run_query's text branch: the engine's selection for the embedding.
  TextResult t = engine().text(embedding, load_rival_embeddings(r));
  nlohmann::json q = {{"type", "text"}, {"text", phrase}};
  return finish_query(std::move(t.selected), t.ms, {{"query", q}, {"best_score", t.best}, {"none", t.none}});
}

QueryEngine& ViewSession::engine() {
  if (!engine_)
    throw std::invalid_argument("selecting is possible once training has ended (the model changes while it trains)");
  return *engine_;
}

void ViewSession::clear() {
  selected_.clear();
  std::fill(in_selection_.begin(), in_selection_.end(), 0);
  if (visibility_ != Visibility::show) shown_dirty_ = true;
}

void ViewSession::set_visibility(Visibility v) {
  if (v != visibility_) shown_dirty_ = true;
  visibility_ = v;
}

std::vector<uint8_t> ViewSession::mask_png(const Camera& cam) {
  return encode_mask_png(engine().mask(cam, selected_), cam.width, cam.height);
}

std::vector<uint8_t> ViewSession::selection_ply() const {
  if (selected_.empty()) throw std::invalid_argument("nothing is selected: click an object or run a text query first");
  const GaussianSet sel = gaussians_of_anchors(trained_.model, trained_.sh_degree, in_selection_, true);
  // write_ply writes files: through a private temporary one.
  char dir[] = "/tmp/ag2gs_view_XXXXXX";
  if (!::mkdtemp(dir)) throw std::runtime_error("could not create a temporary folder for the selection's PLY");
  const fs::path file = fs::path(dir) / "selection.ply";
  std::vector<uint8_t> bytes;
  try {
    write_ply(file.string(), sel, true);
    std::ifstream in(file, std::ios::binary);
    bytes.assign(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
  } catch (...) {
    fs::remove_all(dir);
    throw;
  }
  fs::remove_all(dir);
  return bytes;
}

}  // namespace ag2gs::cli
