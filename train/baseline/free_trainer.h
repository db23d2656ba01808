// The free-Gaussian baseline: vanilla 3D Gaussian Splatting (no anchors) run
// through the same renderer, image loss and Adam kernels as the anchor
// trainer (train/trainer.h), so that PSNR and Gaussian counts can be put
// side by side.
//
// Initialisation (3DGS): one Gaussian per SfM point, isotropic scale
// log(sqrt(mean squared distance to its 3 nearest other points)), identity
// rotation, opacity 0.1, SH DC from the point colour ((c - 0.5) / C0), higher
// SH zero. The stored parameters are mean, log scale, quaternion, opacity
// logit, SH DC and SH rest, one Adam group each, with 3DGS's learning rates
// (positions 1.6e-4 x extent decaying exponentially to 1.6e-6 x extent over
// the run, extent = the scene's camera radius).
//
// Per iteration on the device: activate (kernels/free_trainer.cl) ->
// render -> 0.8 L1 + 0.2 (1 - SSIM) -> renderer backward -> activation
// backward -> non-finite check (skip the step) -> Adam -> densification
// statistics (NDC gradient norm sum, visible count, largest radius).
//
// Densification rounds every densify_every iterations in [densify_from,
// densify_until] (plan_densification below, on the host with the device's
// current values, as the anchor trainer decides its growing rounds):
// Gaussians whose mean NDC gradient over the views where they were visible
// is >= grad_threshold are cloned (max scale <= percent_dense x extent) or
// split into two samples of themselves (scale / 1.6); then Gaussians with
// opacity < prune_opacity and, once an opacity reset has happened, those
// larger than max_screen_size pixels or max_world_size x extent are removed.
// Every opacity_reset_every iterations (up to densify_until; on a white
// background also at densify_from) the opacities are clamped to at most 0.01
// and their Adam moments zeroed. The Adam state
// follows the rows (kept rows keep theirs, new rows start at zero).
//
// Deterministic: the view order is the anchor trainer's (a counter-based
// hash of (seed, epoch)), the split samples come from a counter-based hash of
// (seed, iteration, index, sample), the kernels use no floating-point atomics
// and the decisions run over the rows in index order.
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <functional>
#include <memory>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "host/core/gaussians.h"
#include "host/device/cl_runtime.h"
#include "host/losses/image_loss.h"
#include "host/optim/adam.h"
#include "host/render/renderer.h"
#include "host/scene/scene.h"
#include "train/param_groups.h"
#include "train/trainer.h"

namespace ag2gs {

struct FreeTrainConfig : GaussianRates {
  int iterations = 30000;
  uint64_t seed = 0;
  int sh_degree = 3;    // highest SH degree
  int sh_interval = 0;  // iterations per SH degree step; 0 = min(1000, iterations / (sh_degree + 1)), at least 1
  float lambda_ssim = kSsimLambda;
  bool white_background = false;
  float init_opacity = 0.1f;

  // Learning rates (3DGS). Positions: init -> final (x extent) exponentially.
  double position_lr_init = 1.6e-4;
  double position_lr_final = 1.6e-6;
  // sh_dc_lr, sh_rest_lr, opacity_lr, scaling_lr, rotation_lr: GaussianRates (host/optim/adam.h).
  AdamSettings adam;

  // Densification (3DGS: 500 .. 15000 of 30000 every 100). Rounds at
  // densify_from <= it <= densify_until with it % densify_every == 0 (the
  // anchor trainer's growing schedule; 3DGS starts one round later, at
  // it > densify_from); statistics collected up to densify_until.
  // densify_every 0 turns it off; densify_until 0 = half the iterations (the
  // official 15k of 30k), scaled with --iters as the anchor trainer's
  // grow_until is (2/3); from and every are not rescaled, as there.
  int densify_from = 500;
  int densify_until = 0;
  int densify_every = 100;
  double grad_threshold = 2e-4;    // mean NDC positional gradient norm
  double percent_dense = 0.01;     // clone when max scale <= this x extent, else split
  double prune_opacity = 0.005;    // remove below this opacity in every round
  int opacity_reset_every = 3000;  // 0 = never
  double max_screen_size = 20;     // pixels; after the first reset (0 = off)
  double max_world_size = 0.1;     // x extent; after the first reset (0 = off)

