// A scene directory as 3DGS, OpenGaussian and LangSplat lay it out
// (docs/formats.md): images/, sparse/0/ or sparse/ (COLMAP), and optionally
// language_features/<stem>_s.npy + <stem>_f.npy (SAM masks + CLIP features) or
// masks/<stem>.png (16-bit instance ids).
//
// Scene::open reads the COLMAP model and checks that every image and semantic
// file exists; pixels are loaded lazily and kept in a cache with a byte bound,
// so a 500-image scene never needs all its images in memory at once.
#pragma once

#include <Eigen/Core>
#include <cstddef>
#include <cstdint>
#include <functional>
#include <list>
#include <map>
#include <memory>
#include <string>
#include <utility>
#include <vector>

#include "host/core/gaussians.h"

namespace ag2gs {

struct SceneOptions {
  int resolution = 1;  // divide every camera by this (1, 2, 4, 8, ...); images_N/ is used when present
  bool eval = false;   // hold out every 8th image (name order, index % 8 == 0) as a test view
  // Hold out these images (names as in the COLMAP model, or their stems)
  // instead of every 8th; non-empty implies eval. Unknown names are errors.
  std::vector<std::string> test_images;
  // SAM levels of language_features/ to train on (0 default, 1 small, 2
  // medium, 3 large). With more than one level, masks fully contained in a
  // mask of another level are dropped.
  std::vector<int> sam_levels = {3};
  size_t cache_bytes = size_t(2) << 30;  // images and masks kept in memory
  std::string images = "images";         // image folder inside the scene
  std::string sparse;                    // COLMAP model folder inside the scene; empty = find_colmap_model's rule
};

// The COLMAP model folder of the scene at `dir`, one rule for every
// subcommand: `sparse` (inside the scene, or an absolute path) when given,
// else sparse/0/, else sparse/ itself when it holds cameras.bin or
// cameras.txt (a model written without the 0/ level). Throws
// std::runtime_error naming the folder looked at and the fix (--sparse DIR,
// or `ag2gs sfm` to make a model).
std::string find_colmap_model(const std::string& dir, const std::string& sparse = "");

enum class SemanticsKind { none, language_features, mask_png };
const char* to_string(SemanticsKind kind);

struct SceneView {
  int index = 0;               // position in the name-sorted list
  Camera camera;               // at the loaded resolution: render at this size
  Camera full_camera;          // as the COLMAP model has it
  std::string name;            // image name in the COLMAP model
  std::string stem;            // file stem: names semantics and outputs
  std::string image_path;      // the file actually read (images_N/ or images/)
  bool downscale = false;      // image_path is full size and gets resized on load
  bool test = false;           // held out by --eval
  std::string semantics_path;  // <stem>_s.npy or masks/<stem>.png; empty = none
  std::string features_path;   // <stem>_f.npy; empty = none
};

// An RGB image [H,W,3] floats in [0,1], row-major.
struct Image {
  int width = 0;
  int height = 0;
  std::vector<float> rgb;
};

// The SAM masks of one view at the loaded resolution.
struct ViewMasks {
  int width = 0;
  int height = 0;
  int layers = 0;               // one label map per SAM level used
  std::vector<int32_t> labels;  // [layers,H,W] mask index 0..count-1, -1 = no mask
  int count = 0;                // masks kept
  std::vector<int64_t> pixels;  // [count] pixel count of each mask
  int feature_dim = 0;          // 0 when the masks carry no CLIP feature (masks/ PNGs)
  std::vector<float> features;  // [count, feature_dim]
  int dropped_contained = 0;    // masks fully inside another mask
  int dropped_empty = 0;        // masks with no pixel left after rescaling

  size_t bytes() const { return labels.size() * 4 + pixels.size() * 8 + features.size() * 4; }
};

struct SceneBounds {
  Eigen::Vector3d lo = Eigen::Vector3d::Zero();  // robust box of the SfM points
  Eigen::Vector3d hi = Eigen::Vector3d::Zero();
  int points_kept = 0;  // points inside the robust box
  int points_total = 0;
  Eigen::Vector3d camera_center = Eigen::Vector3d::Zero();  // mean camera centre
  double camera_radius = 0;  // 1.1 x the largest camera distance from it (3DGS's "extent")

