// Stage-1 training (appearance, DESIGN.md sections 2, 3, 8, 9): anchors from
// the scene's SfM points, then per iteration one training view
//
//   expand anchors -> render -> L = L_rgb + w_in L_in + w_d L_d
//   -> renderer backward -> expander backward (+ dL_in/d offset)
//   -> non-finite check (skip the step) -> Adam per parameter group
//
// with L_rgb = (1 - lambda) L1 + lambda (1 - SSIM) (host/image_loss.h),
// L_in = mean over offsets of exp(relu(|o|^2 - 1)) (offsets in voxel units),
// L_d = mean over pixels of the renderer's distortion output.
//
// Growing and pruning (DESIGN.md section 2) are AnchorGrowth's
// (stages/anchor_growth.h): per child, the screen-space positional gradient
// norm (3DGS's NDC units) is summed on the device over the views where it was
// visible; every grow_every iterations in [grow_from, grow_until] a child seen
// in at least grow_min_seen of the round whose mean exceeds grow_threshold *
// 2^layer asks for an anchor of the next finer layer at the voxel holding its
// mean (one per voxel, in voxel-key order); in the same rounds anchors whose
// children's mean opacity is below prune_opacity, or none of whose children
// was seen in the last prune_unseen_window views, are removed. The optimiser
// state follows the rows (GrowthResult's gather maps).
//
// Mask losses (DESIGN.md section 3, host/mask_loss.h): when the scene has
// SAM masks and the iteration is at least mask_from, the view's rendered
// feature map F (optionally divided by the accumulated alpha) gets
// w_is L_is + w_ic L_ic; the gradient goes back through the renderer and the
// expander to the anchors' semantic features, which Adam steps with
// feature_lr on those iterations only; with mask_geometry (the default) the
// same gradient also reaches every Gaussian parameter, as the RGB loss's
// does. Scenes without masks train appearance only.
// Two additions to the method as published, both measured (see the README):
// the pixels no mask covers form one more mask (mask_unmasked_group), so the
// objects' features are pushed away from their unmasked surroundings; and
// after each step the features are projected into the unit ball
// (feature_ball), so the contrast term cannot inflate their scale past the
// absolute thresholds of stages 2 and 3 and the queries.
//
// Opacity reset (3DGS): at every opacity_reset_every-th iteration before
// growing stops (iteration < grow_until, whether or not growing is on), every
// child's opacity logit becomes min(current, logit(0.01)) and the opacity
// group's Adam moments are zeroed (its step count is kept). Growing rounds in
// the opacity_reset_pause iterations after a reset do not prune by opacity:
// the mean opacity says nothing until training has restored it.
//
// Stage 2 (DESIGN.md section 4): after the `iterations` stage-1 steps come
// prop_iters more with the same losses plus w_prop L_prop
// (stages/propagation_loss.h) over the anchor graph (stages/anchor_graph.h),
// which is built once at the first stage-2 step (growing, pruning and opacity
// resets are over by then: none of them runs in stage 2). The features are
// stepped on every stage-2 iteration (mask losses where the view has masks,
// plus the propagation term). The graph goes into the checkpoint and
// model.ag2gs; a run resumed inside stage 2 reads it back.
//
// Stage 3 (run_stage3_on_model): clusters of the saved model's anchors over
// its graph and, for scenes with CLIP features, one language feature per
// cluster, written back into model.ag2gs.
//
// Checkpoints (save_checkpoint, resume): MODEL_DIR/checkpoint.ag2gs holds the
// anchor model, every Adam group's moments and step count, AnchorGrowth's
// statistics and counters, the iteration, the config and a fingerprint of the
// scene; everything else a step uses is a function of (config, iteration), so
// a resumed run continues bit for bit.
//
// Deterministic: the view order comes from a counter-based hash of (seed,
// epoch); every kernel on the path is free of floating-point atomics, so the
// same seed on the same device gives the same bits in the model files.
#pragma once

