// Stage 3, part 3 (docs/design.md section 7): score every cluster's instance map
// against the SAM masks of each view and attach CLIP features to clusters.
//
// Per view (InstanceMap ids, rendered feature F [3,H,W] and alpha [H,W], the
// view's masks): G(p) = F(p) / alpha(p) where alpha(p) >= kMaskAlphaMin and
// the pixel is "featureless" otherwise (as the mask loss sees F, host/losses/mask_loss.h;
// with normalise_by_alpha = false, G = F and every pixel has a feature). Then
// for every (cluster c, mask M) pair sharing at least one pixel:
//   IoU      = |I_c ∩ M| / |I_c ∪ M|         (I_c = pixels with id c; a pixel in
//                                              several SAM layers with M counts once)
//   Gbar_c   = mean of G over I_c's pixels with a feature
//   Gbar_M   = mean of G over M's pixels with a feature
//   S        = IoU * (1 - |Gbar_c - Gbar_M|_1)
// Choice of Gbar_c: the mean rendered feature over the cluster's instance
// pixels in the same view, not the mean anchor feature, so both sides of the
// L1 distance are the same quantity measured the same way (the rendered
// feature is a blend of several anchors and of the alpha normalisation; the
// anchor mean is not what the mask mean is made of). When either side has no
// pixel with a feature, the pair gets S = 0 (no match).
// All pairs come from one pass over the pixels that builds the sparse
// (cluster, mask) intersection counts and the per-cluster and per-mask sums,
// never a scan per pair.
//
// Over all views, cluster c gets
//   L_c = normalise( sum_k e^{s S_k} clip_k / sum_k e^{s S_k} )
// over its matches k with S_k > min_score (s = softmax_scale): the
// softmax(s S)-weighted mean of the matched masks' CLIP features, L2
// normalised. Clusters without a match get a zero row and matches 0.
// Sums run in double in a fixed order (views as given, pairs by (cluster,
// mask)): the result does not depend on threads.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "host/device/cl_runtime.h"
#include "host/io/model_io.h"
#include "host/scene/scene.h"
#include "train/anchors/anchor_model.h"
#include "train/stage3/clustering.h"
#include "train/stage3/instance_map.h"

namespace ag2gs {

struct LanguageConfig {
  float min_score = 0.3f;          // matches need S > min_score (official 0.3)
  float softmax_scale = 10.f;      // weights softmax(softmax_scale * S) (official 10)
  bool normalise_by_alpha = true;  // G = F / alpha, pixels with alpha < kMaskAlphaMin featureless
  float instance_fraction = 0.5f;  // InstanceMapper min_fraction
  // Throws std::invalid_argument naming the field out of range.
  void validate() const;
};

// One overlapping (cluster, mask) pair of a view.
struct MaskMatch {
  int32_t cluster = -1;
  int32_t mask = -1;         // index into the view's masks
  int64_t intersection = 0;  // pixels
  double iou = 0;
  double feature_l1 = 0;  // |Gbar_c - Gbar_M|_1, NaN when a side has no feature
  double score = 0;       // S (0 when feature_l1 is NaN)
};

// Every overlapping pair of one view, sorted by (cluster, mask). ids [H,W]
// with values in [-1, clusters); feature_chw [3,H,W]; alpha [H,W] (may be
// empty when !config.normalise_by_alpha); masks at the same size. Throws
// std::invalid_argument on size mismatches, naming the arrays.
std::vector<MaskMatch> score_view(const std::vector<int32_t>& ids, int clusters, const std::vector<float>& feature_chw,
                                  const std::vector<float>& alpha, const ViewMasks& masks,
                                  const LanguageConfig& config);

struct LanguageFeatures {
  int dim = 0;                   // D (CLIP feature size)
  std::vector<float> features;   // [C,D] L2-normalised, zero rows without a match
  std::vector<int32_t> matches;  // [C] matches that contributed
  int clusters() const { return static_cast<int>(matches.size()); }
  int with_language() const;  // clusters with matches > 0
};

// The softmax-weighted attachment across views.
class LanguageAccumulator {
 public:
  LanguageAccumulator(int clusters, int dim, const LanguageConfig& config);
  // Adds the matches of one view (score_view's output) whose S > min_score;
  // masks.features must be [count, dim].
  void add_view(const std::vector<MaskMatch>& matches, const ViewMasks& masks);
  LanguageFeatures finish() const;

 private:
  int clusters_, dim_;
  LanguageConfig config_;
  std::vector<double> weight_sum_;  // [C]
  std::vector<double> acc_;         // [C,D]
  std::vector<int32_t> matches_;    // [C]
};

// What attach_language did and how long it took (wall clock, ms).
struct LanguageStats {
  int views = 0;       // views scored (views without masks are skipped)
  size_t pairs = 0;    // overlapping (cluster, mask) pairs, all views
  size_t matches = 0;  // pairs with S > min_score
  double expand_ms = 0, render_ms = 0, instance_ms = 0, score_ms = 0, total_ms = 0;
};

// The whole of part 2 + 3 on a trained model: expands the model on the device
// (SH degree 0: colour is not needed), and for each view renders it, computes
// the instance map, downloads ids, feature and alpha, scores against the
// view's masks and accumulates. Views are scene view indices (e.g.
// scene.train_views()). Throws std::runtime_error when the scene has no CLIP
// features (masks/ PNGs only, or no semantics) saying what the scene needs,
// and std::invalid_argument when clustering and model disagree in size.
LanguageFeatures attach_language(Runtime& rt, const AnchorModel& model, const Clustering& clustering, Scene& scene,
                                 const std::vector<int>& views, const LanguageConfig& config,
                                 LanguageStats* stats = nullptr);

// Archive entries: "clusters/language" f32 [C,D], "clusters/language_matches"
// i32 [C], meta["language"] = {dim, clusters_with_language, min_score,
// softmax_scale, normalise_by_alpha, instance_fraction, cluster_feature}.
void language_to_archive(ModelArchive& archive, const LanguageFeatures& language, const LanguageConfig& config);
// Reads what language_to_archive wrote for `clusters` clusters; throws
// std::runtime_error naming the archive and the entry at fault.
LanguageFeatures language_from_archive(const ModelArchive& archive, int clusters);

// Stage 3 in one call: cluster the anchors over `graph` (its edge_values are
// ignored: recomputed from the model's current features, as distances or as
// bilateral weights with tau, whichever cluster.edge_value says),
// then attach language features. Store with clustering_to_archive and
// language_to_archive next to AnchorModel::to_archive.
struct Stage3Config {
  ClusterConfig cluster;
  float tau = 0.05f;  // bilateral weight scale when cluster.edge_value == bilateral_weight
  LanguageConfig language;
};
struct Stage3Result {
  Clustering clustering;
  LanguageFeatures language;
  LanguageStats stats;
  double cluster_ms = 0;
};
Stage3Result run_stage3(Runtime& rt, const AnchorModel& model, const AnchorGraphView& graph, Scene& scene,
                        const std::vector<int>& views, const Stage3Config& config);

}  // namespace ag2gs
