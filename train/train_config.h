// The stage-1 and stage-2 training settings (TrainConfig): defaults,
// validation, the values derived from a scene (SH interval, growth schedule,
// coarse-to-fine levels, the Gaussian budget) and the JSON form stored in
// model.ag2gs and checkpoints.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "host/core/gaussians.h"
#include "host/losses/image_loss.h"
#include "host/optim/adam.h"
#include "train/anchors/anchor_model.h"
#include "train/densify/anchor_growth.h"
#include "train/graph/propagation_loss.h"

namespace ag2gs {

struct TrainConfig : GaussianRates {
  int iterations = 30000;  // stage 1
  // Stage 2: this many more iterations with w_prop L_prop added; -1 =
  // iterations / 6 (the official 5k after 30k), 0 = no stage 2.
  int prop_iters = -1;
  float w_prop = kPropagationWeight;  // weight of the edge-mean L_prop (train/graph/propagation_loss.h)
  float prop_tau = kPropagationTau;   // bilateral bandwidth of L_prop
  uint64_t seed = 0;

  // Representation (children, layers, voxel size, init, highest SH degree).
  AnchorConfig anchors;
  // Iterations between SH degree increments; 0 = min(1000, iterations / (sh_degree + 1)), at least 1.
  int sh_interval = 0;

  // Losses.
  float lambda_ssim = kSsimLambda;  // L_rgb = (1 - lambda) L1 + lambda (1 - SSIM)
  float w_offset = 0.5f;            // w_in, offset regulariser (paper 0.5)
  float w_distortion = 50.f;        // w_d, depth distortion (paper 50, official scripts 20)
  int distortion_from = 0;          // first iteration with the distortion term (official: 10000 at 30k)
  // SAM mask losses on the rendered feature map (paper 2.5 / 0.25, official
  // scripts 0.1 for both from 5k of 30k); only for scenes with masks.
  // Defaults measured on data_samples/synth_small (README, train section).
  float w_is = 0.1f;  // L_is, pulls each mask's features together
  float w_ic = 0.1f;  // L_ic, pushes the mask means apart
  // First iteration (0-based) with the mask losses; -1 = iterations / 6
  // (the official 5k of 30k).
  int mask_from = -1;
  bool mask_alpha_normalise = true;  // G = F / alpha (official), pixels with alpha < 0.1 left out
  // true (the paper's joint loss): the mask losses' gradient reaches every
  // Gaussian parameter, so a thin object that the RGB loss leaves faint
  // (a 2-3 pixel pole) is made opaque where its masks say it is; false: they
  // train the semantic features only (a separate backward pass whose feature
  // gradient alone is kept), and appearance and geometry train exactly as
  // without masks. Measured in the README (query section).
  bool mask_geometry = true;
  // The pixels no SAM mask covers form one more mask in the mask losses
  // (with_unmasked_group in host/losses/mask_loss.h).
  bool mask_unmasked_group = true;
  // Project the semantic features into the unit ball after each of their
  // steps (kernels/anchor_regularisers.cl feature_ball).
  bool feature_ball = true;

  // Learning rates (docs/design.md section 5). The offset rate decays
  // exponentially from init to final over the run; offsets are in voxel
  // units, and with offset_lr_extent (the default, as the official code) the
  // rates are multiplied by the scene's camera radius. Measured without it
  // (README, train section): 1.4-2.4 dB lower test PSNR on the sample scene
  // and the cup at 1500-2000 iterations.
  double offset_lr_init = 1e-3;
  double offset_lr_final = 1e-4;
  bool offset_lr_extent = true;
  double feature_lr = 0.05;  // semantic features (stepped on iterations with the mask losses)
  // sh_dc_lr, sh_rest_lr, opacity_lr, scaling_lr, rotation_lr: GaussianRates (host/optim/adam.h).
  AdamSettings adam;

