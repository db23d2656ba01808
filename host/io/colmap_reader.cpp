// COLMAP sparse model reader (binary and text) and camera helpers.
// File formats: https://colmap.github.io/format.html (binary layout as in
// COLMAP's scripts/python/read_write_model.py).
#include "host/io/colmap_reader.h"

#include <Eigen/Geometry>
#include <algorithm>
#include <cctype>
#include <climits>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <map>
#include <sstream>
#include <stdexcept>

namespace ag2gs {
namespace {

namespace fs = std::filesystem;

[[noreturn]] void fail(const std::string& path, const std::string& what) {
  throw std::runtime_error(path + ": " + what);
}

// COLMAP's camera model ids, names and parameter counts (src/colmap/sensor/models.h).
struct ModelInfo {
  int id;
  const char* name;
  int num_params;
};
constexpr ModelInfo kModels[] = {
    {0, "SIMPLE_PINHOLE", 3},
    {1, "PINHOLE", 4},
    {2, "SIMPLE_RADIAL", 4},
    {3, "RADIAL", 5},
    {4, "OPENCV", 8},
    {5, "OPENCV_FISHEYE", 8},
    {6, "FULL_OPENCV", 12},
    {7, "FOV", 5},
    {8, "SIMPLE_RADIAL_FISHEYE", 4},
    {9, "RADIAL_FISHEYE", 5},
    {10, "THIN_PRISM_FISHEYE", 12},
    {11, "RAD_TAN_THIN_PRISM_FISHEYE", 16},
};

const ModelInfo* model_by_id(int id) {
  for (const ModelInfo& m : kModels) {
    if (m.id == id) return &m;
  }
  return nullptr;
}
const ModelInfo* model_by_name(const std::string& name) {
  for (const ModelInfo& m : kModels) {
    if (name == m.name) return &m;
  }
  return nullptr;
}

constexpr const char* kUndistortHint =
    "ag2gs renders only PINHOLE and SIMPLE_PINHOLE cameras. Undistort first with "
    "`ag2gs undistort SCENE -o OUT` (runs COLMAP for you), or with "
    "`colmap image_undistorter --image_path IMAGES --input_path SPARSE --output_path OUT "
    "--output_type COLMAP` and use OUT as the scene";

struct RawCamera {
  std::string model;
  uint64_t width = 0, height = 0;
  std::vector<double> params;
};

struct RawImage {
  uint32_t camera_id = 0;
  uint32_t image_id = 0;
  double q[4] = {1, 0, 0, 0};  // w x y z
  double t[3] = {0, 0, 0};
  std::string name;
};

struct RawPoint {
  uint64_t id = 0;
  Eigen::Vector3d xyz = Eigen::Vector3d::Zero();
  Eigen::Vector3<uint8_t> rgb = Eigen::Vector3<uint8_t>::Zero();
};

// ------------------------------------------------------------------ binary

std::vector<unsigned char> read_file(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) fail(path, std::string("cannot open: ") + std::strerror(errno));
  in.seekg(0, std::ios::end);
  const std::streamoff size = in.tellg();
  if (size < 0) fail(path, "cannot determine the file size");
  std::vector<unsigned char> data(static_cast<size_t>(size));
  in.seekg(0);
  in.read(reinterpret_cast<char*>(data.data()), size);
  if (in.gcount() != size) fail(path, "read error");
  return data;
}

// Little-endian cursor that reports truncation with the file name.
class BinaryCursor {
 public:
  BinaryCursor(std::string path, std::vector<unsigned char> data) : path_(std::move(path)), data_(std::move(data)) {}

