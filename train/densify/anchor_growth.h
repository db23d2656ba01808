// Anchor growing and pruning (docs/design.md section 3): statistics of
// every child Gaussian collected on the device after each backward pass
// (kernels/anchor_growth.cl), and the decision step on the host model that adds
// finer anchors where children ask for detail and drops anchors that do not
// contribute.
//
// Statistics, per child g (row g = a * K + i, the renderer's row):
//   grad_sum[g]  sum over the views where g was visible (radii > 0) of
//                |(gx * sx, gy * sy)|, (gx, gy) = dL/d(u, v) in pixels (the
//                renderer's means2d gradient, u = fx x/z + cx); sx = W/2,
//                sy = H/2 with ndc = true: 3DGS's NDC units, in which the
//                official threshold 1.5e-4 is given (pixel = ((ndc+1)W-1)/2,
//                so dL/dndc = dL/dpixel * W/2). ndc = false: sx = sy = 1.
//   count[g]     views where g was visible since the last decision.
//   last_seen[g] the accumulation step (1, 2, ...) of g's last visible view;
//                a new row starts at the step it was created.
// The kernel sums each child's own entries in order, without atomics: the
// statistics and every decision are bit-reproducible.
//
// Decision (AnchorGrowth::step), on the host model:
//  1. Grow. A child with count >= max(min_observations, ceil(min_seen_fraction
//     * steps since the last decision)) and mean gradient grad_sum / count >
//     grad_threshold * layer_factor^layer(anchor), whose anchor is not on the
//     finest layer, asks for an anchor of layer + 1 at the voxel holding its
//     mean (pos + offset * l, from the model's host values); with same_layer,
//     a growing child (any layer) whose mean lies outside its anchor's own
//     voxel also asks for an anchor of its layer at that voxel. Requests are
//     sorted by (voxel key, child row); the first request of a voxel wins
//     (its child is the parent: the new children copy its SH, opacity and
//     rotation, AnchorModel::add_anchor), taken voxels are skipped. New
//     anchors are appended in voxel-key order.
//  2. Prune, among the anchors that existed before this step (new anchors are
//     never pruned in the step that made them):
//     - mean over its K children of sigmoid(opacity_logit) < prune_opacity
//       (opacity is a per-child parameter here, not view-dependent as in
//       Scaffold-GS's MLP, so the model's current value is the mean);
//     - unseen: none of its children visible in the last W accumulation
//       steps, W = max(unseen_window, steps since the last decision). Set
//       unseen_window to about two epochs of views (2 x training views):
//       with shuffled views, a window of 100 steps would drop anchors that
//       only a few of many views see. No step since the last decision: no
//       unseen pruning.
//  3. Reset grad_sum and count to zero; last_seen follows the rows.
//
// How the trainer calls it (iterations numbered from 1):
//
//   AnchorGrowth growth(rt, growth_config.scale_to(config.iterations));
//   growth.reset(model.gaussians());
//   for (int it = 1; it <= iterations; ++it) {
//     ... expander.forward, renderer.forward, loss, renderer.backward ...
//     RenderOutput out = renderer.download_output();   // for out.radii
//     if (growth.collecting(it))
//       growth.accumulate(*renderer.device_grads().means2d, out.radii, cam.width, cam.height);
//     ... expander.backward, Adam steps ...
//     if (growth.due(it)) {
//       anchors.download(model);                        // host values current
//       const GrowthResult r = growth.step(model, seed);
//       if (r.changed()) {
//         anchors.upload(model);
//         for (AdamGroup* g : per_child_groups) g->gather(r.child_rows);
//         for (AdamGroup* g : per_anchor_groups) g->gather(r.anchor_rows);  // feature
//         // ... and any other per-row state the trainer keeps
//       }
//     }
//   }
//
// Skip accumulate() on iterations whose step was skipped (non-finite
// gradients). The device-buffer overload of accumulate() takes radii already
// on the device (e.g. from a renderer accessor), avoiding the upload.
// After an opacity reset (3DGS sets every opacity near 0.01), turn the
// opacity prune off for a while (set_config with prune_opacity = 0): the
// mean opacity says nothing until training has restored it.
//
// The stage-1 Trainer (train/trainer.h) calls it as above;
// TrainConfig::growth_config() maps grow_from / grow_until / grow_every /
// grow_threshold / grow_min_seen / prune_opacity / prune_unseen_window onto
// start / stop / every / grad_threshold / min_seen_fraction / prune_opacity /
// unseen_window (layer_factor 2, the schedule as given, not rescaled).
// The gather maps are std::vector<int>, the type AdamGroup::gather takes.
#pragma once

