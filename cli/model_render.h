// A trained model (or a 3DGS .ply) on the device, rendered view by view into
// the arrays `ag2gs render` writes: RGB over the model's learned sky, mean
// depth, alpha, the 3 rendered feature channels and instance ids. Shared by
// the render command and the Python module (python/), so both give the same
// bits.
#pragma once

#include <array>
#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "host/core/gaussians.h"

namespace ag2gs {
class Runtime;
}

namespace ag2gs::cli {

// The outputs a render can give, in this order.
inline const std::vector<std::string>& render_output_names() {
  static const std::vector<std::string> names = {"rgb", "depth", "alpha", "feature", "instance"};
  return names;
}
// Throws std::invalid_argument naming `flag` unless every output is one of
// render_output_names() and there is at least one.
void check_render_outputs(const std::vector<std::string>& outputs, const std::string& flag);

struct ModelRenderOptions {
  std::string model;  // a model folder written by `ag2gs train` (or empty)
  std::string ply;    // a Gaussian .ply instead (or empty)
  std::vector<std::string> outputs = {"rgb"};
  // A fixed background instead of the model's learned sky.
  std::optional<std::array<float, 3>> background;
  bool drop_invalid = false;  // leave out Gaussians with invalid numbers instead of refusing the file
};

// One view's arrays, row-major; only the outputs asked for are filled.
struct ModelFrame {
  int width = 0, height = 0;
  std::vector<float> rgb;         // [H,W,3] in [0,1], over the sky or background
  std::vector<float> depth;       // [H,W] mean depth along the ray, 0 where nothing was hit
  std::vector<float> alpha;       // [H,W] (always filled)
  std::vector<float> feature;     // [H,W,3]
  std::vector<int32_t> instance;  // [H,W] cluster ids, -1 = none
  size_t intersections = 0;
};

class ModelRender {
 public:
  // Reads and checks the model (or the .ply) and uploads it; throws naming
  // the file and the fix when it cannot be rendered.
  ModelRender(Runtime& rt, const ModelRenderOptions& options);
  ~ModelRender();
  ModelRender(const ModelRender&) = delete;
  ModelRender& operator=(const ModelRender&) = delete;

  // The camera at the size to render (scale_camera already applied).
  ModelFrame render(const Camera& camera);

  size_t gaussians() const;
  int sh_degree() const;
  bool has_sky() const;
  const std::string& ply() const;  // the Gaussian file rendered (or the model's objects file)

 private:
  struct State;
  std::unique_ptr<State> s_;
};

}  // namespace ag2gs::cli