  bool white_background = false;
  // The sky (host/render/sky.h): a colour per viewing direction, spherical
  // harmonics of this degree (0..3; -1 = none, the constant background
  // above), learned behind the Gaussians with rate sky_lr. kSkyAuto (the
  // default) chooses from the scene: degree 3 when at least
  // kSkyMinOpenShare of the training pixels are open (no SfM point near
  // them), else none; the trainer resolves it before the first step, so
  // its config() and checkpoints hold the choice.
  static constexpr int kSkyAuto = -2;
  static constexpr double kSkyMinOpenShare = 0.05;
  // A degree-3 sky fitted to the open pixels with an RMS error above this
  // says they show surfaces without SfM points (a room's far walls), not
  // an open sky (generated open skies fit within 0.012, rooms 0.07-0.23).
  static constexpr double kSkyMaxFitError = 0.04;
  int sky_degree = kSkyAuto;
  // The far shell: where the open pixels show surfaces without SfM points
  // (above), their rays seed anchors on the top layer where they leave a
  // sphere around the cameras holding 98% of the SfM points, so the room
  // behind the objects gets Gaussians to grow from; false = off (the
  // published rule; the program's default preset turns it on).
  bool far_shell = false;
  double sky_lr = 0.01;

  // Growing. grow_every = 0 turns it off; grow_until = 0 means 2/3 of the
  // iterations (the official 20k of 30k).
  int grow_from = 500;
  int grow_until = 0;
  int grow_every = 100;
  double grow_threshold = 1.5e-4;
  // Growing also adds anchors of a child's own layer where its mean left its
  // voxel (GrowthConfig::same_layer).
  bool grow_same_layer = true;
  // In the same rounds: children below this opacity become copies of their
  // anchor's most opaque child (GrowthConfig::recycle_opacity); 0 = off.
  double recycle_opacity = 0;
  // Growth budgets (GrowthConfig::round_growth, max_gaussians): a round
  // adds at most this fraction of the anchors it starts with (at least 64;
  // 0 = no limit), and the model never holds more than max_gaussians
  // children: -1 = derived from the scene, max(pixels of the largest
  // training view, 2 x the initial Gaussians), effective_max_gaussians();
  // 0 = no limit. Initial counts above an explicit budget are refused.
  double grow_budget = 0.25;
  int64_t max_gaussians = -1;
  // A child grows only when visible in at least this fraction of the
  // iterations since the last round (official: 0.4 = 40 of 100).
  double grow_min_seen = 0.4;
  // Split growth (GrowthConfig::split_voxels): a growing child this many
  // voxels of the layer it grows into wide also asks at +- one standard
  // deviation, and grown children start at the asking child's scale / 1.6;
  // 0 = off (the published rule).
  double grow_split = 0;
  // In the same rounds: remove anchors whose children's mean opacity is
  // below this; 0 = no pruning.
  double prune_opacity = 0.01;
  // After the last stage-1 iteration: remove anchors whose children's mean
  // opacity is below this (children that faded after the last growing
  // round draw almost nothing; the default preset sets 0.02, the recycling
  // threshold); 0 = off.
  double final_prune_opacity = 0;
  // Once, at iteration prune_importance_at (0 = halfway between the end of
  // growing and the last stage-1 iteration): each anchor's children's
  // blending weights are summed over every pixel of the training views at
  // that step's resolution (host/render/importance.h), and the anchors that draw least are removed
  // while together they draw at most this share of the total
  // (least_drawing_anchors). 0 = off (the published rule; the program's
  // default preset sets 0.01).
  double prune_importance = 0;
  int prune_importance_at = 0;
  // In the same rounds: remove anchors none of whose children was visible in
  // the last this many training views (at least a round); 0 = 2 x the number
  // of training views (two epochs: anchors that only a few views see stay),
  // -1 = no unseen pruning.
  int prune_unseen_window = 0;
  // Opacity reset every this many iterations while growing runs; 0 = off.
  int opacity_reset_every = 3000;
  // Growing rounds within this many iterations after a reset skip the opacity pruning.
  int opacity_reset_pause = 500;