#include <cstddef>
#include <cstdint>
#include <vector>

#include "host/device/cl_runtime.h"
#include "train/anchors/anchor_model.h"

namespace ag2gs {

// 3DGS's split divides a Gaussian's scale by 1.6 (0.8 x 2).
inline constexpr double kSplitShrink = 1.6;

struct GrowthConfig {
  float grad_threshold = 1.5e-4f;  // mean gradient norm (NDC units when ndc) to grow, layer 0
  float layer_factor = 2.f;        // the threshold on layer L is grad_threshold * layer_factor^L
  int start = 500;                 // first decision iteration
  int stop = 20000;                // last decision iteration
  int every = 100;                 // decisions at iterations start <= it <= stop with it % every == 0
  int min_observations = 1;        // a child grows only when visible at least this often ...
  float min_seen_fraction = 0.4f;  // ... and in at least this fraction of the steps since the
                                   // last decision (Scaffold-GS: 40 of 100)
  float prune_opacity = 0.01f;     // prune anchors whose children's mean opacity is below; 0 = off
  bool prune_unseen = true;        // prune anchors none of whose children was seen in the window
  int unseen_window = 0;           // accumulation steps; max(this, steps since last decision)
  bool ndc = true;                 // gradients in NDC units (x W/2, H/2) rather than pixels
  // Also grow sideways: a growing child whose mean left its anchor's voxel
  // asks for an anchor of the same layer at the voxel holding its mean (any
  // layer, the finest too). Lets the model spread into regions without SfM
  // points (textureless walls) instead of only refining where points were.
  bool same_layer = false;
  // Children of a kept anchor whose opacity is below this are recycled: each
  // becomes a copy of the anchor's most opaque child, moved by a little
  // jitter, and the two share that child's opacity (1 - sqrt(1 - o) each, so
  // the pair covers as much as the one did); fresh optimiser moments. A
  // transparent child costs as much to render as an opaque one; this puts it
  // where its anchor has something to show. 0 = off.
  float recycle_opacity = 0.f;
  // Split growth, 3DGS's split carried over to anchors; 0 = off (the
  // published rule). A growing child whose standard deviation along one of
  // its two longest axes spans at least split_voxels voxels of the layer it
  // grows into is split: it also asks at its mean +- one standard deviation
  // along each such axis, and the anchors it wins give their children its
  // scale / kSplitShrink instead of init_scale (other children grow as
  // published). Without it a large child (a wall or a far background
  // smeared by one Gaussian) asks for one fine anchor at its mean, once, and
  // the new children start a pixel wide in the middle of it
  // (docs/benchmarks.md, "Cluttered rooms: split growth").
  float split_voxels = 0.f;
  // Budgets. A round adds at most max(min_round_anchors, ceil(round_growth *
  // anchors before it)) anchors (0 = no per-round limit) and never takes the
  // model past max_gaussians children (0 = no limit). When more voxels ask,
  // the ones whose child asks hardest (mean gradient / its layer's
  // threshold, ties in voxel-key order) win: the threshold adapts to what
  // the round can afford instead of letting growth run away.
  float round_growth = 0.f;
  int min_round_anchors = 64;
  size_t max_gaussians = 0;