  size_t left() const { return data_.size() - pos_; }
  uint64_t u64(const char* what) { return load(8, what); }
  uint32_t u32(const char* what) { return static_cast<uint32_t>(load(4, what)); }
  uint8_t u8(const char* what) { return static_cast<uint8_t>(load(1, what)); }
  double f64(const char* what) {
    const uint64_t bits = load(8, what);
    double d;
    std::memcpy(&d, &bits, 8);
    return d;
  }
  std::string cstring(const char* what) {
    const auto begin = data_.begin() + static_cast<std::ptrdiff_t>(pos_);
    const auto nul = std::find(begin, data_.end(), 0);
    if (nul == data_.end()) truncated(what);
    std::string s(begin, nul);
    pos_ += s.size() + 1;
    return s;
  }
  void skip(uint64_t count, uint64_t item_bytes, const char* what) {
    check_count(count, item_bytes, what);
    pos_ += static_cast<size_t>(count * item_bytes);
  }
  // Rejects counts the rest of the file cannot hold, before anything is allocated.
  void check_count(uint64_t count, uint64_t min_item_bytes, const char* what) {
    if (min_item_bytes > 0 && count > left() / min_item_bytes) truncated(what);
  }
  [[noreturn]] void truncated(const char* what) const {
    fail(path_, "truncated or corrupt: the data ends (at byte " + std::to_string(data_.size()) + ") while reading " +
                    what + "; re-export the model with COLMAP");
  }

 private:
  uint64_t load(int bytes, const char* what) {
    if (left() < static_cast<size_t>(bytes)) truncated(what);
    uint64_t v = 0;
    for (int i = 0; i < bytes; ++i) v |= uint64_t(data_[pos_ + i]) << (8 * i);
    pos_ += static_cast<size_t>(bytes);
    return v;
  }

  std::string path_;
  std::vector<unsigned char> data_;
  size_t pos_ = 0;
};

std::map<uint32_t, RawCamera> read_cameras_bin(const std::string& path) {
  BinaryCursor in(path, read_file(path));
  const uint64_t count = in.u64("the camera count");
  in.check_count(count, 24, "the cameras");
  std::map<uint32_t, RawCamera> cameras;
  for (uint64_t i = 0; i < count; ++i) {
    const uint32_t id = in.u32("a camera id");
    const int model_id = static_cast<int>(in.u32("a camera model id"));
    const ModelInfo* model = model_by_id(model_id);
    if (!model) {
      fail(path, "camera " + std::to_string(id) + " has unknown model id " + std::to_string(model_id) + ". " +
                     kUndistortHint);
    }
    RawCamera cam;
    cam.model = model->name;
    cam.width = in.u64("a camera width");
    cam.height = in.u64("a camera height");
    for (int p = 0; p < model->num_params; ++p) cam.params.push_back(in.f64("camera parameters"));
    cameras[id] = cam;
  }
  if (in.left() != 0) fail(path, "trailing bytes after the last camera; the file is corrupt");
  return cameras;
}

std::vector<RawImage> read_images_bin(const std::string& path) {
  BinaryCursor in(path, read_file(path));
  const uint64_t count = in.u64("the image count");
  in.check_count(count, 73, "the images");
  std::vector<RawImage> images(static_cast<size_t>(count));
  for (RawImage& im : images) {
    im.image_id = in.u32("an image id");
    for (double& q : im.q) q = in.f64("an image rotation");
    for (double& t : im.t) t = in.f64("an image translation");
    im.camera_id = in.u32("an image's camera id");
    im.name = in.cstring("an image name");
    const uint64_t n_points2d = in.u64("an image's 2D point count");
    in.skip(n_points2d, 24, "an image's 2D points");  // x, y (double), point3D id (int64)
  }
  if (in.left() != 0) fail(path, "trailing bytes after the last image; the file is corrupt");
  return images;
}

std::vector<RawPoint> read_points_bin(const std::string& path) {
  BinaryCursor in(path, read_file(path));
  const uint64_t count = in.u64("the point count");
  in.check_count(count, 51, "the points");
  std::vector<RawPoint> points(static_cast<size_t>(count));
  for (RawPoint& p : points) {
    p.id = in.u64("a point id");
    for (int i = 0; i < 3; ++i) p.xyz[i] = in.f64("a point position");
    for (int i = 0; i < 3; ++i) p.rgb[i] = in.u8("a point colour");
    in.f64("a point error");
    const uint64_t track = in.u64("a point's track length");
    in.skip(track, 8, "a point's track");  // image id, point2D index (uint32 each)
  }
  if (in.left() != 0) fail(path, "trailing bytes after the last point; the file is corrupt");
  return points;
}

// ------------------------------------------------------------------ text

class TextReader {
 public:
  explicit TextReader(std::string path) : path_(std::move(path)), in_(path_) {
    if (!in_) fail(path_, std::string("cannot open: ") + std::strerror(errno));
  }

