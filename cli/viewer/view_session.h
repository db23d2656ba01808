// What `ag2gs view` serves, without the HTTP: one trained model on the
// device, the scene's training cameras, the current selection (made by a
// click or a text query exactly as `ag2gs query` makes it) and how it is
// shown. Every method may be called from any thread, one at a time (the
// server serialises them); requests the user got wrong throw
// std::invalid_argument with a message meant for them (HTTP 400).
#pragma once

#include <Eigen/Core>
#include <Eigen/LU>  // Matrix3d::determinant
#include <cstdint>
#include <memory>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <vector>

#include "cli/commands.h"
#include "host/device/cl_runtime.h"
#include "host/io/semantic_io.h"
#include "host/render/renderer.h"
#include "host/render/sky.h"
#include "host/scene/scene.h"
#include "queries/query.h"
#include "train/stage3/instance_map.h"

namespace ag2gs::cli {

struct ViewOptions {
  std::string model;   // MODEL_DIR (model.ag2gs)
  std::string scene;   // SCENE_DIR; empty = no training views (pose renders only)
  std::string vocab;   // phrase -> CLIP embedding; empty = no text queries
  std::string sparse;  // --sparse inside the scene; empty = the scene-folder rule
  int resolution = 0;  // 0 = the model's training -r
  // A model still training (`train --view`): pictures only, no selection
  // (its query graph would be rebuilt for every snapshot).
  bool training = false;
};

// What the picture shows: the model, the selection tinted over it, or the
// per-pixel channels the renderer also blends.
enum class ViewMode { rgb, depth, feature, instance, selection };
// show: everything; hide: everything but the selection (a removal preview);
// only: the selection alone.
enum class Visibility { show, hide, only };

ViewMode parse_view_mode(const std::string& s);      // throws std::invalid_argument
Visibility parse_visibility(const std::string& s);   // throws std::invalid_argument
const char* visibility_name(Visibility v);

// Render sizes the server accepts (each side, and pixels per picture).
constexpr int kMaxViewSide = 4096;
// At most 4K UHD's pixels: one render of that size needs about 0.6 GB of
// device and host memory on the CPU device; larger ones are refused.
constexpr int64_t kMaxViewPixels = 3840LL * 2160;

class ViewSession {
 public:
  ViewSession(Runtime& rt, const ViewOptions& options);
  // The same for a model in memory (the live training view's snapshots).
  ViewSession(Runtime& rt, const ViewOptions& options, TrainedModel trained);

  // Counts, what is available, the training views (camera at the served
  // resolution, full image size, world-to-camera pose) and the scene's centre
  // and radius (for a camera that orbits it).
  nlohmann::json info() const;

  // The camera of a training view at the served resolution; throws for an
  // unknown name (listing a few) or when no scene was given.
  Camera view_camera(const std::string& name) const;
  // A camera resized to width x height (the intrinsics scaled with it);
  // std::invalid_argument outside the render bounds.
  static Camera resized(const Camera& camera, int width, int height);
  // A camera from a pose (R row-major then t, world to camera), intrinsics
  // and size; throws naming what is out of range.
  static Camera pose_camera(const std::vector<double>& pose12, double fx, double fy, double cx, double cy, int width,
                            int height);

  // The picture as JPEG (quality 1-100), or as PNG (lossless, a screenshot)
  // when png is true; *ms gets the render time.
  std::vector<uint8_t> render_image(const Camera& camera, ViewMode mode, int quality, bool png, double* ms);

  // Queries: make the result the current selection and answer
  // {"anchors", "gaussians", "ms", ...}. A click in a training view takes
  // full-size image pixels (as `ag2gs query --click`); a click in a posed
  // camera takes that camera's pixels.
  nlohmann::json click_view(const std::string& view, double x, double y);
  nlohmann::json click_camera(const Camera& camera, double x, double y);
  nlohmann::json text(const std::string& phrase);
  void clear();
  void set_visibility(Visibility v);
  Visibility visibility() const { return visibility_; }

  // The current selection's mask in a training view: the PNG bytes `ag2gs
  // query` writes for the same selection and view.
  std::vector<uint8_t> mask_png(const Camera& camera);
  // The current selection's Gaussians, standard 3DGS layout (query's
  // selection.ply); throws when nothing is selected.
  std::vector<uint8_t> selection_ply() const;

  size_t selected_anchors() const { return selected_.size(); }

 private:
  nlohmann::json finish_query(std::vector<int32_t> selected, double ms, nlohmann::json detail);
  void upload_shown();  // the colour set with the visibility applied
  QueryEngine& engine();  // throws std::invalid_argument while training

  Runtime& rt_;
  ViewOptions options_;
  TrainedModel trained_;
  std::unique_ptr<Scene> scene_;
  int resolution_ = 1;
  bool text_ready_ = false;
  Vocabulary vocab_;
  std::unique_ptr<QueryEngine> engine_;
  GaussianSet colours_;  // expand_reference at the trained SH degree: [A*K]
  Renderer renderer_;
  DeviceGaussians shown_;
  bool shown_dirty_ = true;
  Sky sky_;
  std::unique_ptr<InstanceMapper> instances_;  // null without clusters
  Eigen::Vector3d centre_ = Eigen::Vector3d::Zero();
  double radius_ = 1;
  std::optional<Eigen::Vector3d> up_;  // the scene's up (with --scene), else none
  std::vector<int32_t> selected_;  // ascending anchor ids
  std::vector<uint8_t> in_selection_;
  Visibility visibility_ = Visibility::show;
};

}  // namespace ag2gs::cli