  double longest_extent() const { return (hi - lo).maxCoeff(); }
};

class Scene {
 public:
  // Reads the COLMAP model that find_colmap_model finds and checks that every
  // image (and every semantic file of a scene that has semantics) exists.
  // Throws std::runtime_error naming the file and the fix: missing folders
  // (the image folder before the cameras), missing images, distorted cameras,
  // a resolution whose images_N/ files disagree with the cameras, ...
  static std::unique_ptr<Scene> open(const std::string& dir, const SceneOptions& options = {});

  const std::string& dir() const { return dir_; }
  const SceneOptions& options() const { return options_; }
  const std::vector<SceneView>& views() const { return views_; }
  std::vector<int> train_views() const;  // every view without --eval
  std::vector<int> test_views() const;   // empty without --eval
  // The view whose name, name without extension or stem is `name`; throws
  // std::invalid_argument listing a few valid names.
  int find_view(const std::string& name) const;

  // Pixels of a view, at camera size. Throws std::runtime_error naming the
  // file when it cannot be decoded or its size disagrees with the camera.
  std::shared_ptr<const Image> image(int view);
  // SAM masks of a view (null when the scene has no semantics).
  std::shared_ptr<const ViewMasks> masks(int view);
  // Loads every image and mask once (not kept beyond the cache bound) so bad
  // files are reported before a long job starts. `before_each` (if given)
  // runs before each view: a caller may stop there (a signal, say).
  void check_all(const std::function<void()>& before_each = {});

  SemanticsKind semantics() const { return semantics_; }
  // CLIP feature dimension (0 without language_features/); known after the
  // first masks() call or check_all().
  int feature_dim() const { return feature_dim_; }

  const std::vector<Eigen::Vector3d>& points() const { return points_; }
  const std::vector<Eigen::Vector3<uint8_t>>& colors() const { return colors_; }
  const std::string& points_path() const { return points_path_; }
  // Throws naming the points3D file when the model has no points.
  void require_points() const;
  const SceneBounds& bounds() const { return bounds_; }

  // Non-fatal findings worth telling the user (views without masks, ...).
  const std::vector<std::string>& notes() const { return notes_; }

  struct CacheStats {
    size_t bytes = 0, peak_bytes = 0, hits = 0, misses = 0, evictions = 0;
  };
  const CacheStats& cache_stats() const { return cache_stats_; }

 private:
  Scene() = default;
  std::shared_ptr<const void> cached(int kind, int view);
  void insert(int kind, int view, std::shared_ptr<const void> value, size_t bytes);
  std::shared_ptr<Image> load_image(const SceneView& view) const;
  std::shared_ptr<ViewMasks> load_masks(const SceneView& view);
  void find_semantics();  // open(): semantics_ and each view's semantic files
  void find_bounds();     // open(): bounds_

  std::string dir_;
  SceneOptions options_;
  std::vector<SceneView> views_;
  SemanticsKind semantics_ = SemanticsKind::none;
  int feature_dim_ = 0;
  std::vector<Eigen::Vector3d> points_;
  std::vector<Eigen::Vector3<uint8_t>> colors_;
  std::string points_path_;
  SceneBounds bounds_;
  std::vector<std::string> notes_;

  // LRU cache: front = most recent.
  struct Entry {
    int kind;
    int view;
    std::shared_ptr<const void> value;
    size_t bytes;
  };
  std::list<Entry> lru_;
  std::map<std::pair<int, int>, std::list<Entry>::iterator> index_;
  CacheStats cache_stats_;
};

// Robust bounds of a point set: per axis the 1st..99th percentile box (the
// full box below 100 points). Exposed for tests.
void robust_box(const std::vector<Eigen::Vector3d>& points, Eigen::Vector3d* lo, Eigen::Vector3d* hi, int* kept);

// Drops masks fully contained in another mask (another label map) and masks
// with no pixels, renumbering the rest 0..count-1 in their original order;
// `features` rows follow. Exposed for tests.
void drop_contained_masks(ViewMasks* masks);

}  // namespace ag2gs