  // Next non-empty, non-comment line split into tokens; false at the end.
  bool next_record(std::vector<std::string>* tokens) {
    std::string line;
    while (next_line(&line)) {
      split(line, tokens);
      if (!tokens->empty() && (*tokens)[0][0] != '#') return true;
    }
    return false;
  }
  bool next_line(std::string* line) {
    if (!std::getline(in_, *line)) return false;
    ++line_no_;
    return true;
  }

  double number(const std::string& tok, const char* what) const {
    char* end = nullptr;
    const double v = std::strtod(tok.c_str(), &end);
    if (tok.empty() || *end != '\0') bad(std::string("bad ") + what + " '" + tok + "'");
    return v;
  }
  uint64_t integer(const std::string& tok, const char* what) const {
    // Digits only: "1e3" or "12.0" must not pass as 1 or 12.
    const bool digits = !tok.empty() && tok.size() <= 19 &&
                        std::all_of(tok.begin(), tok.end(), [](unsigned char c) { return std::isdigit(c); });
    if (!digits) bad(std::string("bad ") + what + " '" + tok + "' (expected a non-negative integer)");
    return static_cast<uint64_t>(std::strtoull(tok.c_str(), nullptr, 10));
  }
  [[noreturn]] void bad(const std::string& what) const { fail(path_ + ":" + std::to_string(line_no_), what); }
  const std::string& path() const { return path_; }

 private:
  static void split(const std::string& line, std::vector<std::string>* tokens) {
    tokens->clear();
    std::istringstream ss(line);
    std::string tok;
    while (ss >> tok) tokens->push_back(tok);
  }

