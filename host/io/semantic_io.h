// The JSON inputs of queries and evaluation (docs/formats.md): a text
// vocabulary of CLIP embeddings, LERF-OVS label frames (labelme polygons) and
// click lists. Every reader validates fully and throws std::runtime_error
// naming the file, the entry and what to fix.
#pragma once

#include <map>
#include <string>
#include <vector>

namespace ag2gs {

// {"phrase": [D floats], ...}: every embedding of the same dimension D >= 1,
// finite, not all zero.
struct Vocabulary {
  int dim = 0;
  std::map<std::string, std::vector<float>> phrases;
  // The embeddings of every phrase but `phrase`, in phrase order: the
  // rivals a text query is ranked against (QueryEngine::text).
  std::vector<std::vector<float>> others(const std::string& phrase) const;
};
Vocabulary read_vocabulary(const std::string& path);

// labelme-style LERF-OVS frame: {"info": {"width", "height", "name"},
// "objects": [{"category", "segmentation": [[x, y], ...], "bbox"}]}.
struct LabelObject {
  std::string category;
  std::vector<std::pair<double, double>> polygon;  // at least 3 points
};
struct LabelFrame {
  int width = 0;
  int height = 0;
  std::string name;  // frame name from info.name (may be an image file name)
  std::vector<LabelObject> objects;

  // Categories present, sorted and unique.
  std::vector<std::string> categories() const;
  // The category's GT mask [H,W] (0/1): the union of its filled polygons.
  std::vector<unsigned char> mask(const std::string& category) const;
};
LabelFrame read_label_frame(const std::string& path);

// [{"frame": "name", "x": px, "y": py, "category": optional}, ...]
struct Click {
  std::string frame;
  double x = 0, y = 0;
  std::string category;  // empty when not given
};
std::vector<Click> read_clicks(const std::string& path);

}  // namespace ag2gs