  // Coarse-to-fine resolution (as in splatfacto / OpenSplat): stage-1
  // iterations render and compare images downscaled by 2^level, level =
  // max(0, downscales - iteration / res_schedule), each pixel the mean of a
  // 2^level square of the loaded image. Iterations with the mask losses and
  // stage 2 always run at the loaded resolution. downscales 0 = off, -1 =
  // chosen from the training images (auto_downscales); res_schedule 0 =
  // chosen from the iterations (auto_res_schedule). The trainer resolves
  // both before the first step, so its config() and checkpoints hold values.
  int downscales = -1;
  int res_schedule = 0;
  // The screen-space low-pass (the 0.3 px^2 every splat gets) at level L is
  // 0.3 x coarse_lowpass^L pixels^2 of the downscaled image: 1 keeps it at
  // 0.3 of the coarse pixels (a splat then looks 4^L x wider in full-resolution
  // terms, and Gaussians fitted under that blur come out too thin when the
  // resolution doubles), 0.25 keeps 0.3 of the full-resolution pixels at
  // every level. Measured in docs/benchmarks.md ("The low-pass at coarse levels").
  double coarse_lowpass = kDefaultCoarseLowpass;
  static constexpr double kDefaultCoarseLowpass = 0.5;

  // Throws std::invalid_argument naming the first field out of range.
  void validate() const;
  // What `ag2gs train --preset NAME` trains with when no other flag is
  // given: "default" (or "appearance": the measured settings for
  // photographed scenes: children that may outgrow their voxel, 2 per
  // anchor on the SfM points, two seeded layers, growth of at most 10% of
  // the anchors per round, split growth, the far shell, recycling and the
  // importance prune, faster offset and scale rates) or "paper" (the
  // method as published: 200 top-layer cells, 5 children inside their
  // voxels, one seeded layer, no budget, no sky). The fields a preset does
  // not name keep the defaults above. Throws std::invalid_argument for
  // another name.
  static TrainConfig preset(const std::string& name);
  // Every field (for the model archive and metrics).
  nlohmann::json to_json() const;
  // The inverse of to_json (sh_interval and grow_until come back as the
  // effective values, which to_json maps to themselves). Throws
  // std::runtime_error naming a missing or mistyped field.
  static TrainConfig from_json(const nlohmann::json& j);
  // The SH interval actually used.
  int effective_sh_interval() const;
  int effective_grow_until() const;
  int effective_prune_importance_at() const;
  int effective_prop_iters() const { return prop_iters >= 0 ? prop_iters : iterations / 6; }
  // Stage 1 + stage 2.
  int total_iterations() const { return iterations + effective_prop_iters(); }
  int effective_mask_from() const;
  // Levels for training images whose shorter side is `min_side` pixels: as
  // many halvings (at most 3) as keep that side at kCoarseMinSide pixels or
  // more. Measured on the cup (README): 2 levels cut 2000 iterations from
  // 199 s to 126 s at equal test PSNR.
  static constexpr int kCoarseMinSide = 64;
  static int auto_downscales(int min_side);
  // Iterations per level: the run reaches full resolution at
  // kFullResolutionFrom of its iterations, and at 3000 per level
  // (splatfacto's) in long runs. Measured on the cup and the fox
  // (docs/benchmarks.md, "The low-pass at coarse levels"): with the coarse
  // low-pass at 0.5, full resolution from 85% of 2000 iterations is 0.04 dB
  // below full from the middle on the cup, at the tuned command's time.
  static constexpr double kFullResolutionFrom = 0.85;
  static int auto_res_schedule(int iterations, int downscales);
  // The downscale level (a power of two) of stage-1 iteration `it` (0-based),
  // before the mask-loss rule.
  int resolution_level(int it) const {
    return downscales > 0 && res_schedule > 0 ? std::max(0, downscales - it / res_schedule) : 0;  // resolved
  }
  // The low-pass (pixels^2 of the rendered image) at a resolution level.
  float lowpass_at_level(int level) const {
    return static_cast<float>(RenderSettings::kDefaultLowpass * std::pow(coarse_lowpass, level));
  }
  // AnchorGrowth's schedule and rules for a scene with `train_views`
  // training views (grow_from/until/every -> start/stop/every as given, not
  // rescaled; grow_threshold -> grad_threshold, layer factor 2; grow_min_seen
  // -> min_seen_fraction; the prune fields as above).
  GrowthConfig growth_config(size_t train_views) const;
  // max_gaussians with -1 resolved for a scene whose largest training view
  // has `view_pixels` pixels and a model that starts with `initial` children.
  size_t effective_max_gaussians(size_t view_pixels, size_t initial) const;
};

}  // namespace ag2gs