  std::string path_;
  std::ifstream in_;
  int line_no_ = 0;
};

std::map<uint32_t, RawCamera> read_cameras_txt(const std::string& path) {
  TextReader in(path);
  std::map<uint32_t, RawCamera> cameras;
  std::vector<std::string> tok;
  while (in.next_record(&tok)) {
    // CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]
    if (tok.size() < 4) in.bad("expected 'CAMERA_ID MODEL WIDTH HEIGHT PARAMS...'");
    const uint32_t id = static_cast<uint32_t>(in.integer(tok[0], "camera id"));
    RawCamera cam;
    cam.model = tok[1];
    cam.width = in.integer(tok[2], "width");
    cam.height = in.integer(tok[3], "height");
    for (size_t i = 4; i < tok.size(); ++i) cam.params.push_back(in.number(tok[i], "camera parameter"));
    const ModelInfo* model = model_by_name(cam.model);
    if (model && static_cast<int>(cam.params.size()) != model->num_params) {
      in.bad("camera " + std::to_string(id) + " of model " + cam.model + " has " + std::to_string(cam.params.size()) +
             " parameters; expected " + std::to_string(model->num_params));
    }
    cameras[id] = cam;
  }
  return cameras;
}

std::vector<RawImage> read_images_txt(const std::string& path) {
  TextReader in(path);
  std::vector<RawImage> images;
  std::vector<std::string> tok;
  std::string points_line;
  while (in.next_record(&tok)) {
    // IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, then a line of POINTS2D (may be empty).
    if (tok.size() < 10) in.bad("expected 'IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME'");
    RawImage im;
    im.image_id = static_cast<uint32_t>(in.integer(tok[0], "image id"));
    for (int i = 0; i < 4; ++i) im.q[i] = in.number(tok[1 + i], "quaternion");
    for (int i = 0; i < 3; ++i) im.t[i] = in.number(tok[5 + i], "translation");
    im.camera_id = static_cast<uint32_t>(in.integer(tok[8], "camera id"));
    im.name = tok[9];
    for (size_t i = 10; i < tok.size(); ++i) im.name += " " + tok[i];
    images.push_back(im);
    // The 2D points (not needed) as X Y POINT3D_ID triples, possibly none. A
    // dropped points line would otherwise swallow the next image's header.
    if (in.next_line(&points_line)) {
      std::istringstream ss(points_line);
      std::string t;
      size_t n = 0;
      while (ss >> t) {
        char* end = nullptr;
        std::strtod(t.c_str(), &end);
        if (*end != '\0')
          in.bad("expected the 2D points of image '" + im.name + "' (X Y POINT3D_ID ..., or an empty line), found '" +
                 points_line.substr(0, 80) + "': every image takes two lines, its header and its points");
        ++n;
      }
      if (n % 3 != 0)
        in.bad("the 2D points of image '" + im.name + "' hold " + std::to_string(n) +
               " numbers, not X Y POINT3D_ID triples: every image takes two lines, its header and its points");
    }
  }
  return images;
}

std::vector<RawPoint> read_points_txt(const std::string& path) {
  TextReader in(path);
  std::vector<RawPoint> points;
  std::vector<std::string> tok;
  while (in.next_record(&tok)) {
    // POINT3D_ID X Y Z R G B ERROR TRACK[]
    if (tok.size() < 8) in.bad("expected 'POINT3D_ID X Y Z R G B ERROR TRACK...'");
    RawPoint p;
    p.id = in.integer(tok[0], "point id");
    for (int i = 0; i < 3; ++i) p.xyz[i] = in.number(tok[1 + i], "coordinate");
    for (int i = 0; i < 3; ++i) {
      const uint64_t c = in.integer(tok[4 + i], "colour");
      if (c > 255) in.bad("colour " + tok[4 + i] + " is out of range 0..255");
      p.rgb[i] = static_cast<uint8_t>(c);
    }
    points.push_back(p);
  }
  return points;
}

// The .bin file when present, else the .txt file, else an error.
std::string pick_file(const std::string& dir, const std::string& stem) {
  const fs::path bin = fs::path(dir) / (stem + ".bin");
  const fs::path txt = fs::path(dir) / (stem + ".txt");
  for (const fs::path& p : {bin, txt}) {
    if (!fs::exists(p)) continue;
    if (!fs::is_regular_file(p))
      fail(p.string(), "is a folder (or another kind of entry), not a file: the COLMAP model needs " + stem +
                           ".bin or " + stem + ".txt here");
    return p.string();
  }
  std::string hint = "pass the COLMAP model folder, e.g. scene/sparse/0";
  if (fs::is_directory(fs::path(dir) / "sparse" / "0")) {
    hint = "did you mean '" + (fs::path(dir) / "sparse" / "0").string() + "'?";
  }
  fail(dir, "no " + stem + ".bin or " + stem + ".txt; " + hint);
}

bool ends_with(const std::string& s, const std::string& suffix) {
  return s.size() >= suffix.size() && s.compare(s.size() - suffix.size(), suffix.size(), suffix) == 0;
}

Camera make_camera(const RawImage& im, const RawCamera& raw, uint32_t camera_id, const std::string& cameras_path,
                   const std::string& images_path, bool allow_distorted) {
  const std::string who = "camera " + std::to_string(camera_id) + " (used by image '" + im.name + "')";
  Camera cam;
  cam.name = im.name;
  const ModelInfo* model = model_by_name(raw.model);
  if (!model || static_cast<int>(raw.params.size()) != model->num_params) {
    fail(cameras_path, who + " has unknown camera model '" + raw.model + "'. " + kUndistortHint);
  }
  const bool pinhole = raw.model == "PINHOLE" || raw.model == "SIMPLE_PINHOLE";
  if (!pinhole && !allow_distorted) {
    fail(cameras_path, who + " has model " + raw.model + ". " + kUndistortHint);
  }
  // Models with one focal length list (f, cx, cy, ...); the others (fx, fy, cx, cy, ...).
  const bool single_focal =
      raw.model.rfind("SIMPLE_", 0) == 0 || raw.model == "RADIAL" || raw.model == "RADIAL_FISHEYE";
  if (single_focal) {
    cam.fx = cam.fy = raw.params[0];
    cam.cx = raw.params[1];
    cam.cy = raw.params[2];
  } else {
    cam.fx = raw.params[0];
    cam.fy = raw.params[1];
    cam.cx = raw.params[2];
    cam.cy = raw.params[3];
  }
  if (raw.width == 0 || raw.height == 0 || raw.width > INT_MAX || raw.height > INT_MAX) {
    fail(cameras_path, who + " has an unusable size " + std::to_string(raw.width) + "x" + std::to_string(raw.height));
  }
  cam.width = static_cast<int>(raw.width);
  cam.height = static_cast<int>(raw.height);

  Eigen::Quaterniond q(im.q[0], im.q[1], im.q[2], im.q[3]);
  const double norm = q.norm();
  if (!(std::isfinite(norm) && norm > 1e-12)) {
    fail(images_path, "image '" + im.name + "' has a degenerate rotation quaternion");
  }
  cam.R = q.normalized().toRotationMatrix();
  cam.t = Eigen::Vector3d(im.t[0], im.t[1], im.t[2]);
  try {
    cam.validate();
  } catch (const std::invalid_argument& e) {
    fail(images_path, std::string(e.what()) + " (intrinsics from " + cameras_path + ", " + who + ")");
  }
  return cam;
}

std::string list_some_names(const std::vector<Camera>& cameras) {
  std::string s;
  const size_t shown = std::min<size_t>(cameras.size(), 5);
  for (size_t i = 0; i < shown; ++i) s += (i ? ", " : "") + cameras[i].name;
  if (cameras.size() > shown) s += ", ...";
  return s + " (" + std::to_string(cameras.size()) + " views)";
}

std::string trim(const std::string& s) {
  const size_t b = s.find_first_not_of(" \t\r\n");
  if (b == std::string::npos) return "";
  const size_t e = s.find_last_not_of(" \t\r\n");
  return s.substr(b, e - b + 1);
}

}  // namespace

