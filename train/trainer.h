// Stage-1 training (appearance, docs/design.md sections 2-5 and 11): anchors from
// the scene's SfM points, then per iteration one training view
//
//   expand anchors -> render -> L = L_rgb + w_in L_in + w_d L_d
//   -> renderer backward -> expander backward (+ dL_in/d offset)
//   -> non-finite check (skip the step) -> Adam per parameter group
//
// with L_rgb = (1 - lambda) L1 + lambda (1 - SSIM) (host/losses/image_loss.h),
// L_in = mean over offsets of exp(relu(|o|^2 - 1)) (offsets in voxel units),
// L_d = mean over pixels of the renderer's distortion output.
//
// Growing and pruning (docs/design.md section 3) are AnchorGrowth's
// (train/densify/anchor_growth.h): per child, the screen-space positional gradient
// norm (3DGS's NDC units) is summed on the device over the views where it was
// visible; every grow_every iterations in [grow_from, grow_until] a child seen
// in at least grow_min_seen of the round whose mean exceeds grow_threshold *
// 2^layer asks for an anchor of the next finer layer at the voxel holding its
// mean (one per voxel, in voxel-key order); in the same rounds anchors whose
// children's mean opacity is below prune_opacity, or none of whose children
// was seen in the last prune_unseen_window views, are removed. The optimiser
// state follows the rows (GrowthResult's gather maps).
//
// Mask losses (docs/design.md section 4, host/losses/mask_loss.h): when the scene has
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
// Stage 2 (docs/design.md section 6): after the `iterations` stage-1 steps come
// prop_iters more with the same losses plus w_prop L_prop
// (train/graph/propagation_loss.h) over the anchor graph (train/graph/anchor_graph.h),
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
#include <utility>
#include <vector>

#include "host/device/cl_runtime.h"
#include "host/io/model_io.h"
#include "host/io/model_ply.h"
#include "host/losses/image_loss.h"
#include "host/losses/mask_loss.h"
#include "host/optim/adam.h"
#include "host/render/renderer.h"
#include "host/render/sky.h"
#include "host/scene/scene.h"
#include "train/anchors/anchor_model.h"
#include "train/anchors/expander.h"
#include "train/anchors/voxel_rule.h"
#include "train/checkpoint.h"
#include "train/densify/anchor_growth.h"
#include "train/graph/anchor_graph.h"
#include "train/graph/propagation_loss.h"
#include "train/param_groups.h"
#include "train/stage3/language.h"
#include "train/stage3/stage3.h"
#include "train/train_common.h"
#include "train/train_config.h"

namespace ag2gs {

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
  // How the top-layer voxel was chosen (config.anchors, train/anchors/voxel_rule.h).
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
  // expanded Gaussians, standard 3DGS, with the sky baked in when the model
  // has one, and then point_cloud_objects.ply without it: host/io/model_ply.h),
  // each written atomically. last_ply() says what the last save wrote.
  void save(const std::string& model_dir);
  const ModelPlyReport& last_ply() const { return last_ply_; }
  // What save() writes as model.ag2gs, in memory (the live view's snapshot).
  ModelArchive model_archive();
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
  // The sky's coefficients [K, 3] (empty without a sky; host/render/sky.h).
  std::vector<float> sky() const { return sky_.enabled() ? sky_.download() : std::vector<float>{}; }
  // The fraction of the training pixels that are open (that would teach a
  // sky; 0 when the config says no sky).
  double sky_open_fraction() const { return sky_open_fraction_; }
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
  // The parts of step(), in order: render the view and enqueue every loss
  // and its gradient down to the anchors (returns the image size); the
  // non-finite check and the Adam updates (and growth statistics); the
  // growing round; the opacity reset.
  std::pair<int, int> render_and_losses(StepStats& st, bool compute_offset_loss);
  // The downscale level (a power of two) iteration `it` (0-based) renders
  // at: the coarse-to-fine level, 0 on mask-loss steps and in stage 2.
  int training_level(int it, bool stage2) const;
  void update(StepStats& st, int w, int h);
  void growing_round(StepStats& st);
  // After the last stage-1 iteration (TrainConfig::final_prune_opacity).
  void final_prune(StepStats& st);
  // Once, at TrainConfig::effective_prune_importance_at().
  void importance_prune(StepStats& st);
  // Removes the anchors with keep[a] = 0 from the model, the device arrays,
  // the optimiser's rows and the growth statistics (after the prunes).
  void remove_anchor_rows(const std::vector<uint8_t>& keep);
  void reset_opacities(StepStats& st);
  // The open pixels of every training view (sky_open_, their share and
  // radius), and the sky's start (config.sky_degree >= 0).
  void find_open_pixels();
  double init_sky();
  // Finds the open pixels and decides the sky (config.sky_degree) and the
  // far shell, whose points it appends to the seeding points.
  void choose_background(const VoxelGrid& grid, std::vector<Eigen::Vector3d>& points,
                         std::vector<Eigen::Vector3<uint8_t>>& colors);

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
  Sky sky_;
  ModelPlyReport last_ply_;      // what the last save() wrote
  DeviceBuffer sky_grad_alpha_;  // the sky's alpha gradient when no mask loss wrote one
  // Per scene view (training views only): 1 where a pixel is open
  // (open_sky_pixels), the weights of the sky's gradient.
  std::vector<std::vector<uint8_t>> sky_open_;
  std::vector<float> sky_weight_host_;
  DeviceBuffer sky_weight_dev_;
  double sky_open_fraction_ = 0;
  int sky_radius_ = 0;
  bool has_masks_ = false;  // the scene has SAM masks (and a mask weight is > 0)
  Adam adam_;
  // The optimiser groups, in the order of group_specs().
  // kSky exists only with a sky (config.sky_degree >= 0).
  enum Group : size_t { kOffset, kScaling, kRotation, kOpacity, kShDc, kShRest, kFeature, kSky };
  std::vector<ParamGroupSpec> group_specs() const;
  std::unique_ptr<ParamGroups> groups_;
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

}  // namespace ag2gs
