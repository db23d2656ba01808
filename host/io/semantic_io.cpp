#include "host/io/semantic_io.h"
#include "host/io/json_input.h"

#include <algorithm>
#include <cmath>
#include <fstream>
#include <nlohmann/json.hpp>
#include <opencv2/imgproc.hpp>
#include <set>
#include <sstream>
#include <stdexcept>

namespace ag2gs {
namespace {

using nlohmann::json;

[[noreturn]] void fail(const std::string& path, const std::string& what) {
  throw std::runtime_error(path + ": " + what);
}

json parse_file(const std::string& path) {
  return read_json_file(path);
}

double finite_number(const json& v, const std::string& path, const std::string& what) {
  if (!v.is_number()) fail(path, what + " is not a number");
  const double d = v.get<double>();
  if (!std::isfinite(d)) fail(path, what + " is not finite");
  return d;
}

}  // namespace

std::vector<std::vector<float>> Vocabulary::others(const std::string& phrase) const {
  std::vector<std::vector<float>> out;
  for (const auto& [p, e] : phrases)
    if (p != phrase) out.push_back(e);
  return out;
}

Vocabulary read_vocabulary(const std::string& path) {
  const json j = parse_file(path);
  if (!j.is_object() || j.empty()) {
    fail(path, "a vocabulary is a JSON object {\"phrase\": [512 floats], ...} with at least one phrase");
  }
  Vocabulary vocab;
  for (auto it = j.begin(); it != j.end(); ++it) {
    const std::string who = "phrase '" + it.key() + "'";
    if (!it.value().is_array() || it.value().empty()) fail(path, who + ": the embedding must be a list of numbers");
    std::vector<float> e;
    double norm2 = 0;
    for (size_t i = 0; i < it.value().size(); ++i) {
      const double d = finite_number(it.value()[i], path, who + " element " + std::to_string(i));
      e.push_back(static_cast<float>(d));
      norm2 += d * d;
    }
    if (norm2 == 0) fail(path, who + ": the embedding is all zeros");
    if (vocab.dim == 0) vocab.dim = static_cast<int>(e.size());
    if (static_cast<int>(e.size()) != vocab.dim) {
      fail(path, who + " has " + std::to_string(e.size()) + " dimensions but earlier phrases have " +
                     std::to_string(vocab.dim) + "; all embeddings must come from one CLIP model");
    }
    vocab.phrases[it.key()] = std::move(e);
  }
  return vocab;
}

std::vector<std::string> LabelFrame::categories() const {
  std::set<std::string> s;
  for (const LabelObject& o : objects) s.insert(o.category);
  return {s.begin(), s.end()};
}

std::vector<unsigned char> LabelFrame::mask(const std::string& category) const {
  cv::Mat m = cv::Mat::zeros(height, width, CV_8U);
  for (const LabelObject& o : objects) {
    if (o.category != category) continue;
    std::vector<cv::Point> pts;
    for (const auto& [x, y] : o.polygon) {
      pts.emplace_back(static_cast<int>(std::lround(x)), static_cast<int>(std::lround(y)));
    }
    cv::fillPoly(m, std::vector<std::vector<cv::Point>>{pts}, cv::Scalar(1));
  }
  return std::vector<unsigned char>(m.data, m.data + m.total());
}

LabelFrame read_label_frame(const std::string& path) {
  const json j = parse_file(path);
  LabelFrame f;
  if (!j.is_object() || !j.contains("info") || !j.contains("objects")) {
    fail(path, "a label frame is {\"info\": {\"width\", \"height\", \"name\"}, \"objects\": [...]} (LERF-OVS)");
  }
  const json& info = j["info"];
  if (!info.is_object()) fail(path, "'info' must be an object with width, height and name");
  const double w = info.contains("width") ? finite_number(info["width"], path, "info.width") : 0;
  const double h = info.contains("height") ? finite_number(info["height"], path, "info.height") : 0;
  if (!(w >= 1 && h >= 1 && w <= 1 << 16 && h <= 1 << 16) || w != std::floor(w) || h != std::floor(h)) {
    fail(path, "info.width and info.height must be positive integers up to 65536");
  }
  f.width = static_cast<int>(w);
  f.height = static_cast<int>(h);
  if (info.contains("name")) {
    if (!info["name"].is_string()) fail(path, "info.name must be a string");
    f.name = info["name"].get<std::string>();
  }
  if (!j["objects"].is_array()) fail(path, "'objects' must be a list");
  for (size_t i = 0; i < j["objects"].size(); ++i) {
    const json& o = j["objects"][i];
    const std::string who = "objects[" + std::to_string(i) + "]";
    if (!o.is_object() || !o.contains("category") || !o["category"].is_string()) {
      fail(path, who + " needs a string 'category'");
    }
    LabelObject obj;
    obj.category = o["category"].get<std::string>();
    if (!o.contains("segmentation") || !o["segmentation"].is_array()) {
      fail(path, who + " ('" + obj.category + "') needs 'segmentation': [[x, y], ...]");
    }
    for (size_t k = 0; k < o["segmentation"].size(); ++k) {
      const json& p = o["segmentation"][k];
      if (!p.is_array() || p.size() != 2)
        fail(path, who + " segmentation point " + std::to_string(k) + " is not [x, y]");
      obj.polygon.emplace_back(finite_number(p[0], path, who + " x"), finite_number(p[1], path, who + " y"));
    }
    if (obj.polygon.size() < 3) fail(path, who + " ('" + obj.category + "') has fewer than 3 polygon points");
    // Pixel coordinates of this frame: a polygon that misses the image
    // would score as an object with no pixels (labels made at another
    // size, or x and y swapped).
    double x0 = obj.polygon[0].first, x1 = x0, y0 = obj.polygon[0].second, y1 = y0;
    for (const auto& [x, y] : obj.polygon) {
      x0 = std::min(x0, x), x1 = std::max(x1, x), y0 = std::min(y0, y), y1 = std::max(y1, y);
      if (std::abs(x) > 64.0 * w || std::abs(y) > 64.0 * h)
        fail(path, who + " ('" + obj.category + "') has the point (" + std::to_string(x) + ", " + std::to_string(y) +
                       "), far outside the " + std::to_string(f.width) + "x" + std::to_string(f.height) +
                       " image of info.width/height; polygons are in that image's pixels");
    }
    if (x1 < 0 || y1 < 0 || x0 > w || y0 > h)
      fail(path, who + " ('" + obj.category + "') lies outside the " + std::to_string(f.width) + "x" +
                     std::to_string(f.height) + " image of info.width/height (its points span x " +
                     std::to_string(x0) + ".." + std::to_string(x1) + ", y " + std::to_string(y0) + ".." +
                     std::to_string(y1) + "); were the labels made at another image size?");
    f.objects.push_back(std::move(obj));
  }
  return f;
}

std::vector<Click> read_clicks(const std::string& path) {
  const json j = parse_file(path);
  if (!j.is_array()) fail(path, "a click list is a JSON array of {\"frame\", \"x\", \"y\", \"category\"?}");
  std::vector<Click> clicks;
  for (size_t i = 0; i < j.size(); ++i) {
    const json& c = j[i];
    const std::string who = "click " + std::to_string(i);
    if (!c.is_object() || !c.contains("frame") || !c["frame"].is_string() || !c.contains("x") || !c.contains("y")) {
      fail(path, who + " needs \"frame\" (a string), \"x\" and \"y\" (pixels)");
    }
    Click k;
    k.frame = c["frame"].get<std::string>();
    k.x = finite_number(c["x"], path, who + " x");
    k.y = finite_number(c["y"], path, who + " y");
    if (c.contains("category")) {
      if (!c["category"].is_string()) fail(path, who + " category must be a string");
      k.category = c["category"].get<std::string>();
    }
    clicks.push_back(k);
  }
  return clicks;
}

}  // namespace ag2gs