ColmapModel read_colmap_model(const std::string& sparse_dir, bool allow_distorted) {
  if (!fs::is_directory(sparse_dir)) {
    fail(sparse_dir, "not a directory; pass the COLMAP model folder, e.g. scene/sparse/0");
  }
  const std::string cameras_path = pick_file(sparse_dir, "cameras");
  const std::string images_path = pick_file(sparse_dir, "images");
  const std::string points_path = pick_file(sparse_dir, "points3D");

  const auto cameras =
      ends_with(cameras_path, ".bin") ? read_cameras_bin(cameras_path) : read_cameras_txt(cameras_path);
  auto images = ends_with(images_path, ".bin") ? read_images_bin(images_path) : read_images_txt(images_path);
  auto points = ends_with(points_path, ".bin") ? read_points_bin(points_path) : read_points_txt(points_path);

  ColmapModel model;
  std::sort(images.begin(), images.end(), [](const RawImage& a, const RawImage& b) { return a.name < b.name; });
  for (size_t i = 0; i < images.size(); ++i) {
    const RawImage& im = images[i];
    if (i > 0 && images[i - 1].name == im.name) {
      fail(images_path, "image name '" + im.name + "' appears twice");
    }
    const auto it = cameras.find(im.camera_id);
    if (it == cameras.end()) {
      fail(images_path, "image '" + im.name + "' (id " + std::to_string(im.image_id) + ") refers to camera " +
                            std::to_string(im.camera_id) + ", which " + cameras_path + " does not define");
    }
    model.cameras_for_images.push_back(
        make_camera(im, it->second, im.camera_id, cameras_path, images_path, allow_distorted));
    model.camera_models.push_back(it->second.model);
  }

  std::sort(points.begin(), points.end(), [](const RawPoint& a, const RawPoint& b) { return a.id < b.id; });
  model.points.reserve(points.size());
  model.colors.reserve(points.size());
  for (const RawPoint& p : points) {
    model.points.push_back(p.xyz);
    model.colors.push_back(p.rgb);
  }
  return model;
}