#include <cstddef>
#include <cstdint>
#include <functional>
#include <memory>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "host/adam.h"
#include "host/cl_runtime.h"
#include "host/image_loss.h"
#include "host/mask_loss.h"
#include "host/renderer.h"
#include "host/scene.h"
#include "stages/anchor_graph.h"
#include "stages/anchor_growth.h"
#include "stages/anchor_model.h"
#include "stages/expander.h"
#include "stages/language.h"
#include "stages/propagation_loss.h"
#include "stages/voxel_rule.h"

namespace ag2gs {

struct TrainConfig {
  int iterations = 30000;  // stage 1
  // Stage 2: this many more iterations with w_prop L_prop added; -1 =
  // iterations / 6 (the official 5k after 30k), 0 = no stage 2.
  int prop_iters = -1;
  float w_prop = kPropagationWeight;  // weight of the edge-mean L_prop (stages/propagation_loss.h)
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
  // (with_unmasked_group in host/mask_loss.h).
  bool mask_unmasked_group = true;
  // Project the semantic features into the unit ball after each of their
  // steps (kernels/train.cl feature_ball).
  bool feature_ball = true;

  // Learning rates (DESIGN.md section 9). The offset rate decays
  // exponentially from init to final over the run; offsets are in voxel
  // units, and with offset_lr_extent (the default, as the official code) the
  // rates are multiplied by the scene's camera radius. Measured without it
  // (README, train section): 1.4-2.4 dB lower test PSNR on the sample scene
  // and the cup at 1500-2000 iterations.
  double offset_lr_init = 1e-3;
  double offset_lr_final = 1e-4;
  bool offset_lr_extent = true;
  double feature_lr = 0.05;  // semantic features (stepped on iterations with the mask losses)
  double sh_dc_lr = 0.0025;
  double sh_rest_lr = 0.0025 / 20;
  double opacity_lr = 0.05;
  double scaling_lr = 0.005;
  double rotation_lr = 0.001;
  AdamSettings adam;

  bool white_background = false;

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
  // In the same rounds: remove anchors whose children's mean opacity is
  // below this; 0 = no pruning.
  double prune_opacity = 0.01;
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

