#include "train/train_settings.h"

#include <limits>
#include <stdexcept>

#include "train/train_config.h"

namespace ag2gs {

namespace {

constexpr std::nullopt_t kKeep = std::nullopt;  // a preset that keeps the initialiser

template <class T>
constexpr auto field = &TrainSetting::of<T>;  // a row's field from a lambda

using Rows = SettingRows<TrainConfig>;

// The run, the sky, the schedule and the losses.
void add_run_and_loss_settings(Rows& add) {
  add(field<int>([](TrainConfig& c) -> int& { return c.iterations; }), "iterations", "--iters",
      "Training iterations (default 30000)")
      .range(1, 1e8);
  add(field<uint64_t>([](TrainConfig& c) -> uint64_t& { return c.seed; }), "seed", "--seed",
      "Random seed: anchor init and view order (default 0)")
      .seed();
  add(field<int>([](TrainConfig& c) -> int& { return c.anchors.sh_degree; }), "anchors.sh_degree", "--sh-degree",
      "Highest SH degree (default 3)")
      .range(0, 3);
  add(field<int>([](TrainConfig& c) -> int& { return c.sh_interval; }), "sh_interval", "--sh-interval",
      "Iterations per SH degree step (default 0 = min(1000, iters / (sh-degree + 1)))")
      .non_negative()
      .effective([](const TrainConfig& c) { return c.effective_sh_interval(); });
  add(field<bool>([](TrainConfig& c) -> bool& { return c.white_background; }), "white_background", "--white-bg",
      "White background instead of black (with a sky: its start)");
  add(field<int>([](TrainConfig& c) -> int& { return c.sky_degree; }), "sky_degree", "--sky-degree",
      "The sky behind the Gaussians: a colour per viewing direction, spherical harmonics of this degree "
      "(0 = one learned colour; -1 = none, a fixed black or white background, as --preset paper; default "
      "-2 = from the scene: 3 when at least 5% of the training pixels have no SfM point near them, else "
      "-1)")
      .range(-2, 3)
      .before(-1)
      .presets(kKeep, -1);
  add(field<bool>([](TrainConfig& c) -> bool& { return c.far_shell; }), "far_shell", "--far-shell",
      "Where the pixels without SfM points show surfaces rather than an open sky (a degree-3 sky fits "
      "them with an RMS error above 0.04, as a room's far walls), seed anchors from them on a sphere "
      "around the cameras (default true; false: --preset paper and the official code)")
      .before(0)
      .presets(1, kKeep)
      .with_value();
  add(field<double>([](TrainConfig& c) -> double& { return c.sky_lr; }), "sky_lr", "--lr-sky",
      "Learning rate of the sky's coefficients (default 0.01)")
      .range(0, 100)
      .before(0.01);
  add(field<float>([](TrainConfig& c) -> float& { return c.lambda_ssim; }), "lambda_ssim", "--lambda-ssim",
      "Weight of 1 - SSIM in L_rgb (default 0.2)")
      .range(0, 1);
  add(field<float>([](TrainConfig& c) -> float& { return c.w_offset; }), "w_offset", "--w-offset",
      "Weight of the offset regulariser L_in (default 0.5)")
      .range(0, 1e6);
  add(field<float>([](TrainConfig& c) -> float& { return c.w_distortion; }), "w_distortion", "--w-dist",
      "Weight of the depth distortion L_d (default 50)")
      .range(0, 1e6);
  add(field<int>([](TrainConfig& c) -> int& { return c.distortion_from; }), "distortion_from", "--dist-from",
      "First iteration with the distortion term (default 0)")
      .non_negative();
  add(field<int>([](TrainConfig& c) -> int& { return c.downscales; }), "downscales", "--downscales",
      "Coarse-to-fine: start at the images divided by 2^N, doubling the resolution every --res-schedule "
      "iterations (default -1: as many halvings, at most 3, as keep the shorter side >= 64 px; 0 = off, "
      "as --preset paper; mask-loss iterations and stage 2 always at full resolution)")
      .range(-1, 6)
      .before(0)
      .presets(kKeep, 0);
  add(field<int>([](TrainConfig& c) -> int& { return c.res_schedule; }), "res_schedule", "--res-schedule",
      "Iterations per resolution doubling with --downscales (default 0: 0.85 x iters / levels, at most "
      "3000, so full resolution for the last 15% of the run)")
      .range(0, 1e8)
      .before(250);
  add(field<double>([](TrainConfig& c) -> double& { return c.coarse_lowpass; }), "coarse_lowpass", "--coarse-lowpass",
      "At the coarse levels of --downscales, the screen-space low-pass is 0.3 px^2 x F^level of the "
      "downscaled image (default 0.5; 1 = 0.3 coarse px at every level, 0.25 = 0.3 full-resolution px)")
      .range(1e-6, 1)
      .before(1.0);
  add(field<float>([](TrainConfig& c) -> float& { return c.w_is; }), "w_is", "--w-is",
      "Weight of the mask-internal loss L_is on the rendered features (default 0.1; scenes with masks)")
      .range(0, 1e6);
  add(field<float>([](TrainConfig& c) -> float& { return c.w_ic; }), "w_ic", "--w-ic",
      "Weight of the mask-contrast loss L_ic (default 0.1)")
      .range(0, 1e6);
  add(field<int>([](TrainConfig& c) -> int& { return c.mask_from; }), "mask_from", "--mask-from",
      "First iteration with the mask losses (default -1 = iters / 6, the official 5k of 30k)")
      .range(-1, std::numeric_limits<int>::max())
      .effective([](const TrainConfig& c) { return c.effective_mask_from(); });
  add(field<bool>([](TrainConfig& c) -> bool& { return c.mask_alpha_normalise; }), "mask_alpha_normalise",
      "!--no-mask-alpha-norm",
      "Mask losses on the raw rendered feature instead of the feature divided by alpha (default: divided, "
      "pixels with alpha < 0.1 left out)");
  add(field<bool>([](TrainConfig& c) -> bool& { return c.mask_geometry; }), "mask_geometry",
      "--mask-geometry,!--mask-features-only",
      "--mask-geometry (default): the mask losses' gradient reaches every Gaussian parameter (the "
      "paper's joint loss); --mask-features-only: it trains the semantic features alone, so appearance "
      "and geometry train as without masks");
  add(field<bool>([](TrainConfig& c) -> bool& { return c.mask_unmasked_group; }), "mask_unmasked_group",
      "!--no-unmasked-group",
      "Leave pixels without a SAM mask out of the mask losses (default: they form one more mask, so "
      "object features are pushed away from the unmasked surroundings)")
      .before(0);
  add(field<bool>([](TrainConfig& c) -> bool& { return c.grow_same_layer; }), "grow_same_layer",
      "!--no-grow-same-layer",
      "Grow only finer anchors (default: also anchors of a child's own layer where its mean left its "
      "voxel, so the model spreads into regions without SfM points)")
      .before(0);
  add(field<double>([](TrainConfig& c) -> double& { return c.recycle_opacity; }), "recycle_opacity",
      "--recycle-opacity",
      "In growing rounds, children of a kept anchor below this opacity become copies of its most opaque "
      "child, the two sharing its opacity (default 0.02; --preset paper 0 = off)")
      .range(0, 0.999)
      .before(0)
      .presets(0.02, kKeep);
  add(field<bool>([](TrainConfig& c) -> bool& { return c.feature_ball; }), "feature_ball", "!--no-feature-ball",
      "Let the semantic features grow without bound (default: projected into the unit ball after each "
      "step, so the graph stages' absolute thresholds keep their meaning)")
      .before(0);
}

// The learning rates and the anchors.
void add_rate_and_anchor_settings(Rows& add) {
  add(field<double>([](TrainConfig& c) -> double& { return c.feature_lr; }), "feature_lr", "--lr-feature",
      "Semantic feature learning rate (default 0.05)")
      .range(0, 100);
  add(field<double>([](TrainConfig& c) -> double& { return c.offset_lr_init; }), "offset_lr_init", "--lr-offset",
      "Offset learning rate at the start (default 1e-2; --preset paper 1e-3; voxel units)")
      .range(0, 100)
      .presets(1e-2, kKeep);
  add(field<double>([](TrainConfig& c) -> double& { return c.offset_lr_final; }), "offset_lr_final",
      "--lr-offset-final", "Offset learning rate at the end (default 1e-4)")
      .range(0, 100);
  add(field<bool>([](TrainConfig& c) -> bool& { return c.offset_lr_extent; }), "offset_lr_extent",
      "--lr-offset-extent,!--no-lr-offset-extent",
      "Multiply the offset rates by the camera radius (default on, as the official code; "
      "--no-lr-offset-extent for voxel units alone)");
  add(field<double>([](TrainConfig& c) -> double& { return c.sh_dc_lr; }), "sh_dc_lr", "--lr-sh",
      "SH DC learning rate (default 0.0025)")
      .range(0, 100);
  add(field<double>([](TrainConfig& c) -> double& { return c.sh_rest_lr; }), "sh_rest_lr", "--lr-sh-rest",
      "Higher SH learning rate (default 0.0025 / 20)")
      .range(0, 100);
  add(field<double>([](TrainConfig& c) -> double& { return c.opacity_lr; }), "opacity_lr", "--lr-opacity",
      "Opacity logit learning rate (default 0.05)")
      .range(0, 100);
  add(field<double>([](TrainConfig& c) -> double& { return c.scaling_lr; }), "scaling_lr", "--lr-scaling",
      "Scale logit learning rate (default 0.01; --preset paper 0.005)")
      .range(0, 100)
      .presets(0.01, kKeep);
  add(field<double>([](TrainConfig& c) -> double& { return c.rotation_lr; }), "rotation_lr", "--lr-rotation",
      "Rotation learning rate (default 0.001)")
      .range(0, 100);
  add(field<int>([](TrainConfig& c) -> int& { return c.anchors.top_cells; }), "anchors.top_cells", "--top-cells",
      "Top-layer voxels along the longest robust extent of the SfM points (default: the voxel is "
      "chosen from the scene, a finest-layer voxel of about a pixel at the points' median depth; "
      "--preset paper: 200)")
      .positive()
      .automatic(0)
      .presets(kKeep, 200);
  add(field<double>([](TrainConfig& c) -> double& { return c.anchors.voxel_size; }), "anchors.voxel_size",
      "--voxel-size", "Top-layer voxel edge in world units (overrides --top-cells and the scene's choice)")
      .positive()
      .automatic(0)
      .before(0);
  add(field<int64_t>([](TrainConfig& c) -> int64_t& { return c.max_gaussians; }), "max_gaussians", "--max-gaussians",
      "Growth never takes the model past this many Gaussians (default: the pixels of a training view, "
      "at least twice the initial count; 0 = no limit; below the initial count is an error)")
      .range(0, static_cast<double>(std::numeric_limits<int64_t>::max()))
      .automatic(-1)
      .before(0)
      .presets(kKeep, 0);
  add(field<double>([](TrainConfig& c) -> double& { return c.grow_budget; }), "grow_budget", "--grow-budget",
      "A growing round adds at most this fraction of the anchors (at least 64; default 0.1, the "
      "library's 0.25; 0 = no limit); the children asking hardest win")
      .range(0, 1e6)
      .before(0)
      .presets(0.1, 0);
  add(field<int>([](TrainConfig& c) -> int& { return c.anchors.children; }), "anchors.children", "--children",
      "Gaussians per anchor (default 2; --preset paper 5)")
      .range(1, 64)
      .presets(2, kKeep);
  add(field<int>([](TrainConfig& c) -> int& { return c.anchors.init_layer; }), "anchors.init_layer", "--init-layer",
      "First voxel layer the SfM points initialise anchors on (default 0 = the top layer, as the "
      "official code; -1 = every layer, as the paper says)")
      .range(-1, 15);
  add(field<int>([](TrainConfig& c) -> int& { return c.anchors.init_layers; }), "anchors.init_layers", "--init-layers",
      "Layers the SfM points initialise anchors on, from --init-layer down (default 2: the top layer "
      "and the next, so thin objects start with anchors of their own; --preset paper 1, the official "
      "code)")
      .range(1, 16)
      .before(1)
      .presets(2, 1);
  add(field<float>([](TrainConfig& c) -> float& { return c.anchors.init_scale; }), "anchors.init_scale", "--init-scale",
      "Scale of a fresh child as a fraction of its voxel edge (default 0.5; below --scale-cap)")
      .range(1e-4, 1023);
  add(field<float>([](TrainConfig& c) -> float& { return c.anchors.scale_cap; }), "anchors.scale_cap", "--scale-cap",
      "A child's scale is at most this many voxel edges (default 64; --preset paper 1: a child "
      "never outgrows its voxel)")
      .range(1, 1024)
      .before(1)
      .presets(64, kKeep);
  add(field<int>([](TrainConfig& c) -> int& { return c.anchors.scale_cap_layers; }), "anchors.scale_cap_layers",
      "--scale-cap-layers",
      "--scale-cap holds on this many of the coarsest layers (1 = the top layer only); finer layers keep "
      "their children inside their voxels (default: every layer)")
      .range(1, 16)
      .before(kMaxLayers);
  add(field<float>([](TrainConfig& c) -> float& { return c.anchors.init_opacity; }), "anchors.init_opacity",
      "--init-opacity", "Opacity of a fresh child (default 0.1)")
      .range(1e-4, 0.9999);
  add(field<bool>([](TrainConfig& c) -> bool& { return c.anchors.init_children_at_points; }),
      "anchors.init_children_at_points", "--init-children-at-points,!--init-children-random",
      "Seeded anchors put their children on the SfM points of their voxel, with those points' colours "
      "(default; --init-children-random, as the official code and --preset paper: random offsets and "
      "the voxel's mean colour)")
      .before(0)
      .presets(1, kKeep);
}

// Growing and pruning, stage 2, and the settings without a flag.
void add_growth_and_stage2_settings(Rows& add) {
  add(field<int>([](TrainConfig& c) -> int& { return c.grow_from; }), "grow.from", "--grow-from",
      "First iteration of anchor growing (default 500)")
      .non_negative();
  add(field<int>([](TrainConfig& c) -> int& { return c.grow_until; }), "grow.until", "--grow-until",
      "Last iteration of anchor growing (default 0 = 2/3 of --iters)")
      .non_negative()
      .effective([](const TrainConfig& c) { return c.effective_grow_until(); });
  add(field<int>([](TrainConfig& c) -> int& { return c.grow_every; }), "grow.every", "--grow-every",
      "Iterations between growing rounds (default 100; 0 = no growing)")
      .non_negative();
  add(field<double>([](TrainConfig& c) -> double& { return c.grow_threshold; }), "grow.threshold", "--grow-threshold",
      "Mean screen-space gradient (NDC units) above which a child grows a finer anchor (default 1.5e-4, "
      "x2 per layer)")
      .range(1e-12, 1000);
  add(field<double>([](TrainConfig& c) -> double& { return c.grow_min_seen; }), "grow.min_seen", "--grow-min-seen",
      "Fraction of a round's iterations a child must be visible in to grow (default 0.1, so the far "
      "background that a circling capture sees in a few views grows too; --preset paper and the "
      "official code 0.4)")
      .range(0, 1)
      .presets(0.1, kKeep);
  add(field<double>([](TrainConfig& c) -> double& { return c.grow_split; }), "grow.split", "--grow-split",
      "Split growth, as 3DGS splits a large Gaussian: a growing child at least this many voxels of the "
      "layer it grows into wide along one of its two longest axes also asks for anchors at +-1 "
      "standard deviation along it, and the anchors it grows start at its scale / 1.6 "
      "(default 4; 0 = off: one anchor at the child's mean whose children start at --init-scale, "
      "--preset paper and the official code)")
      .range(0, 1e6)
      .before(0)
      .presets(4, kKeep);
  add(field<double>([](TrainConfig& c) -> double& { return c.prune_opacity; }), "prune_opacity", "--prune-opacity",
      "In growing rounds, remove anchors whose children's mean opacity is below this (default 0.01; 0 = "
      "off)")
      .range(0, 0.999);
  add(field<double>([](TrainConfig& c) -> double& { return c.final_prune_opacity; }), "final_prune_opacity",
      "--final-prune-opacity",
      "After the last stage-1 iteration, remove anchors whose children's mean opacity is below this "
      "(default 0.015; --preset paper: 0 = off)")
      .range(0, 0.999)
      .before(0)
      .presets(0.015, kKeep);
  add(field<double>([](TrainConfig& c) -> double& { return c.prune_importance; }), "prune_importance",
      "--prune-importance",
      "Once, at --prune-importance-at, remove the anchors that draw least (their Gaussians' blending "
      "weights summed over every pixel of the training views) while together they draw at most this "
      "share of the pictures (default 0.01; --preset paper: 0 = off)")
      .range(0, 0.999)
      .before(0)
      .presets(0.01, kKeep);
  add(field<int>([](TrainConfig& c) -> int& { return c.prune_importance_at; }), "prune_importance_at",
      "--prune-importance-at",
      "The iteration of the importance prune (default 0: halfway between the end of growing and --iters)")
      .range(0, std::numeric_limits<int>::max())
      .before(0)
      .effective([](const TrainConfig& c) { return c.effective_prune_importance_at(); });
  add(field<int>([](TrainConfig& c) -> int& { return c.prune_unseen_window; }), "prune_unseen_window",
      "--prune-unseen-window",
      "In growing rounds, remove anchors none of whose children was visible in the last N training views "
      "(default 0 = 2 x training views; -1 = off)")
      .range(-1, std::numeric_limits<int>::max());
  add(field<int>([](TrainConfig& c) -> int& { return c.opacity_reset_every; }), "opacity_reset_every",
      "--opacity-reset-every",
      "Reset every opacity to at most 0.01 every N iterations while growing runs (default 3000; 0 = off)")
      .non_negative();
  add(field<int>([](TrainConfig& c) -> int& { return c.opacity_reset_pause; }), "opacity_reset_pause",
      "--opacity-reset-pause",
      "Growing rounds this many iterations after a reset do not prune by opacity (default 500)")
      .non_negative();
  add(field<int>([](TrainConfig& c) -> int& { return c.prop_iters; }), "prop_iters", "--prop-iters",
      "Stage-2 iterations after stage 1 (default -1 = iters / 6, the official 5000 after 30000; 0 = no "
      "stage 2)")
      .range(-1, std::numeric_limits<int>::max())
      .before(0)
      .effective([](const TrainConfig& c) { return c.effective_prop_iters(); });
  add(field<float>([](TrainConfig& c) -> float& { return c.w_prop; }), "w_prop", "--w-prop",
      "Weight of the propagation loss L_prop (a mean over edges) in stage 2 (default 10; the paper's 0.01 "
      "is on a sum)")
      .range(0, 1e6)
      .before(0.01);
  add(field<float>([](TrainConfig& c) -> float& { return c.prop_tau; }), "prop_tau", "--prop-tau",
      "Bilateral bandwidth tau of L_prop (default 0.05)")
      .range(1e-9, 1e6)
      .before(kPropagationTau);
  add(field<int>([](TrainConfig& c) -> int& { return c.anchors.layers; }), "anchors.layers", "", "");
  add(field<int>([](TrainConfig& c) -> int& { return c.anchors.layer_ratio; }), "anchors.layer_ratio", "", "");
  add(field<float>([](TrainConfig& c) -> float& { return c.anchors.init_feature; }), "anchors.init_feature", "", "");
  add(field<double>([](TrainConfig& c) -> double& { return c.adam.beta1; }), "adam.beta1", "", "");
  add(field<double>([](TrainConfig& c) -> double& { return c.adam.beta2; }), "adam.beta2", "", "");
  add(field<double>([](TrainConfig& c) -> double& { return c.adam.eps; }), "adam.eps", "", "");
}

// In --help's order; the settings without a flag last.
std::vector<TrainSetting> build_table() {
  Rows rows;
  add_run_and_loss_settings(rows);
  add_rate_and_anchor_settings(rows);
  add_growth_and_stage2_settings(rows);
  return rows.t;
}

}  // namespace

const std::vector<TrainSetting>& train_settings() {
  static const std::vector<TrainSetting> table = build_table();
  return table;
}

std::optional<double> train_preset_value(const TrainSetting& s, const std::string& preset) {
  check_train_preset(preset);
  return preset == "paper" ? s.in_paper : s.in_default;
}

void check_train_preset(const std::string& name) {
  if (name != "default" && name != "appearance" && name != "paper")
    throw std::invalid_argument("preset '" + name + "': choose default (also called appearance) or paper");
}

void apply_train_preset(TrainConfig& c, const std::string& name, const std::function<bool(const TrainSetting&)>& keep) {
  check_train_preset(name);
  const TrainConfig initial;
  for (const TrainSetting& s : train_settings()) {
    if (!s.in_a_preset() || (keep && keep(s))) continue;
    if (const std::optional<double> v = train_preset_value(s, name))
      s.assign(c, *v);
    else
      s.set(c, s.get(initial));
  }
}

}  // namespace ag2gs
