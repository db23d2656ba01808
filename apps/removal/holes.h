// Holes left by removing an object (docs/design.md section 15): the pixels of
// a view that the object covered and that the rest of the model cannot show,
// because no view saw what lay behind it. These are what the removal must
// fill; the object's other pixels already show the background the model
// knows from other views.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "host/core/gaussians.h"
#include "host/render/renderer.h"
#include "host/render/sky.h"

namespace ag2gs {

struct HoleSettings {
  // A pixel is the object's when its Gaussians' blending weights (alpha T)
  // sum to at least this in the full model: at least half its colour.
  float object_weight = 0.5f;
  // After deletion, an object pixel is a hole when its opacity is below this
  float alpha_min = 0.8f;
  // ... or when the first surface it shows lies more than this many object
  // diameters behind the object's surface at that pixel (a far wall seen
  // through unseen ground).
  float behind = 2.0f;
  // Dilation of the hole mask in pixels (a 3x3 cross per step), so the fill
  // covers the object's blurred rim and its contact shadow (5: measured on
  // the removal benchmark, docs/benchmarks.md).
  int dilate = 5;

  // Throws std::invalid_argument naming the field.
  void validate() const;
};

struct ViewHole {
  int width = 0, height = 0;
  std::vector<uint8_t> object;      // [H,W] 1 where the removed Gaussians' weights sum to >= object_weight
  std::vector<uint8_t> hole;        // [H,W] 1 in the (dilated) hole
  std::vector<float> rgb_after;     // [H,W,3] the render after deletion
  std::vector<float> alpha_after;   // [H,W] the kept Gaussians' opacity
  std::vector<float> depth_after;   // [H,W] their mean camera depth (sum w z / alpha; 0 where alpha is 0)
  std::vector<float> object_depth;  // [H,W] the removed Gaussians' mean depth on object pixels, else 0
  size_t object_pixels = 0, hole_pixels = 0, undilated_hole_pixels = 0;
};

// Diameter of the removed Gaussians: twice the 95th percentile of their
// means' distances from the median point (robust to a few stray Gaussians).
double object_diameter(const GaussianSet& removed);

// The holes of one removal, view by view. `kept` and `removed` split one
// model (same SH degree; std::invalid_argument otherwise); both must outlive
// the finder. Per view, two renders: the full model with each Gaussian's
// feature set to (1, camera depth, 0) for removed ones and 0 for kept ones
// (so the blended feature gives the object's summed weight and mean depth
// per pixel), and the kept model alone. The full set is assembled once; a
// view only rewrites the removed Gaussians' depths.
class HoleFinder {
 public:
  HoleFinder(const GaussianSet& kept, const GaussianSet& removed);
  // With a sky (the model's, host/render/sky.h), rgb_after is composited
  // over it; the hole rule reads the Gaussians' alpha alone.
  ViewHole find(Renderer& renderer, const Camera& cam, const HoleSettings& settings, const RenderSettings& render = {},
                Sky* sky = nullptr);
  double diameter() const { return diameter_; }  // object_diameter(removed)

 private:
  const GaussianSet& kept_;
  const GaussianSet& removed_;
  GaussianSet full_;
  double diameter_ = 0;
};

// `mask` ([H,W] 0/1) grown by `steps` pixels, a 3x3 cross per step.
std::vector<uint8_t> dilate_mask(const std::vector<uint8_t>& mask, int width, int height, int steps);

enum class InpaintMethod { kTelea, kNavierStokes, kNone };

// "telea" | "ns" | "none"; throws std::invalid_argument otherwise.
InpaintMethod parse_inpaint_method(const std::string& name);

// Fills the hole of `rgb` ([H,W,3], linear 0..1) by classical inpainting
// (OpenCV's Telea or Navier-Stokes, radius 3 pixels) and returns the filled
// image; kNone returns rgb unchanged. Pixels outside the hole keep their values.
std::vector<float> inpaint_hole(const std::vector<float>& rgb, const std::vector<uint8_t>& hole, int width, int height,
                                InpaintMethod method);

}  // namespace ag2gs