  // Throws std::invalid_argument naming the first field out of range.
  void validate() const;
  // Every field (for the model archive and metrics).
  nlohmann::json to_json() const;
  // The inverse of to_json (sh_interval and grow_until come back as the
  // effective values, which to_json maps to themselves). Throws
  // std::runtime_error naming a missing or mistyped field.
  static TrainConfig from_json(const nlohmann::json& j);
  // The SH interval actually used.
  int effective_sh_interval() const;
  int effective_grow_until() const;
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
  // Iterations per level: the run reaches full resolution by its middle,
  // and by iteration 3 x 2000 (splatfacto's 3000 per level) in long runs.
  static int auto_res_schedule(int iterations, int downscales);
  // The downscale level (a power of two) of stage-1 iteration `it` (0-based),
  // before the mask-loss rule.
  int resolution_level(int it) const {
    return downscales > 0 && res_schedule > 0 ? std::max(0, downscales - it / res_schedule) : 0;  // resolved
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

// What one iteration did.
struct StepStats {
  int iteration = 0;  // 1-based number of the step just taken
  int view = -1;
  bool skipped = false;  // non-finite gradients: no parameter changed
  uint64_t nonfinite = 0;
  double loss = 0;  // total (L_in only when computed, see with_offset_loss)
  double l1 = 0, ssim = 1, psnr = 0;
  double distortion = 0;      // mean over pixels (unweighted)
  double offset_reg = 0;      // L_in (unweighted), 0 unless computed this step
  bool stage2 = false;        // a stage-2 step (L_prop included in loss)
  double l_prop = 0;          // unweighted L_prop of this step (stage 2)
  bool with_masks = false;    // the mask losses were applied (and included in loss)
  double l_is = 0, l_ic = 0;  // unweighted mask losses of this view
  int masks = 0;              // masks of this view with rendered pixels
  bool with_offset_loss = false;
  int sh_degree = 0;
  size_t intersections = 0;
  int downscale = 1;           // the images of this step were the loaded ones divided by this
  int grown = 0;               // anchors added after this step
  int over_budget = 0;         // anchors asked for after this step but left out by the budgets
  bool opacity_reset = false;  // opacities reset after this step
  int pruned = 0;              // anchors removed after this step
  int recycled = 0;            // children recycled after this step (TrainConfig::recycle_opacity)
};

struct EvalStats {
  int views = 0;
  double psnr = 0, ssim = 0, l1 = 0;  // means over the views
};

class Trainer {
 public:
  // Opens nothing: `scene` is the caller's (its resolution and split are
  // used as they are). Throws when the config is invalid or the scene has no
  // points (Scene::require_points).
  Trainer(Runtime& rt, Scene& scene, const TrainConfig& config);
  ~Trainer();

  // Anchors from the scene's SfM points (config.anchors, seed); uploads them
  // and creates the optimiser state. Called by the constructor.
  const AnchorInitStats& init_stats() const { return init_stats_; }
  // How the top-layer voxel was chosen (config.anchors, stages/voxel_rule.h).
  const VoxelChoice& voxel_choice() const { return voxel_choice_; }

  // One training iteration. With compute_offset_loss the (unweighted) L_in
  // is read back and included in the stats' loss (a host synchronisation,
  // for progress lines); the gradient is always applied.
  // before_rounds, when set, runs after the parameter update and before
  // this iteration's growing round and opacity reset (3DGS evaluates there:
  // a test at a reset iteration then sees the trained opacities, not the
  // reset ones). It must leave the parameters alone (evaluate() does).
  StepStats step(bool compute_offset_loss = false, const std::function<void()>& before_rounds = {});

  // Mean PSNR/SSIM/L1 over `views` (rendered at the active SH degree, no
  // clamping of the rendered colours).
  EvalStats evaluate(const std::vector<int>& views);

  // MODEL_DIR/checkpoint.ag2gs (save_checkpoint), MODEL_DIR/model.ag2gs
  // (anchors, config, iteration, seed) and MODEL_DIR/point_cloud.ply (the
  // expanded Gaussians, standard 3DGS), each written atomically.
  void save(const std::string& model_dir);
  // MODEL_DIR/checkpoint.ag2gs alone, atomically.
  void save_checkpoint(const std::string& model_dir);
  // Settings of the caller's that shape the run's files but are not the
  // trainer's (the stages to run, stage 3's settings): stored in the
  // checkpoint as meta.checkpoint.run, for a resumed run to take back.
  void set_run_record(nlohmann::json record) { run_record_ = std::move(record); }
  // Continues from MODEL_DIR/checkpoint.ag2gs: replaces the model, the
  // optimiser state, the growth statistics and the iteration. Throws
  // std::runtime_error naming the file when it is missing or broken, was
  // written for another scene (views, cameras, points, resolution, split) or
  // with another config (naming the fields that differ).
  void resume(const std::string& model_dir);
  static std::string checkpoint_path(const std::string& model_dir);
  // A fingerprint of what the trainer reads from the scene: view names,
  // cameras at the loaded resolution, split, SfM points.
  nlohmann::json scene_fingerprint() const;

  int iteration() const { return iteration_; }
  // The stage-2 anchor graph (empty before the first stage-2 step).
  bool has_graph() const { return graph_ready_; }
  const AnchorGraph& graph() const { return graph_; }
  int active_sh_degree() const;
  size_t anchors() const { return model_.size(); }
  size_t gaussians() const { return model_.gaussians(); }
  // The Gaussian budget growth keeps to (0 = none; TrainConfig::max_gaussians).
  size_t max_gaussians() const { return max_gaussians_; }
  // The model with the device's current values.
  const AnchorModel& model();
  const TrainConfig& config() const { return config_; }
  // The training view of iteration `it` (0-based): a permutation of the
  // training views per epoch from a counter-based hash of (seed, epoch).
  int view_for_iteration(int it) const;
  double offset_lr(int it) const;
  // Whether the step numbered `iteration` (1-based) ends with an opacity reset.
  bool opacity_reset_due(int iteration) const;
  // The optimiser state of a parameter group: "offset", "scaling",
  // "rotation", "opacity", "sh_dc", "sh_rest", "feature". Throws
  // std::invalid_argument for another name.
  AdamGroup& adam_group(const std::string& name);

 private:
  Runtime& rt_;
  Scene& scene_;
  TrainConfig config_;
  std::vector<int> train_views_;
  AnchorModel model_;
  AnchorInitStats init_stats_;
  VoxelChoice voxel_choice_;
  size_t max_gaussians_ = 0;
  nlohmann::json run_record_;
  int iteration_ = 0;
  bool host_stale_ = false;
  double extent_ = 1;

  DeviceAnchors anchors_;
  DeviceAnchorGrads grads_;
  DeviceAnchorGrads feature_grads_;  // the mask losses' own pass (mask_geometry off)
  DeviceGaussians gaussians_;
  Expander expander_;
  Renderer renderer_;
  ImageLoss image_loss_;
  MaskLoss mask_loss_;
  bool has_masks_ = false;  // the scene has SAM masks (and a mask weight is > 0)
  Adam adam_;
  std::unique_ptr<AdamGroup> g_offset_, g_scale_, g_quat_, g_opacity_, g_dc_, g_rest_;
  std::unique_ptr<AdamGroup> g_feature_;  // per anchor [A,3]
  DeviceBuffer reg_value_;
  // The view's target image [3,H,W], the loss gradients fed back to the
  // renderer ([3,H,W] rgb; [H,W] constant distortion weight) and the
  // distortion plane read back for the reported loss.
  DeviceBuffer target_dev_, grad_rgb_dev_, grad_dist_dev_;
  DeviceBuffer grad_feat_dev_, grad_alpha_dev_;  // mask-loss gradients [3,H,W], [H,W]
  size_t grad_dist_pixels_ = 0;
  float grad_dist_value_ = 0.f;
  std::vector<float> target_planar_, distortion_host_;
  AnchorGrowth growth_;  // statistics on the device, decisions in growing rounds
  PropagationLoss prop_;
  AnchorGraph graph_;
  bool graph_ready_ = false;
};

// Stage 3 on a saved model: reads MODEL_DIR/model.ag2gs, takes its anchor
// graph (built when missing or stale), clusters the anchors
// (config.cluster), attaches CLIP language features from `views` when the
// scene has them (SemanticsKind::language_features; otherwise the clusters
// alone are stored and `language` is false), and replaces model.ag2gs
// atomically with the graph, clusters and language features added (earlier
// stage-3 entries are overwritten). Throws std::runtime_error naming the file
// when the model is missing or broken.
struct Stage3Summary {
  int clusters = 0;
  size_t components = 0, skipped_anchors = 0, anchors = 0;
  bool language = false;  // the scene had CLIP features
  int with_language = 0;  // clusters with a language feature
  double cluster_ms = 0, total_ms = 0;
  LanguageStats stats;
};
Stage3Summary run_stage3_on_model(Runtime& rt, Scene& scene, const std::string& model_dir,
                                  const std::vector<int>& views, const Stage3Config& config);

// Creates `dir` if needed and checks that a file can be written in it;
// throws std::runtime_error naming the directory otherwise. The trainer's
// caller runs this before training so a long run cannot fail at the end.
void check_model_dir_writable(const std::string& dir);

// The leaves ("a.b.c") where two JSON objects differ, as "key (a vs b)".
std::vector<std::string> config_differences(const nlohmann::json& a, const nlohmann::json& b);

// A JSON document written atomically (host/atomic_file.h).
void write_json_atomic(const std::string& path, const nlohmann::json& doc);

// The camera of an image downscaled by an integer factor: width / factor
// (rounded down, at least 1) and every intrinsic divided by the factor.
Camera downscaled_camera(const Camera& cam, int factor);
// That image's pixels, each the mean of its factor x factor block of `img`,
// written planar [3, H, W] to `out` (room for 3 x the small image's pixels).
void box_downscale_planar(const Image& img, int factor, float* out);

}  // namespace ag2gs
