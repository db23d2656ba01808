// Scoring stages 2 and 3 against exact ground truth: which object
// each anchor belongs to, how well the clusters match the objects (purity and
// adjusted Rand index), and whether each object's cluster carries the right
// category's CLIP feature.
//
// Ground truth per anchor comes from the per-pixel object ids of a synthetic
// scene (gt/<stem>.png: 0 = background, 1..K = objects, see ag2gs synth):
// the anchor's centre is projected into every given view and votes for the
// id under it when it is visible there, i.e. when its camera depth lies
// within depth_tolerance voxel edges of the model's rendered mean depth at
// that pixel. The most voted id wins (ties: the smaller id); an anchor that no
// view sees is unknown (-1).
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "host/device/cl_runtime.h"
#include "host/scene/scene.h"
#include "train/anchors/anchor_model.h"

namespace ag2gs {

struct AnchorTruthOptions {
  double depth_tolerance = 1.5;  // in units of the anchor's voxel edge
  float min_alpha = 0.5f;        // pixels with less rendered alpha have no depth
};

// [A] object id per anchor (0 background, 1..K objects, -1 unknown). Throws
// std::runtime_error naming the gt file when one is missing or unreadable.
std::vector<int32_t> anchor_ground_truth(Runtime& rt, const AnchorModel& model, Scene& scene,
                                         const std::vector<int>& views, const AnchorTruthOptions& options = {});

// gt/<stem>.png of a view at the view's camera size (nearest sampling).
std::vector<int32_t> read_gt_ids(const Scene& scene, int view);

struct ClusterQuality {
  size_t object_anchors = 0;     // anchors with truth >= 1 (the ARI's population)
  size_t clustered_anchors = 0;  // anchors with truth >= 0 and a cluster >= 0 (purity's population)
  double purity = 0;             // sum over clusters of its largest truth class / clustered_anchors
  double ari = 0;                // adjusted Rand index over object anchors; unclustered anchors are singletons
};

// truth: [A] as anchor_ground_truth; clusters: [A] cluster id or -1.
ClusterQuality cluster_quality(const std::vector<int32_t>& truth, const std::vector<int32_t>& clusters);

// Adjusted Rand index of two labelings of the same items (Hubert and Arabie):
// 1 for identical partitions, ~0 for independent ones. Labels are any ints.
// Two items' pair counts are exact (64-bit). n < 2 gives 1.
double adjusted_rand_index(const std::vector<int32_t>& a, const std::vector<int32_t>& b);

// Category check per GT object: the object's cluster is the one holding most of
// its anchors; its language feature is compared (cosine) with every vocabulary
// entry; correct when the best entry is the object's category.
struct ObjectCategoryResult {
  int object = 0;              // GT id
  std::string category;        // from synth.json
  int anchors = 0;             // anchors whose truth is this object
  int cluster = -1;            // the object's cluster (-1: none of its anchors is clustered)
  double cluster_share = 0;    // fraction of the object's anchors in that cluster
  std::string predicted;       // best vocabulary entry ("" without a language feature)
  double cosine_true = 0;      // cosine to the object's own category
  double cosine_best = 0;      // cosine to the predicted one
  bool correct = false;
};

// objects: (id, category) from the scene's synth.json (read_synth_objects).
// language: [C, D] per-cluster features (zero rows = none); vocabulary: name ->
// [D] vector.
std::vector<ObjectCategoryResult> object_categories(
    const std::vector<int32_t>& truth, const std::vector<int32_t>& clusters,
    const std::vector<std::pair<int, std::string>>& objects, const std::vector<float>& language, int dim,
    const std::vector<std::pair<std::string, std::vector<float>>>& vocabulary);

// (id, category) of every object in SCENE/synth.json; throws naming the file.
std::vector<std::pair<int, std::string>> read_synth_objects(const std::string& scene_dir);

}  // namespace ag2gs
