// The fill of a removal (docs/design.md section 15): new anchors where the
// rays through each view's hole meet the surfaces around it, and, when
// asked for (`remove --iters N`; the default is none, measured), a
// fine-tune of those anchors and the ones near them against targets that
// are the photos outside the object and the inpainted renders inside it.
// Everything far from the hole is frozen (Adam leaves its rows alone), so
// the rest of the scene keeps its bits.
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include "apps/removal/holes.h"
#include "host/device/cl_runtime.h"
#include "host/losses/image_loss.h"
#include "host/optim/adam.h"
#include "host/render/renderer.h"
#include "host/render/sky.h"
#include "host/scene/scene.h"
#include "train/anchors/anchor_model.h"
#include "train/anchors/expander.h"
#include "train/param_groups.h"

namespace ag2gs {

struct FillSettings {
  // A footprint voxel becomes an anchor when hole pixels of at least this
  // many views land in it (one view's depth guess alone is not trusted,
  // unless only one view has a hole).
  int min_views = 2;
  // At most this many fill anchors (0: as many as were removed); the
  // best-supported voxels first.
  size_t max_anchors = 0;
  // Opacity of the fill's children (at the start of the fine-tune, if any).
  // 0.3, measured on the removal benchmark: a fill this transparent blends
  // its guessed colour with what lies behind it. It scored higher than 0.5
  // on seven of eight scenes (two of them held out), and 0.8 and 0.95
  // lower still.
  float opacity = 0.3f;
  // Kept anchors within this many of their own voxel edges of a footprint
  // point are fine-tuned with the fill; the rest are frozen.
  float near = 1.5f;
  // After the fine-tune, fill anchors whose children's mean opacity is
  // below this are dropped again (they found nothing to show).
  float prune_opacity = 0.01f;
  // Hole pixels the kept model already covers with this alpha or more get
  // no fill (HoleFootprint's max_alpha).
  float max_alpha = 0.5f;
  // The fill's colour. Each view that sees a fill voxel gives one estimate,
  // the mean of its target colours there; the estimates are ranked by
  // brightness (sum of the channels) and the one at this quantile is taken.
  // The removed object's shadow on the ring a view's inpainting draws from
  // can only darken its estimate, so an upper quantile (0.75, measured on
  // the removal benchmark) keeps the views that saw the surface lit; 0.5 is
  // the median, 1 the brightest.
  float colour_quantile = 0.75f;

  // Throws std::invalid_argument naming the field.
  void validate() const;
};

// The 3D footprint of the holes: per view, each hole pixel's ray meets the
// surface around the hole at the depth inpainted from the hole's rim (the
// kept model's inverse depth, Navier-Stokes on the float map), held between the
// object's own surface and `behind` object diameters behind it. Points are
// summed per voxel of the model's finest layer with the target's colour.
class HoleFootprint {
 public:
  // Hole pixels where the kept model's alpha is at least max_alpha (and
  // the surface it shows is not a far one behind the object) are skipped.
  HoleFootprint(const VoxelGrid& grid, double object_diameter, float behind, float max_alpha = 1.f);
  // `target`: [H,W,3] the view's inpainted image (its colours go with the points).
  void add_view(const Camera& cam, const ViewHole& hole, const std::vector<float>& target);
  struct Cell {
    double sum[3] = {0, 0, 0};  // points
    size_t points = 0;
    int last_view = -1;
    std::vector<std::array<double, 4>> per_view;  // per view that reaches it: target colour sums, point count
    int views() const { return static_cast<int>(per_view.size()); }
  };
  const std::map<uint64_t, Cell>& cells() const { return cells_; }  // by finest-layer voxel key
  size_t points() const { return points_; }
  int views_with_holes() const { return views_; }