  void validate() const;  // std::invalid_argument naming the first bad field
  nlohmann::json to_json() const;
  int effective_sh_interval() const;
  int effective_densify_until() const;
  // Whether iteration `it` (1-based) is a densification round / an opacity reset.
  bool densify_due(int it) const;
  bool reset_due(int it) const;
  // Whether a round at `it` also prunes by screen and world size (3DGS:
  // once past the first opacity_reset_every iterations).
  bool prune_big_at(int it) const;
};

// The stored (pre-activation) parameters, row-major, host copy.
struct FreeGaussians {
  std::vector<float> mean;           // [N,3]
  std::vector<float> log_scale;      // [N,3]
  std::vector<float> quat;           // [N,4] w x y z
  std::vector<float> opacity_logit;  // [N]
  std::vector<float> sh_dc;          // [N,3]
  std::vector<float> sh_rest;        // [N,15,3]
  size_t size() const { return opacity_logit.size(); }
  void resize(size_t n);
  // The 3DGS initialisation from points (see the header comment). Points
  // that are not finite are skipped.
  static FreeGaussians from_points(const std::vector<Eigen::Vector3d>& points,
                                   const std::vector<Eigen::Vector3<uint8_t>>& colors, float init_opacity);
  // The set for the PLY writer with PlyValues::stored (opacities are the
  // logits, scales the logs, bit for bit), `sh_degree` coefficients.
  GaussianSet to_stored_set(int sh_degree) const;
};

// Densification statistics, host copy.
struct DensifyStats {
  std::vector<float> grad_sum;      // [N] sum of NDC gradient norms where visible
  std::vector<int32_t> count;       // [N] views where visible
  std::vector<int32_t> max_radius;  // [N] pixels
};

// One round's decisions. New row r of the result comes from old row
// source[r]; kind[r] says how: kept (the row itself), clone (a copy) or split
// (a sample of a split row). Order: kept rows in index order, then clones in
// index order, then two split samples per split row in index order, with the
// pruned ones left out.
enum class RowKind : uint8_t { kept = 0, clone = 1, split = 2 };
struct DensifyPlan {
  std::vector<int> source;
  std::vector<RowKind> kind;
  std::vector<int> split_sample;  // 0 or 1 for split rows, 0 otherwise
  int cloned = 0, split = 0;      // rows cloned / split (each split row -> 2 samples, original removed)
  int pruned = 0;                 // rows removed by the prune (original, clones and samples counted)
  size_t before = 0, after = 0;
  // Adam's gather map: source for kept rows, -1 for new ones.
  std::vector<int> adam_rows() const;
};

// The decisions of 3DGS's densify_and_prune for `g` and `stats` (same N);
// extent = the scene's camera radius; prune_big = also prune by screen and
// world size (FreeTrainConfig::prune_big_at). New rows' opacity and scale are those they will get (clones: the
// source's; split samples: the source's scale / 1.6), new rows' max radius 0.
DensifyPlan plan_densification(const FreeGaussians& g, const DensifyStats& stats, const FreeTrainConfig& config,
                               double extent, bool prune_big);
// Builds the new parameters from a plan: split samples at mean + R(q) (s * z)
// with z ~ N(0, I) from a counter-based hash of (seed, iteration, source row,
// sample), scale / 1.6 (log scale - log 1.6); everything else copied.
FreeGaussians apply_densification(const FreeGaussians& g, const DensifyPlan& plan, uint64_t seed, int iteration);
// The standard normal draw used for split samples (exposed for tests).
std::array<double, 3> split_normal(uint64_t seed, int iteration, int row, int sample);

struct FreeStepStats {
  int iteration = 0;
  int view = -1;
  bool skipped = false;
  uint64_t nonfinite = 0;
  double loss = 0, l1 = 0, ssim = 1, psnr = 0;
  int sh_degree = 0;
  bool densified = false;
  int cloned = 0, split = 0, pruned = 0;
  bool opacity_reset = false;
};

class FreeTrainer {
 public:
  // Throws when the config is invalid or the scene has no points / training views.
  FreeTrainer(Runtime& rt, Scene& scene, const FreeTrainConfig& config);
  ~FreeTrainer();

  // before_rounds, when set, runs after the parameter update and before
  // this iteration's densification and opacity reset (as Trainer::step).
  FreeStepStats step(const std::function<void()>& before_rounds = {});
  EvalStats evaluate(const std::vector<int>& views);
  // MODEL_DIR/point_cloud.ply (standard 3DGS, active SH degree), atomic.
  void save(const std::string& model_dir);

  int iteration() const { return iteration_; }
  int active_sh_degree() const;
  size_t gaussians() const { return n_; }
  double extent() const { return extent_; }
  double position_lr(int it) const;
  // The anchor trainer's view order: a permutation of the training views
  // per epoch from a counter-based hash of (seed, epoch).
  int view_for_iteration(int it) const;
  const FreeTrainConfig& config() const { return config_; }
  // Host copy of the device's current parameters / statistics.
  FreeGaussians download();
  DensifyStats download_stats();
  // Replaces the parameters (same row count keeps the Adam state; another
  // count resets it) and zeroes the statistics. For tests.
  void upload(const FreeGaussians& g);

 private:
  void upload_params(const FreeGaussians& g);
  // Stored parameters -> the renderer's Gaussians (kernels/free_trainer.cl).
  void activate(int sh_degree);
  // The renderer's gradients through the activations (kernels/free_trainer.cl
  // free_activate_bwd) into the stored parameters' gradient buffers.
  void activate_backward(const DeviceGaussianGrads& rg);
  // This view's screen-space gradient norms and radii into the densification
  // statistics (free_densify_accumulate).
  void accumulate_densify_stats(const DeviceGaussianGrads& rg, int width, int height);
  void reset_stats();
  void densify(FreeStepStats& st);
  void reset_opacity();

  Runtime& rt_;
  Scene& scene_;
  FreeTrainConfig config_;
  std::vector<int> train_views_;
  int iteration_ = 0;
  size_t n_ = 0;
  double extent_ = 1;

  DeviceBuffer mean_, log_scale_, quat_, opacity_logit_, sh_dc_, sh_rest_;
  DeviceBuffer v_log_scale_, v_opacity_logit_, v_sh_dc_, v_sh_rest_;
  DeviceBuffer grad_sum_, count_, max_radius_;
  DeviceGaussians gaussians_;
  Renderer renderer_;
  ImageLoss image_loss_;
  Adam adam_;
  // The optimiser groups (train/param_groups.h), in this order.
  enum Group : size_t { kMeans, kScaling, kRotation, kOpacity, kShDc, kShRest };
  std::unique_ptr<ParamGroups> groups_;
  DeviceBuffer target_dev_, grad_rgb_dev_;
  std::vector<float> target_planar_;
};

}  // namespace ag2gs