  // Throws std::invalid_argument naming the first field out of range.
  void validate() const;
  // The schedule for a run of `iterations` when this one is meant for
  // `reference` iterations (the official 30k): start, stop and every scale
  // by iterations / reference (rounded; every >= min_every so each round
  // still sees enough views, start >= every), stop is clamped to
  // iterations. Longer runs keep the schedule (stop clamped only).
  GrowthConfig scale_to(int iterations, int reference = 30000, int min_every = 10) const;
  // Whether iteration `it` (1-based) is a decision iteration.
  bool due(int it) const;
  // Whether iteration `it` should accumulate statistics: from one round
  // before `start` through `stop`.
  bool collecting(int it) const;
};

// What one decision did.
struct GrowthResult {
  int added = 0;           // anchors grown
  int pruned = 0;          // anchors removed (pruned_opacity + pruned_unseen)
  int pruned_opacity = 0;  // ... for low mean opacity
  int pruned_unseen = 0;   // ... for not being seen in the window (and not low opacity)
  int recycled = 0;        // transparent children made copies of an opaque sibling
  int requests = 0;        // children above the threshold asking for a finer anchor
  int over_budget = 0;     // free voxels asked for but left out by the budgets
  size_t anchors_before = 0, anchors_after = 0;
  size_t gaussians_before = 0, gaussians_after = 0;
  // Gather maps for AdamGroup::gather and any per-row state: new row r comes
  // from old row anchor_rows[r] ([anchors_after]) / child_rows[r]
  // ([gaussians_after]); -1 marks a new row (zero moments). Identity when
  // nothing changed.
  std::vector<int> anchor_rows;
  std::vector<int> child_rows;

  bool changed() const { return added > 0 || pruned > 0 || recycled > 0; }
};

// Host copy of the statistics (tests, logs).
struct GrowthStatsHost {
  int steps = 0;                   // accumulations since the last decision
  int step = 0;                    // accumulations since reset() (last_seen's clock)
  std::vector<float> grad_sum;     // [N]
  std::vector<int32_t> count;      // [N]
  std::vector<int32_t> last_seen;  // [N]
};

// Whether the mean over an anchor's children of sigmoid(opacity_logit) is
// below `threshold`: the opacity rule of the growing rounds' pruning and of
// the trainer's final prune.
bool mean_opacity_below(const AnchorModel& model, size_t anchor, double threshold);

class AnchorGrowth {
 public:
  AnchorGrowth(Runtime& rt, const GrowthConfig& config);  // validates config

  const GrowthConfig& config() const { return config_; }
  void set_config(const GrowthConfig& config);  // validates; statistics are kept
  bool due(int it) const { return config_.due(it); }
  bool collecting(int it) const { return config_.collecting(it); }

  // Sizes the statistics for `gaussians` children, all zero, last_seen =
  // the current step (every row counts as just seen). Call once the model
  // exists, and after any add/remove not made by step().
  void reset(size_t gaussians);
  size_t gaussians() const { return n_; }

  // Adds one view's statistics. v_means2d: [N,2] pixel gradients on the
  // device (Renderer::device_grads().means2d after backward()); radii: [N]
  // ints, > 0 = visible; width/height of that view's image. N must be
  // gaussians() (std::invalid_argument otherwise).
  void accumulate(const DeviceBuffer& v_means2d, const DeviceBuffer& radii, int width, int height);
  // The same with the radii on the host (RenderOutput::radii), uploaded here.
  void accumulate(const DeviceBuffer& v_means2d, const std::vector<int>& radii, int width, int height);

  // The decision (header comment): grows and prunes `model` (its host values
  // must be current), resets the statistics for the new rows. `seed` keys
  // the new children's random offsets (AnchorModel::add_anchor). Throws
  // std::invalid_argument when model.gaussians() != gaussians().
  GrowthResult step(AnchorModel& model, uint64_t seed);

  GrowthStatsHost download();
  // The inverse of download() (resuming from a checkpoint): sizes the
  // statistics for stats.grad_sum.size() children and sets every array and
  // both step counters. Throws std::invalid_argument when the arrays differ
  // in length or a counter is negative.
  void restore(const GrowthStatsHost& stats);

 private:
  // How many new anchors a round may add to a model of `anchors` anchors and
  // `gaussians` children (GrowthConfig's budgets).
  size_t growth_allowance(size_t anchors, size_t gaussians, size_t children) const;
  // GrowthConfig::recycle_opacity on the anchors kept by this step; marks the
  // recycled rows -1 in r.child_rows. Returns how many.
  int recycle(AnchorModel& model, GrowthResult& r, uint64_t seed) const;

  Runtime& rt_;
  GrowthConfig config_;
  size_t n_ = 0;
  int step_ = 0;   // accumulations since reset()
  int steps_ = 0;  // accumulations since the last decision
  DeviceBuffer grad_sum_, count_, last_seen_, radii_upload_;
};

}  // namespace ag2gs