 private:
  VoxelGrid grid_;
  double diameter_;
  float behind_;
  float max_alpha_;
  std::map<uint64_t, Cell> cells_;
  size_t points_ = 0;
  int views_ = 0;
};

struct FillResult {
  std::vector<int> added;          // ids of the new anchors (appended at the end, in voxel-key order)
  std::vector<int> parent;         // [added] the kept anchor each was initialised from
  std::vector<uint8_t> trainable;  // [anchors] 1: fine-tuned (the fill and the kept anchors near it)
  size_t trainable_kept = 0;
  size_t candidates = 0;  // footprint voxels at the anchors' layers with enough views, before the cap
};

// Appends fill anchors to `model` (kept anchors keep their ids and bytes).
// Each footprint voxel takes the layer of the kept anchor nearest to it (the
// surface's own scale); a voxel that already holds an anchor gets none.
// A new anchor copies its nearest kept anchor (add_anchor's parent_child,
// so feature, rotation and offsets follow it), its children take the mean
// target colour of its points as SH DC (higher SH zero) and opacity
// `settings.opacity`.
FillResult add_fill_anchors(AnchorModel& model, const HoleFootprint& footprint, const FillSettings& settings,
                            size_t removed_anchors, uint64_t seed);

// Children of kept anchors that belong to the removed object: an anchor
// the selection kept can hold a child that sits in the object's surface
// and shows its colour (its voxel straddles the two, and its one feature is
// the other surface's). A visible kept child (opacity >= kStrayMinOpacity)
// is stray when, over the finest-layer voxels within `reach` voxels of its
// own along each axis, visible removed Gaussians lie there, its colour (SH
// DC) is within `max_colour` (mean absolute, 0..1) of their mean colour, and
// nearer to it than to the mean colour of the other visible kept Gaussians
// there (so a child among kept Gaussians of its own colour stays, however
// near the object: two touching mugs of close colours). Returns the child
// rows of `model` ([A*K] ids, ascending); `selected`: [A] 1 = removed
// anchor; reach in 0..16.
inline constexpr float kStrayMinOpacity = 0.05f;
std::vector<size_t> stray_children(const AnchorModel& model, const std::vector<uint8_t>& selected,
                                   float max_colour = 0.2f, int reach = 3);

// Per Gaussian of `set`, how much the cameras see of it: the blending
// weight (alpha T, docs/rasterizer.md) it receives, summed over the pixels
// of every camera. That sum is the gradient of the feature image's first
// channel, summed over its pixels, with respect to the Gaussian's first
// feature channel: one forward and one backward pass a camera. With
// `object` ([N] flags), only pixels outside the object's silhouette count
// (where the flagged Gaussians' blending weight is 0.5 or less, the test
// of query masks).
std::vector<double> seen_weight(Renderer& renderer, const GaussianSet& set, const std::vector<Camera>& cameras,
                                const RenderSettings& settings, const std::vector<uint8_t>* object = nullptr);

// Kept anchors the object hid from every photo: each of their visible
// children (opacity >= kStrayMinOpacity) lies within `reach` finest-layer
// voxels of the object's visible Gaussians along each axis, and the
// training views see less than `max_fraction` of it outside the object's
// silhouette (its seen_weight outside it, rendered with the object's
// Gaussians, against its seen_weight rendered with the candidates alone).
// What the photos show of such an anchor they show through the object
// (junk inside it, never reached by a gradient, or an untrained surface
// behind it); deleting the object uncovers it, and no photo vouches for
// what it shows, so it goes with the object and its voxel is free for the
// fill. An anchor with one seen child stays: it is a surface the photos
// show, a neighbour's face the object stood in front of. Anchor ids,
// ascending; reach in 0..16.
std::vector<int> hidden_anchors(Renderer& renderer, const AnchorModel& model, int sh_degree,
                                const std::vector<uint8_t>& selected, const std::vector<Camera>& cameras,
                                const RenderSettings& settings, int reach = 3, double max_fraction = 0.1);

struct FineTuneConfig {
  int iterations = 300;
  uint64_t seed = 1;
  int sh_degree = 3;  // the model's active degree
  std::array<float, 3> background{0.f, 0.f, 0.f};
  float lambda_ssim = 0.2f;
  // Learning rates: the end of training's (the offsets at offset_lr, in
  // world units already scaled by the scene's extent when the model's
  // training did so).
  double offset_lr = 1e-4, scaling_lr = 0.005, rotation_lr = 0.001, opacity_lr = 0.05, sh_dc_lr = 0.0025,
         sh_rest_lr = 0.0025 / 20;
};

// The fine-tune: per iteration one view (a per-epoch shuffle keyed by the
// seed), L = (1 - lambda) L1 + lambda (1 - SSIM) against that view's target,
// gradients through the renderer and the expander, Adam on the trainable
// anchors' children only. The sky (when the model has one) is composited and
// stays fixed. Deterministic like training.
class FillTuner {
 public:
  FillTuner(Runtime& rt, const AnchorModel& model, const std::vector<uint8_t>& trainable, const FineTuneConfig& config,
            const std::vector<float>* sky_coefficients);
  ~FillTuner();
  // One target per training view: the camera and [H,W,3] pixels.
  void add_target(const Camera& camera, std::vector<float> rgb);
  struct Step {
    int iteration = 0;
    double loss = 0, psnr = 0;
    bool skipped = false;
  };
  Step step();
  // The model with the device's values.
  AnchorModel model();

 private:
  Runtime& rt_;
  FineTuneConfig config_;
  AnchorModel model_;
  DeviceAnchors anchors_;
  DeviceAnchorGrads grads_;
  DeviceGaussians gaussians_;
  Expander expander_;
  Renderer renderer_;
  ImageLoss loss_;
  Sky sky_;
  Adam adam_;
  std::unique_ptr<ParamGroups> groups_;
  DeviceBuffer rows_on_, target_dev_, grad_rgb_, grad_alpha_;
  std::vector<Camera> cameras_;
  std::vector<Image> targets_;
  std::vector<float> planar_;
  int iteration_ = 0;
};

}  // namespace ag2gs
