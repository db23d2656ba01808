#include "host/scene/scene.h"

#include <spdlog/spdlog.h>

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <stdexcept>
#include <unordered_map>

#include "host/io/colmap_reader.h"
#include "host/io/image_io.h"
#include "host/io/npy_io.h"

namespace ag2gs {
namespace {

namespace fs = std::filesystem;

enum CacheKind { kImage = 0, kMasks = 1 };

[[noreturn]] void fail(const std::string& path, const std::string& what) {
  throw std::runtime_error(path + ": " + what);
}

std::string some_names(const std::vector<std::string>& names, size_t shown = 5) {
  std::string s;
  for (size_t i = 0; i < std::min(shown, names.size()); ++i) s += (i ? ", " : "") + names[i];
  if (names.size() > shown) s += ", ... (" + std::to_string(names.size()) + " in all)";
  return s;
}

std::string size_str(int w, int h) {
  return std::to_string(w) + "x" + std::to_string(h);
}

// The model's points file (.bin preferred, as the reader does).
std::string points_file(const fs::path& sparse) {
  const fs::path bin = sparse / "points3D.bin";
  return (fs::exists(bin) ? bin : sparse / "points3D.txt").string();
}

}  // namespace

const char* to_string(SemanticsKind kind) {
  switch (kind) {
    case SemanticsKind::language_features:
      return "language_features (SAM masks + CLIP features)";
    case SemanticsKind::mask_png:
      return "masks (16-bit instance PNGs, no CLIP features)";
    default:
      return "none";
  }
}

void robust_box(const std::vector<Eigen::Vector3d>& points, Eigen::Vector3d* lo, Eigen::Vector3d* hi, int* kept) {
  *lo = Eigen::Vector3d::Zero();
  *hi = Eigen::Vector3d::Zero();
  *kept = 0;
  std::vector<Eigen::Vector3d> finite;
  finite.reserve(points.size());
  for (const auto& p : points) {
    if (p.allFinite()) finite.push_back(p);
  }
  if (finite.empty()) return;
  const size_t n = finite.size();
  const size_t a = n < 100 ? 0 : static_cast<size_t>(std::floor(0.01 * (n - 1)));
  const size_t b = n < 100 ? n - 1 : static_cast<size_t>(std::ceil(0.99 * (n - 1)));
  std::vector<double> axis(n);
  for (int d = 0; d < 3; ++d) {
    for (size_t i = 0; i < n; ++i) axis[i] = finite[i][d];
    std::nth_element(axis.begin(), axis.begin() + static_cast<std::ptrdiff_t>(a), axis.end());
    (*lo)[d] = axis[a];
    std::nth_element(axis.begin(), axis.begin() + static_cast<std::ptrdiff_t>(b), axis.end());
    (*hi)[d] = axis[b];
  }
  for (const auto& p : finite) {
    if ((p.array() >= lo->array()).all() && (p.array() <= hi->array()).all()) ++*kept;
  }
}

void drop_contained_masks(ViewMasks* m) {
  const size_t plane = static_cast<size_t>(m->width) * m->height;
  const int count = m->count;
  std::vector<int64_t> pixels(count, 0);
  for (int32_t id : m->labels) {
    if (id >= 0) ++pixels[id];
  }
  // Overlap counts between masks of different label maps (masks of one map
  // are disjoint by construction). Key: a * count + b for a != b.
  std::unordered_map<int64_t, int64_t> overlap;
  if (m->layers > 1) {
    for (size_t p = 0; p < plane; ++p) {
      for (int la = 0; la < m->layers; ++la) {
        const int32_t a = m->labels[la * plane + p];
        if (a < 0) continue;
        for (int lb = la + 1; lb < m->layers; ++lb) {
          const int32_t b = m->labels[lb * plane + p];
          if (b < 0 || b == a) continue;
          ++overlap[int64_t(a) * count + b];
          ++overlap[int64_t(b) * count + a];
        }
      }
    }
  }
  std::vector<char> keep(count, 1);
  int contained = 0, empty = 0;
  for (int a = 0; a < count; ++a) {
    if (pixels[a] == 0) {
      keep[a] = 0;
      ++empty;
    }
  }
  // Iterate in a fixed order so the result is deterministic; a mask equal to
  // another keeps the lower index.
  std::vector<std::pair<int64_t, int64_t>> pairs(overlap.begin(), overlap.end());
  std::sort(pairs.begin(), pairs.end());
  for (const auto& [key, n] : pairs) {
    const int a = static_cast<int>(key / count), b = static_cast<int>(key % count);
    if (!keep[a] || n != pixels[a]) continue;
    if (pixels[a] < pixels[b] || (pixels[a] == pixels[b] && a > b && keep[b])) {
      keep[a] = 0;
      ++contained;
    }
  }
  std::vector<int32_t> remap(count, -1);
  int kept = 0;
  for (int a = 0; a < count; ++a) {
    if (keep[a]) remap[a] = kept++;
  }
  for (int32_t& id : m->labels) {
    if (id >= 0) id = remap[id];
  }
  if (m->feature_dim > 0) {
    std::vector<float> features(static_cast<size_t>(kept) * m->feature_dim);
    for (int a = 0; a < count; ++a) {
      if (remap[a] < 0) continue;
      std::copy_n(m->features.begin() + static_cast<std::ptrdiff_t>(a) * m->feature_dim, m->feature_dim,
                  features.begin() + static_cast<std::ptrdiff_t>(remap[a]) * m->feature_dim);
    }
    m->features = std::move(features);
  }
  m->pixels.assign(kept, 0);
  for (int32_t id : m->labels) {
    if (id >= 0) ++m->pixels[id];
  }
  m->count = kept;
  m->dropped_contained += contained;
  m->dropped_empty += empty;
}

std::string find_colmap_model(const std::string& dir, const std::string& sparse) {
  const fs::path root(dir);
  auto holds_model = [](const fs::path& p) { return fs::exists(p / "cameras.bin") || fs::exists(p / "cameras.txt"); };
  if (!sparse.empty()) {
    const fs::path p = root / sparse;  // an absolute `sparse` replaces the root
    if (!fs::is_directory(p)) {
      fail(p.string(), "no such folder (given with --sparse " + sparse +
                           "); --sparse names the COLMAP model folder (cameras, images, points3D as .bin or "
                           ".txt) inside the scene, e.g. sparse/0");
    }
    return p.string();
  }
  const fs::path zero = root / "sparse" / "0", flat = root / "sparse";
  if (holds_model(zero)) return zero.string();
  if (holds_model(flat)) return flat.string();
  // A sparse/0/ without cameras: the reader names the missing file.
  if (fs::is_directory(zero)) return zero.string();
  fail(flat.string(), std::string(fs::is_directory(flat) ? "holds" : "does not exist, so there is") +
                          " no COLMAP model; looked for cameras, images and points3D (.bin or .txt) in sparse/0/ "
                          "and in sparse/. Name the folder that holds them with --sparse DIR, or make a model "
                          "from photos with `ag2gs sfm IMAGES_DIR -o SCENE_DIR`");
}

// The semantic inputs: language_features/ wins over masks/.
void Scene::find_semantics() {
  const fs::path lf = fs::path(dir_) / "language_features";
  const fs::path mp = fs::path(dir_) / "masks";
  std::vector<std::string> without;
  if (fs::is_directory(lf)) {
    int found = 0;
    for (SceneView& v : views_) {
      const fs::path sp = lf / (v.stem + "_s.npy"), fp = lf / (v.stem + "_f.npy");
      const bool has_s = fs::exists(sp), has_f = fs::exists(fp);
      if (has_s != has_f) {
        fail((has_s ? fp : sp).string(),
             "missing; language features come in pairs <stem>_s.npy (mask ids) and "
             "<stem>_f.npy (CLIP features)");
      }
      if (has_s) {
        v.semantics_path = sp.string();
        v.features_path = fp.string();
        ++found;
      } else {
        without.push_back(v.name);
      }
    }
    if (found > 0)
      semantics_ = SemanticsKind::language_features;
    else
      notes_.push_back(lf.string() + " has no <stem>_s.npy/_f.npy for any image: training appearance only");
  } else if (fs::is_directory(mp)) {
    int found = 0;
    for (SceneView& v : views_) {
      const fs::path p = mp / (v.stem + ".png");
      if (fs::exists(p)) {
        v.semantics_path = p.string();
        ++found;
      } else {
        without.push_back(v.name);
      }
    }
    if (found > 0)
      semantics_ = SemanticsKind::mask_png;
    else
      notes_.push_back(mp.string() + " has no <stem>.png for any image: training appearance only");
  }
  if (semantics_ != SemanticsKind::none && !without.empty()) {
    notes_.push_back(std::to_string(without.size()) +
                     " views have no masks (they train appearance only): " + some_names(without));
  }
  if (semantics_ == SemanticsKind::mask_png && options_.sam_levels.size() > 1) {
    notes_.push_back("masks/ PNGs have one level; the SAM levels option applies to language_features/ only");
  }
}

// The SfM points' robust box, and the cameras' centre and radius.
void Scene::find_bounds() {
  robust_box(points_, &bounds_.lo, &bounds_.hi, &bounds_.points_kept);
  bounds_.points_total = static_cast<int>(points_.size());
  Eigen::Vector3d mean = Eigen::Vector3d::Zero();
  for (const SceneView& v : views_) mean += v.full_camera.center();
  mean /= static_cast<double>(views_.size());
  double far = 0;
  for (const SceneView& v : views_) far = std::max(far, (v.full_camera.center() - mean).norm());
  bounds_.camera_center = mean;
  bounds_.camera_radius = 1.1 * far;
}

std::unique_ptr<Scene> Scene::open(const std::string& dir, const SceneOptions& options) {
  if (!fs::is_directory(dir)) {
    fail(dir, "no such scene directory; a scene holds images/ and sparse/0/ (make one with `ag2gs sfm IMAGES -o " +
                  dir + "` or `ag2gs synth " + dir + "`)");
  }
  if (options.resolution < 1) {
    throw std::invalid_argument("resolution factor " + std::to_string(options.resolution) + " must be 1 or more");
  }
  for (int level : options.sam_levels) {
    if (level < 0 || level > 3) {
      throw std::invalid_argument("SAM level " + std::to_string(level) +
                                  " does not exist; levels are 0 (default), 1 (small), 2 (medium), 3 (large)");
    }
  }
  std::unique_ptr<Scene> s(new Scene());
  s->dir_ = dir;
  s->options_ = options;
  const fs::path root(dir);

  const fs::path sparse = find_colmap_model(dir, options.sparse);
  // The image folder before the cameras: a model without its photos is not
  // trainable whatever its camera model, and undistorting needs the photos.
  const fs::path images = root / options.images;
  if (!fs::is_directory(images)) {
    std::string then;
    try {
      for (const std::string& m : read_colmap_model(sparse.string(), true).camera_models) {
        if (m != "PINHOLE" && m != "SIMPLE_PINHOLE") {
          then = "; its cameras are " + m + ", so then run `ag2gs undistort " + dir + " -o NEW_SCENE_DIR`";
          break;
        }
      }
    } catch (const std::exception&) {
      // The model's own problems are reported once the photos are there.
    }
    fail(images.string(), "no image folder; put the photos the COLMAP model in " + sparse.string() +
                              " was made from in " + options.images + "/" + then);
  }
  const ColmapModel model = read_colmap_model(sparse.string());
  if (model.cameras_for_images.empty()) fail(sparse.string(), "the model has no registered images");
  s->points_path_ = points_file(sparse);
  // Numbers from files are checked at load: a point with a non-finite
  // coordinate is left out, with a count (a damaged or hand-edited model).
  size_t non_finite = 0;
  for (size_t i = 0; i < model.points.size(); ++i) {
    if (!model.points[i].allFinite()) {
      ++non_finite;
      continue;
    }
    s->points_.push_back(model.points[i]);
    if (i < model.colors.size()) s->colors_.push_back(model.colors[i]);
  }
  if (non_finite > 0) {
    const std::string note = s->points_path_ + ": left out " + std::to_string(non_finite) + " of " +
                             std::to_string(model.points.size()) + " points with non-finite coordinates";
    spdlog::warn("{}", note);
    s->notes_.push_back(note);
  }

  fs::path scaled;
  if (options.resolution > 1) {
    const fs::path candidate = root / (options.images + "_" + std::to_string(options.resolution));
    if (fs::is_directory(candidate)) scaled = candidate;
  }

  std::vector<std::string> missing;
  for (size_t i = 0; i < model.cameras_for_images.size(); ++i) {
    SceneView v;
    v.index = static_cast<int>(i);
    v.full_camera = model.cameras_for_images[i];
    v.camera = scale_camera(v.full_camera, options.resolution);
    v.name = v.full_camera.name;
    v.stem = fs::path(v.name).stem().string();
    if (options.test_images.empty()) {
      v.test = options.eval && i % 8 == 0;
    } else {
      for (const std::string& t : options.test_images) v.test = v.test || t == v.name || t == v.stem;
    }
    if (!scaled.empty() && fs::exists(scaled / v.name)) {
      v.image_path = (scaled / v.name).string();
    } else {
      v.image_path = (images / v.name).string();
      v.downscale = options.resolution > 1;
      if (!fs::exists(v.image_path)) missing.push_back(v.name);
    }
    s->views_.push_back(v);
  }
  for (const std::string& t : options.test_images) {
    bool found = false;
    for (const SceneView& v : s->views_) found = found || t == v.name || t == v.stem;
    if (!found) {
      std::vector<std::string> names;
      for (const SceneView& v : s->views_) names.push_back(v.name);
      fail(sparse.string(), "the held-out image '" + t + "' is not in the COLMAP model (it has " + some_names(names) +
                                "); name an image of the model");
    }
  }
  if (!missing.empty()) {
    fail(images.string(), std::to_string(missing.size()) + " of " + std::to_string(s->views_.size()) +
                              " images of the COLMAP model are missing: " + some_names(missing) +
                              ". Copy them here, or give the scene folder that holds them in images/");
  }
  if (options.eval && s->views_.size() == 1) {
    s->notes_.push_back("--eval with a single image holds it out and leaves nothing to train on");
  }

  s->find_semantics();
  s->find_bounds();
  if (s->points_.empty()) s->notes_.push_back(s->points_path_ + " has no points; training needs SfM points");
  return s;
}

std::vector<int> Scene::train_views() const {
  std::vector<int> out;
  for (const SceneView& v : views_) {
    if (!v.test) out.push_back(v.index);
  }
  return out;
}

std::vector<int> Scene::test_views() const {
  std::vector<int> out;
  for (const SceneView& v : views_) {
    if (v.test) out.push_back(v.index);
  }
  return out;
}

int Scene::find_view(const std::string& name) const {
  std::vector<int> loose;
  for (const SceneView& v : views_) {
    if (v.name == name) return v.index;
    if (fs::path(v.name).replace_extension().generic_string() == name || v.stem == name) loose.push_back(v.index);
  }
  if (loose.size() == 1) return loose[0];
  std::vector<std::string> names;
  if (loose.empty()) {
    for (const SceneView& v : views_) names.push_back(v.name);
    throw std::invalid_argument("unknown view '" + name + "'; valid names include " + some_names(names));
  }
  for (int i : loose) names.push_back(views_[i].name);
  throw std::invalid_argument("view '" + name + "' is ambiguous: it matches " + some_names(names) +
                              "; give the full image name");
}

void Scene::require_points() const {
  if (points_.empty()) {
    fail(points_path_,
         "the COLMAP model has no 3D points, and anchors are initialised from them; re-run "
         "structure from motion (`ag2gs sfm`) or check that the model was exported with points");
  }
}

std::shared_ptr<const void> Scene::cached(int kind, int view) {
  auto it = index_.find({kind, view});
  if (it == index_.end()) {
    ++cache_stats_.misses;
    return nullptr;
  }
  ++cache_stats_.hits;
  lru_.splice(lru_.begin(), lru_, it->second);
  return it->second->value;
}

void Scene::insert(int kind, int view, std::shared_ptr<const void> value, size_t bytes) {
  lru_.push_front(Entry{kind, view, std::move(value), bytes});
  index_[{kind, view}] = lru_.begin();
  cache_stats_.bytes += bytes;
  // Evict least recently used entries beyond the bound, never the new one.
  while (cache_stats_.bytes > options_.cache_bytes && lru_.size() > 1) {
    const Entry& old = lru_.back();
    cache_stats_.bytes -= old.bytes;
    index_.erase({old.kind, old.view});
    lru_.pop_back();
    ++cache_stats_.evictions;
  }
  cache_stats_.peak_bytes = std::max(cache_stats_.peak_bytes, cache_stats_.bytes);
}

std::shared_ptr<const Image> Scene::image(int view) {
  if (view < 0 || view >= static_cast<int>(views_.size())) throw std::out_of_range("Scene::image: bad view index");
  if (auto hit = cached(kImage, view)) return std::static_pointer_cast<const Image>(hit);
  std::shared_ptr<Image> img = load_image(views_[view]);
  insert(kImage, view, img, img->rgb.size() * sizeof(float));
  return img;
}

std::shared_ptr<const ViewMasks> Scene::masks(int view) {
  if (view < 0 || view >= static_cast<int>(views_.size())) throw std::out_of_range("Scene::masks: bad view index");
  if (views_[view].semantics_path.empty()) return nullptr;
  if (auto hit = cached(kMasks, view)) return std::static_pointer_cast<const ViewMasks>(hit);
  std::shared_ptr<ViewMasks> m = load_masks(views_[view]);
  insert(kMasks, view, m, m->bytes());
  return m;
}

void Scene::check_all(const std::function<void()>& before_each) {
  for (const SceneView& v : views_) {
    if (before_each) before_each();
    image(v.index);
    masks(v.index);
  }
}

std::shared_ptr<Image> Scene::load_image(const SceneView& v) const {
  std::vector<unsigned char> bytes;
  {
    std::error_code ec;
    if (fs::is_directory(v.image_path, ec)) fail(v.image_path, "is a folder, where an image file was expected");
    std::ifstream in(v.image_path, std::ios::binary);
    if (!in) fail(v.image_path, std::string("cannot be read: ") + std::strerror(errno) + "; check its permissions");
    bytes.assign(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
    if (in.bad()) fail(v.image_path, std::string("reading failed: ") + std::strerror(errno));
  }
  if (jpeg_is_truncated(bytes))
    fail(v.image_path, "is a truncated JPEG (its data stops before the end-of-image marker, " +
                           std::to_string(bytes.size()) + " bytes); copy the photo again");
  cv::Mat raw = bytes.empty() ? cv::Mat() : cv::imdecode(bytes, cv::IMREAD_COLOR | cv::IMREAD_ANYDEPTH);
  if (raw.empty()) {
    fail(v.image_path, "cannot be decoded as an image (corrupt or an unsupported format); replace it");
  }
  const Camera& want = v.downscale ? v.full_camera : v.camera;
  if (raw.cols != want.width || raw.rows != want.height) {
    const bool off_by_one = !v.downscale && options_.resolution > 1 && std::abs(raw.cols - want.width) <= 1 &&
                            std::abs(raw.rows - want.height) <= 1;
    if (!off_by_one) {
      std::string fix = "the image and the COLMAP model must describe the same photo";
      if (raw.cols * want.height == raw.rows * want.width && raw.cols < want.width) {
        fix = "it looks downscaled; keep full-size photos in " + options_.images + "/ (downscaled copies go in " +
              options_.images + "_N/ and are used with -r N)";
      }
      fail(v.image_path, "is " + size_str(raw.cols, raw.rows) + " but camera '" + v.name + "' expects " +
                             size_str(want.width, want.height) +
                             (v.downscale || options_.resolution == 1
                                  ? ""
                                  : " (1/" + std::to_string(options_.resolution) + " of " +
                                        size_str(v.full_camera.width, v.full_camera.height) + ")") +
                             "; " + fix);
    }
  }
  cv::Mat f;
  const double scale = raw.depth() == CV_16U ? 1.0 / 65535.0 : raw.depth() == CV_8U ? 1.0 / 255.0 : 1.0;
  raw.convertTo(f, CV_32F, scale);
  if (f.cols != v.camera.width || f.rows != v.camera.height) {
    cv::resize(f, f, cv::Size(v.camera.width, v.camera.height), 0, 0, cv::INTER_AREA);
  }
  cv::cvtColor(f, f, cv::COLOR_BGR2RGB);
  auto img = std::make_shared<Image>();
  img->width = f.cols;
  img->height = f.rows;
  img->rgb.resize(static_cast<size_t>(f.cols) * f.rows * 3);
  for (int y = 0; y < f.rows; ++y) {
    const float* row = f.ptr<float>(y);
    std::copy(row, row + 3 * f.cols, img->rgb.begin() + static_cast<std::ptrdiff_t>(y) * f.cols * 3);
  }
  for (float& x : img->rgb) x = std::min(1.f, std::max(0.f, x));
  return img;
}

std::shared_ptr<ViewMasks> Scene::load_masks(const SceneView& v) {
  auto m = std::make_shared<ViewMasks>();
  m->width = v.camera.width;
  m->height = v.camera.height;
  const size_t plane = static_cast<size_t>(m->width) * m->height;
  std::vector<cv::Mat> maps;  // CV_32S label maps at the file's size, global ids, -1 none

  if (semantics_ == SemanticsKind::language_features) {
    const NpyArray s = read_npy(v.semantics_path);
    int levels = 0, h = 0, w = 0;
    if (s.shape.size() == 3) {
      levels = static_cast<int>(s.dim(0));
      h = static_cast<int>(s.dim(1));
      w = static_cast<int>(s.dim(2));
    } else if (s.shape.size() == 2) {
      levels = 1;
      h = static_cast<int>(s.dim(0));
      w = static_cast<int>(s.dim(1));
    } else {
      fail(v.semantics_path, "expected mask ids of shape [4,H,W] (levels default, small, medium, large); got " +
                                 std::to_string(s.shape.size()) + " dimensions");
    }
    if (h < 1 || w < 1) fail(v.semantics_path, "the mask image is empty");
    const NpyArray f = read_npy(v.features_path);
    if (f.shape.size() != 2) {
      fail(v.features_path,
           "expected CLIP features of shape [masks, dim], got " + std::to_string(f.shape.size()) + " dimensions");
    }
    const int64_t rows = f.dim(0);
    const int dim = static_cast<int>(f.dim(1));
    if (dim < 1) fail(v.features_path, "the feature dimension is 0");
    if (feature_dim_ != 0 && dim != feature_dim_) {
      fail(v.features_path, "has " + std::to_string(dim) + "-d features but other views have " +
                                std::to_string(feature_dim_) + "-d; all views must come from the same CLIP model");
    }
    for (size_t i = 0; i < f.data.size(); ++i) {
      if (!std::isfinite(f.data[i])) {
        fail(v.features_path, "row " + std::to_string(i / dim) +
                                  " holds a non-finite value (NaN or Inf); re-run the feature extraction");
      }
    }
    feature_dim_ = dim;
    std::vector<int64_t> used;  // global ids in use
    for (int level : options_.sam_levels) {
      if (level >= levels) {
        fail(v.semantics_path, "has " + std::to_string(levels) + " SAM level(s) but level " + std::to_string(level) +
                                   " is used (training reads level 3, LangSplat's largest masks, from its [4,H,W] "
                                   "_s.npy layout); regenerate the file with LangSplat's preprocessing, or inspect "
                                   "another level with `ag2gs info --sam-level 0.." +
                                   std::to_string(levels - 1) + "`");
      }
      cv::Mat map(h, w, CV_32S);
      const float* src = s.data.data() + static_cast<size_t>(level) * h * w;
      for (int y = 0; y < h; ++y) {
        for (int x = 0; x < w; ++x) {
          const float id = src[static_cast<size_t>(y) * w + x];
          if (!(id >= -1.f && id < static_cast<float>(rows)) || id != std::floor(id)) {
            if (id >= 0 && std::isfinite(id) && id == std::floor(id)) {
              fail(v.semantics_path, "mask id " + std::to_string(static_cast<int64_t>(id)) + " at level " +
                                         std::to_string(level) + " has no row in " + v.features_path + " (" +
                                         std::to_string(rows) + " rows); the two files do not belong together");
            }
            fail(v.semantics_path, "holds a mask id that is not an integer >= -1 at level " + std::to_string(level) +
                                       ", pixel (" + std::to_string(x) + ", " + std::to_string(y) + ")");
          }
          map.at<int32_t>(y, x) = static_cast<int32_t>(id);
        }
      }
      maps.push_back(map);
    }
    for (const cv::Mat& map : maps) {
      for (auto it = map.begin<int32_t>(); it != map.end<int32_t>(); ++it) {
        if (*it >= 0) used.push_back(*it);
      }
    }
    std::sort(used.begin(), used.end());
    used.erase(std::unique(used.begin(), used.end()), used.end());
    m->feature_dim = dim;
    m->features.resize(used.size() * static_cast<size_t>(dim));
    for (size_t i = 0; i < used.size(); ++i) {
      std::copy_n(f.data.begin() + static_cast<std::ptrdiff_t>(used[i]) * dim, dim,
                  m->features.begin() + static_cast<std::ptrdiff_t>(i) * dim);
    }
    for (cv::Mat& map : maps) {
      for (auto it = map.begin<int32_t>(); it != map.end<int32_t>(); ++it) {
        if (*it >= 0) *it = static_cast<int32_t>(std::lower_bound(used.begin(), used.end(), *it) - used.begin());
      }
    }
    m->count = static_cast<int>(used.size());
  } else {
    cv::Mat raw = cv::imread(v.semantics_path, cv::IMREAD_UNCHANGED);
    if (raw.empty()) fail(v.semantics_path, "cannot be decoded as a PNG; masks must be 16-bit instance-id PNGs");
    if (raw.channels() != 1 || (raw.depth() != CV_16U && raw.depth() != CV_8U)) {
      fail(v.semantics_path, "must be a single-channel 8- or 16-bit PNG of instance ids (0 = no mask); it has " +
                                 std::to_string(raw.channels()) + " channel(s)");
    }
    cv::Mat ids;
    raw.convertTo(ids, CV_32S);
    std::vector<int32_t> used;
    for (auto it = ids.begin<int32_t>(); it != ids.end<int32_t>(); ++it) {
      if (*it > 0) used.push_back(*it);
    }
    std::sort(used.begin(), used.end());
    used.erase(std::unique(used.begin(), used.end()), used.end());
    for (auto it = ids.begin<int32_t>(); it != ids.end<int32_t>(); ++it) {
      *it = *it > 0 ? static_cast<int32_t>(std::lower_bound(used.begin(), used.end(), *it) - used.begin()) : -1;
    }
    maps.push_back(ids);
    m->count = static_cast<int>(used.size());
  }

  m->layers = static_cast<int>(maps.size());
  m->labels.resize(plane * m->layers);
  for (int l = 0; l < m->layers; ++l) {
    cv::Mat map = maps[l];
    if (map.cols != m->width || map.rows != m->height) {
      cv::resize(map, map, cv::Size(m->width, m->height), 0, 0, cv::INTER_NEAREST);
    }
    for (int y = 0; y < m->height; ++y) {
      const int32_t* row = map.ptr<int32_t>(y);
      std::copy(row, row + m->width, m->labels.begin() + static_cast<std::ptrdiff_t>(l * plane + y * m->width));
    }
  }
  drop_contained_masks(m.get());
  return m;
}

}  // namespace ag2gs