Camera scale_camera(const Camera& camera, int factor) {
  if (factor < 1) {
    throw std::invalid_argument("scale_camera: resolution factor " + std::to_string(factor) + " must be 1 or more");
  }
  if (factor == 1) return camera;
  // round(size / factor), ties to even like Python 3's round() in 3DGS.
  auto divide = [factor](int size) {
    const int q = size / factor, r = size % factor;
    if (2 * r > factor || (2 * r == factor && (q % 2) == 1)) return q + 1;
    return q;
  };
  Camera out = camera;
  out.width = divide(camera.width);
  out.height = divide(camera.height);
  if (out.width < 1 || out.height < 1) {
    throw std::invalid_argument("scale_camera: image '" + camera.name + "' of " + std::to_string(camera.width) + "x" +
                                std::to_string(camera.height) + " vanishes at 1/" + std::to_string(factor) +
                                " resolution; use a smaller factor");
  }
  return resize_camera(camera, out.width, out.height);
}

Camera resize_camera(const Camera& camera, int width, int height) {
  if (width < 1 || height < 1)
    throw std::invalid_argument("resize_camera: " + std::to_string(width) + "x" + std::to_string(height) +
                                " is not an image size");
  Camera out = camera;
  const double sx = static_cast<double>(width) / camera.width;
  const double sy = static_cast<double>(height) / camera.height;
  out.width = width;
  out.height = height;
  out.fx *= sx;
  out.cx *= sx;
  out.fy *= sy;
  out.cy *= sy;
  return out;
}

std::vector<Camera> select_views(const std::vector<Camera>& cameras, const std::string& comma_list) {
  std::vector<std::string> wanted;
  std::stringstream ss(comma_list);
  std::string item;
  while (std::getline(ss, item, ',')) {
    item = trim(item);
    if (!item.empty()) wanted.push_back(item);
  }
  if (wanted.empty()) return cameras;

  std::vector<Camera> selected;
  for (const std::string& w : wanted) {
    const Camera* exact = nullptr;
    std::vector<const Camera*> loose;
    for (const Camera& cam : cameras) {
      if (cam.name == w) {
        exact = &cam;
        break;
      }
      const fs::path p(cam.name);
      if (fs::path(p).replace_extension().generic_string() == w || p.stem().string() == w) {
        loose.push_back(&cam);
      }
    }
    if (exact) {
      selected.push_back(*exact);
    } else if (loose.size() == 1) {
      selected.push_back(*loose[0]);
    } else if (loose.empty()) {
      throw std::invalid_argument("unknown view '" + w + "'; valid names include " + list_some_names(cameras));
    } else {
      std::string names;
      for (size_t i = 0; i < loose.size(); ++i) names += (i ? ", " : "") + loose[i]->name;
      throw std::invalid_argument("view '" + w + "' is ambiguous: it matches " + names + "; give the full image name");
    }
  }
  return selected;
}

bool is_pinhole_model(const std::string& model_name) {
  return model_name == "PINHOLE" || model_name == "SIMPLE_PINHOLE";
}

}  // namespace ag2gs
