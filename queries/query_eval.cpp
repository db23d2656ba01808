#include "queries/query_eval.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <map>
#include <opencv2/imgproc.hpp>
#include <set>
#include <stdexcept>

#include "host/core/timing.h"

namespace fs = std::filesystem;

namespace ag2gs {
namespace {

// The view's full-size camera rescaled to width x height (the label frame's size).
Camera camera_at(const Camera& full, int width, int height) {
  Camera c = full;
  const double sx = static_cast<double>(width) / full.width, sy = static_cast<double>(height) / full.height;
  c.width = width;
  c.height = height;
  c.fx *= sx;
  c.cx *= sx;
  c.fy *= sy;
  c.cy *= sy;
  return c;
}

int count_ones(const std::vector<uint8_t>& m) {
  int n = 0;
  for (uint8_t v : m) n += v != 0;
  return n;
}

}  // namespace

double mask_iou(const std::vector<uint8_t>& pred, const std::vector<uint8_t>& gt) {
  if (pred.size() != gt.size())
    throw std::invalid_argument("mask_iou: masks of " + std::to_string(pred.size()) + " and " +
                                std::to_string(gt.size()) + " pixels");
  int64_t inter = 0, uni = 0;
  for (size_t i = 0; i < pred.size(); ++i) {
    const bool p = pred[i] != 0, g = gt[i] != 0;
    inter += p && g;
    uni += p || g;
  }
  return uni == 0 ? 1.0 : static_cast<double>(inter) / static_cast<double>(uni);
}

int boundary_width(int width, int height, double ratio) {
  const double diag = std::sqrt(static_cast<double>(width) * width + static_cast<double>(height) * height);
  return std::max(1, static_cast<int>(std::lround(ratio * diag)));
}

std::vector<uint8_t> mask_boundary(const std::vector<uint8_t>& mask, int width, int height, int d) {
  if (width < 1 || height < 1 || mask.size() != static_cast<size_t>(width) * height)
    throw std::invalid_argument("mask_boundary: mask of " + std::to_string(mask.size()) + " pixels for a " +
                                std::to_string(width) + "x" + std::to_string(height) + " image");
  if (d < 1) throw std::invalid_argument("mask_boundary: width d must be >= 1");
  cv::Mat m(height, width, CV_8U);
  for (size_t i = 0; i < mask.size(); ++i) m.data[i] = mask[i] ? 1 : 0;
  // A (2d+1)^2 square erosion with a zero border: a pixel survives when every
  // pixel within Chebyshev distance d is inside the image and the mask.
  cv::Mat eroded;
  cv::erode(m, eroded, cv::getStructuringElement(cv::MORPH_RECT, cv::Size(2 * d + 1, 2 * d + 1)),
            cv::Point(-1, -1), 1, cv::BORDER_CONSTANT, cv::Scalar(0));
  std::vector<uint8_t> out(mask.size());
  for (size_t i = 0; i < mask.size(); ++i) out[i] = m.data[i] && !eroded.data[i];
  return out;
}

double boundary_iou(const std::vector<uint8_t>& pred, const std::vector<uint8_t>& gt, int width, int height,
                    double ratio) {
  const int d = boundary_width(width, height, ratio);
  return mask_iou(mask_boundary(pred, width, height, d), mask_boundary(gt, width, height, d));
}

std::vector<NamedLabelFrame> read_label_dir(const std::string& dir) {
  if (!fs::is_directory(dir))
    throw std::runtime_error(dir + ": no such label folder; give the folder of LERF-style <frame>.json files "
                                   "(e.g. SCENE_DIR/label)");
  std::vector<fs::path> files;
  // Every *.json entry, folders too: read_label_frame names one that is not
  // a file (skipping it would score the queries on fewer frames, silently).
  for (const auto& e : fs::directory_iterator(dir))
    if (e.path().extension() == ".json") files.push_back(e.path());
  std::sort(files.begin(), files.end());
  if (files.empty())
    throw std::runtime_error(dir + ": no <frame>.json label files (labelme style: info + objects with polygons)");
  std::vector<NamedLabelFrame> out;
  for (const fs::path& f : files) out.push_back({f.stem().string(), read_label_frame(f.string())});
  return out;
}

QueryEvalSummary QueryEvalReport::summary(const std::string& kind, const std::string& frame) const {
  QueryEvalSummary s;
  for (const QueryEvalItem& q : items) {
    if (q.kind != kind || (!frame.empty() && q.frame != frame)) continue;
    ++s.count;
    s.mean_iou += q.iou;
    s.mean_biou += q.biou;
    s.mean_ms += q.select_ms + q.mask_ms;
    s.max_ms = std::max(s.max_ms, q.select_ms + q.mask_ms);
  }
  if (s.count > 0) {
    s.mean_iou /= s.count;
    s.mean_biou /= s.count;
    s.mean_ms /= s.count;
  }
  return s;
}

nlohmann::json QueryEvalReport::to_json() const {
  auto sum_json = [](const QueryEvalSummary& s) {
    return nlohmann::json{{"queries", s.count},
                          {"mean_iou", s.mean_iou},
                          {"mean_biou", s.mean_biou},
                          {"mean_ms", s.mean_ms},
                          {"max_ms", s.max_ms}};
  };
  nlohmann::json j;
  for (const char* kind : {"text", "click"}) {
    nlohmann::json list = nlohmann::json::array();
    for (const QueryEvalItem& q : items) {
      if (q.kind != kind) continue;
      nlohmann::json e = {{"frame", q.frame},
                          {"view", q.view},
                          {"category", q.category},
                          {"predicted", q.predicted},
                          {"iou", q.iou},
                          {"biou", q.biou},
                          {"selected_anchors", q.selected_anchors},
                          {"predicted_pixels", q.predicted_pixels},
                          {"gt_pixels", q.gt_pixels},
                          {"select_ms", q.select_ms},
                          {"mask_ms", q.mask_ms}};
      if (q.kind == "click") {
        e["x"] = q.x;
        e["y"] = q.y;
      }
      if (!q.note.empty()) e["note"] = q.note;
      list.push_back(e);
    }
    j[kind] = sum_json(summary(kind));
    j[kind]["items"] = list;
  }
  nlohmann::json frames_json = nlohmann::json::array();
  for (const std::string& f : frames)
    frames_json.push_back({{"frame", f}, {"text", sum_json(summary("text", f))}, {"click", sum_json(summary("click", f))}});
  j["frames"] = frames_json;
  j["unscored_clicks"] = unscored_clicks;
  if (!absent.empty()) {
    nlohmann::json list = nlohmann::json::array();
    size_t none = 0;
    for (const AbsentPhrase& a : absent) {
      none += a.none;
      list.push_back({{"phrase", a.phrase}, {"none", a.none}, {"selected_anchors", a.anchors}, {"best_score", a.best}});
    }
    j["absent"] = {{"phrases", absent.size()},
                   {"answered_none", none},
                   {"none_rate", static_cast<double>(none) / static_cast<double>(absent.size())},
                   {"items", list}};
  }
  return j;
}

QueryEvalReport evaluate_queries(QueryEngine& engine, const Scene& scene, const QueryEvalInputs& in) {
  QueryEvalReport report;
  std::map<std::string, const NamedLabelFrame*> by_stem;
  std::vector<int> frame_view;
  for (const NamedLabelFrame& f : in.frames) {
    int v = -1;
    try {
      v = scene.find_view(f.stem);
    } catch (const std::invalid_argument&) {
      try {
        v = scene.find_view(f.frame.name);
      } catch (const std::invalid_argument& e) {
        throw std::runtime_error("label frame " + f.stem + " (info.name \"" + f.frame.name +
                                 "\") names no image of the scene: " + e.what());
      }
    }
    frame_view.push_back(v);
    by_stem[f.stem] = &f;
    report.frames.push_back(f.stem);
  }
  auto score = [&](QueryEvalItem& q, const LabelFrame& lf, const std::vector<int32_t>* selected,
                   const Camera& cam) {
    const std::vector<uint8_t> gt = lf.mask(q.category);
    q.gt_pixels = count_ones(gt);
    if (!selected || selected->empty()) {
      q.predicted = false;
      if (q.note.empty()) q.note = "empty selection";
      return;  // scores 0
    }
    q.predicted = true;
    q.selected_anchors = selected->size();
    const auto t0 = std::chrono::steady_clock::now();
    const std::vector<uint8_t> pred = engine.mask(cam, *selected);
    q.mask_ms = ms_since(t0);
    q.predicted_pixels = count_ones(pred);
    q.iou = mask_iou(pred, gt);
    q.biou = boundary_iou(pred, gt, lf.width, lf.height, in.boundary_ratio);
  };

  // Text: one selection per category, scored in every frame that labels it;
  // each phrase against the vocabulary's others, as `ag2gs query` asks.
  if (in.vocab) {
    std::map<std::string, TextResult> selections;
    std::string no_text_reason;
    for (size_t fi = 0; fi < in.frames.size(); ++fi) {
      const NamedLabelFrame& f = in.frames[fi];
      const SceneView& view = scene.views()[frame_view[fi]];
      const Camera cam = camera_at(view.full_camera, f.frame.width, f.frame.height);
      for (const std::string& cat : f.frame.categories()) {
        auto it = selections.find(cat);
        QueryEvalItem q;
        q.kind = "text";
        q.frame = f.stem;
        q.view = view.name;
        q.category = cat;
        if (it == selections.end()) {
          const auto e = in.vocab->phrases.find(cat);
          if (e == in.vocab->phrases.end())
            throw std::invalid_argument("label frame " + f.stem + " has category \"" + cat +
                                        "\", which the vocabulary lacks; add its CLIP text embedding");
          TextResult tr;
          try {
            tr = engine.text(e->second, in.vocab->others(cat));
          } catch (const std::invalid_argument& err) {
            // No cluster carries a language feature: no prediction (scores 0).
            no_text_reason = err.what();
          }
          it = selections.emplace(cat, std::move(tr)).first;
          q.select_ms = it->second.ms;  // counted once, at the first frame that asks
        }
        if (it->second.selected.empty() && !no_text_reason.empty()) q.note = no_text_reason;
        if (it->second.none) q.note = "answered none: another phrase describes every cluster better";
        score(q, f.frame, &it->second.selected, cam);
        report.items.push_back(q);
      }
    }
  }

  // The vocabulary's phrases that no frame labels: each should answer none.
  if (in.vocab) {
    std::set<std::string> labelled;
    for (const NamedLabelFrame& f : in.frames)
      for (const std::string& cat : f.frame.categories()) labelled.insert(cat);
    for (const auto& [phrase, e] : in.vocab->phrases) {
      if (labelled.count(phrase)) continue;
      AbsentPhrase a;
      a.phrase = phrase;
      try {
        const TextResult tr = engine.text(e, in.vocab->others(phrase));
        a.none = tr.none;
        a.anchors = tr.selected.size();
        a.best = tr.best;
      } catch (const std::invalid_argument&) {
        a.none = true;  // no cluster has a language feature: nothing can be selected
      }
      report.absent.push_back(a);
    }
  }

  // Clicks: scored against the category's mask in the click's frame.
  for (const Click& c : in.clicks) {
    const auto it = by_stem.find(fs::path(c.frame).replace_extension().string());
    const auto it2 = it != by_stem.end() ? it : by_stem.find(c.frame);
    if (c.category.empty() || it2 == by_stem.end()) {
      ++report.unscored_clicks;
      continue;
    }
    const NamedLabelFrame& f = *it2->second;
    const size_t fi = static_cast<size_t>(&f - in.frames.data());
    const SceneView& view = scene.views()[frame_view[fi]];
    const Camera cam = camera_at(view.full_camera, f.frame.width, f.frame.height);
    QueryEvalItem q;
    q.kind = "click";
    q.frame = f.stem;
    q.view = view.name;
    q.category = c.category;
    q.x = c.x;
    q.y = c.y;
    if (!(c.x >= 0 && c.y >= 0 && c.x < view.full_camera.width && c.y < view.full_camera.height))
      throw std::invalid_argument("click (" + std::to_string(c.x) + ", " + std::to_string(c.y) + ") in frame " +
                                  c.frame + " lies outside its " + std::to_string(view.full_camera.width) + "x" +
                                  std::to_string(view.full_camera.height) + " image");
    const Eigen::Vector2d px = full_size_click(view.full_camera, cam, c.x, c.y);
    std::vector<int32_t> selected;
    const auto t0 = std::chrono::steady_clock::now();
    try {
      selected = engine.click(cam, px.x(), px.y()).selected;
    } catch (const std::runtime_error& e) {
      q.note = e.what();  // background: no prediction
    }
    q.select_ms = ms_since(t0);
    score(q, f.frame, q.note.empty() ? &selected : nullptr, cam);
    report.items.push_back(q);
  }
  return report;
}

}  // namespace ag2gs
