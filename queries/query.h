// Click and text queries on a trained anchor model (docs/design.md section 8).
//
// Both queries end in the same region growing over the query graph, the
// anchor graph rebuilt with twice the voxel neighbourhood
// (AnchorGraph::build(model, 2)): starting from the seed anchors, neighbour j
// of a selected anchor i joins when the bilateral weight
//
//   w_ij = exp(-|f_i - f_j|^2 / (2 tau^2)) > min_weight        (0.9, tau 0.05)
//
// which is the feature-distance test |f_i - f_j| < tau sqrt(-2 ln min_weight)
// (0.0230 for the defaults; the official code's distance 0.10 is
// min_weight = exp(-2) = 0.135 at tau 0.05, see equivalent_distance()).
// Growing is a breadth-first search from the seeds in ascending id order,
// each row visited in its CSR (ascending) order; since the graph and the
// weights are symmetric the selection is the union of the seeds' components
// in the subgraph of passing edges, whatever the order, and the result is
// returned sorted.
//
// Click: render the model at the clicked view, read alpha at the pixel;
// group the anchors blended there by feature (the growing rule: bilateral
// weight > min_weight with the group's first anchor) and take the weighted
// mean depth z of the group holding the most blending weight and the
// feature of its heaviest anchor (click_dominant; otherwise the ray's mean
// depth and F / alpha),
// unproject the pixel centre (x + 0.5, y + 0.5) to
// X_cam = ((u - cx) z / fx, (v - cy) z / fy, z) and to the world; of the
// click_candidates anchor centres nearest to it (k-d tree), the seed is the
// one whose feature is closest to that feature (ties to the nearer): at the
// touching face of two objects the nearest centre may belong to the other
// object, the pixel's own feature says which one was clicked.
// A pixel with alpha < min_click_alpha is background: an error naming the
// pixel and its alpha.
//
// Text: cosine similarity between the embedding and each cluster's language
// feature (clusters without one are skipped); the clusters scoring within
// text_margin of the best are the seeds' clusters, all their anchors seeds.
//
// Without growing (QueryConfig::grow false, an ablation): the selection is
// similar_anchors() of the seeds' features instead, for both queries.
//
// Support-plane click (QueryEngine::set_support, for a model whose features
// were never trained: a capture without SAM masks gives every anchor nearly
// the same feature, and feature growing spreads over the whole scene): the
// depth is the ray's median (where the accumulated blending weight passes
// half the pixel's alpha), the seed the anchor nearest the unprojected point,
// and the selection support_grow()'s: the anchors standing on the plane and
// joined to the seed (host/scene/scene_up.h finds the plane and up).
//
// Masks: the model rendered with feature (1, 0, 0) on the selected anchors'
// Gaussians and 0 elsewhere, normal occlusion: the first feature channel is
// the selection's blending weight W(p) = sum of w_i over selected Gaussians,
// and mask(p) = W(p) > mask_threshold (0.5), the same test the stage-3
// instance maps use.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <memory>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <vector>

#include "host/core/gaussians.h"
#include "host/device/cl_runtime.h"
#include "host/render/renderer.h"
#include "host/scene/scene_up.h"
#include "train/anchors/anchor_model.h"
#include "train/graph/anchor_graph.h"
#include "train/stage3/clustering.h"
#include "train/stage3/language.h"

namespace ag2gs {

struct QueryConfig {
  int graph_cell_scale = 2;      // query graph neighbourhood, in top-layer voxels
  float tau = 0.05f;             // bilateral weight scale
  float min_weight = 0.9f;       // grow along edges with w_ij > min_weight, in (0, 1)
  float text_margin = 0.1f;      // text seeds: clusters with score >= best - text_margin
  // A cluster is a phrase's only if its cosine is at least this; -1 (the
  // default): no floor, the vocabulary's other phrases decide (measured on
  // generated scenes, docs/benchmarks.md "Phrases for what is not there").
  // A floor answers "none" for a phrase alone in its vocabulary.
  float text_threshold = -1.f;
  float min_click_alpha = 0.5f;  // clicks on pixels with less alpha are background
  float mask_threshold = 0.5f;   // mask(p) = selection weight > mask_threshold
  // Click seed: of the click_candidates anchors nearest the unprojected
  // point, the one whose feature is closest to the rendered feature at the
  // pixel (F / alpha); 1 = the nearest anchor alone.
  int click_candidates = 8;
  // true: the click's depth and feature come from the anchors blended at the
  // pixel, grouped by feature (tau, min_weight), the group with the most
  // blending weight (what the pixel shows); false: the ray's mean depth and
  // F / alpha (blends of a thin object and what lies behind it).
  bool click_dominant = true;
  // With click_dominant: > 0 takes the nearest group along the ray holding at
  // least this much of the pixel's blending weight instead of the heaviest
  // group (a thin pole half covering a wall); 0 = the heaviest. Measured in
  // the README (query section).
  float click_front_weight = 0.3f;
  // false: the ablation without graph region growing. The selection is then
  // every anchor whose feature lies within equivalent_distance() of a seed
  // feature (click: the seed anchor's; text: each seed cluster's mean),
  // anywhere in the scene: plain feature similarity, no connectivity.
  bool grow = true;
  // Throws std::invalid_argument naming the field out of range.
  void validate() const;
  // Every field by name (`query --print-config`, selection.json's thresholds).
  nlohmann::json to_json() const;
  // tau * sqrt(-2 ln min_weight): the feature distance below which an edge passes.
  double equivalent_distance() const;
};

// A 3-d tree over points for nearest-neighbour queries: median splits on the
// widest axis, built once in O(n log n), exact nearest (ties to the lower id).
class PointKdTree {
 public:
  PointKdTree() = default;
  // points: [n,3]; non-finite points are left out.
  explicit PointKdTree(const std::vector<float>& points);
  size_t size() const { return ids_.size(); }
  // The id of the nearest point to p and its squared distance; -1 when empty.
  int nearest(const Eigen::Vector3d& p, double* dist2 = nullptr) const;
  // The k nearest ids, nearest first (ties to the lower id); fewer when the
  // tree holds fewer points.
  std::vector<int> nearest_k(const Eigen::Vector3d& p, int k) const;

 private:
  struct Node {
    int32_t lo = 0, hi = 0;  // range in ids_
    int32_t axis = -1;       // -1 = leaf
    float split = 0;
    int32_t left = -1, right = -1;
  };
  int build(int lo, int hi);
  void search(int node, const Eigen::Vector3d& p, int* best, double* best_d2) const;
  void search_k(int node, const Eigen::Vector3d& p, size_t k, std::vector<std::pair<double, int>>* heap) const;
  std::vector<float> points_;
  std::vector<int32_t> ids_;
  std::vector<Node> nodes_;
};

// Breadth-first region growing (see the file comment). features: [A,3];
// seeds: anchor ids (duplicates allowed). Returns the selected ids, ascending.
// Throws std::invalid_argument for a seed out of range or a graph of another size.
std::vector<int32_t> region_grow(const AnchorGraph& graph, const std::vector<float>& features,
                                 const std::vector<int32_t>& seeds, float tau, float min_weight);

// The ablation's selection: every anchor a with |f_a - s| < max_distance for
// some row s of seed_features [S,3]; ascending ids.
std::vector<int32_t> similar_anchors(const std::vector<float>& features, const std::vector<float>& seed_features,
                                     double max_distance);

// The object a support-plane click selects (see the file comment). An
// anchor's height is the mean height of its children over the plane; it is
// above the plane beyond 2 plane tolerances, in the band within them. Two
// anchors are linked when their centres lie closer than link_factor x the
// larger of their voxel edges (1.75: the 26 neighbours of one layer). The
// selection is the seed's component among the anchors above the plane, plus
// its base: band anchors linked to the component and no further across `up`
// from the component's axis (its mean) than its lowest part (the lowest tenth
// of its height): the 90th percentile of that part's distances. Ascending
// ids; empty when the seed itself is not above the plane.
std::vector<int32_t> support_grow(const AnchorModel& model, const Plane& plane, int32_t seed,
                                  double link_factor = 1.75);

// Cosine similarity of `embedding` [D] to each cluster's language feature;
// NaN for clusters without one (matches 0 or a zero row). Throws
// std::invalid_argument when the dimension differs, saying both.
std::vector<double> text_scores(const LanguageFeatures& language, const std::vector<float>& embedding);

// A click given in pixels of the full-size image (column x, row y) as a
// position in `camera`, the same view at another size: the centre of the
// clicked pixel, scaled. Queries take full-size clicks (click lists, --click).
Eigen::Vector2d full_size_click(const Camera& full, const Camera& camera, double x, double y);

struct ClickResult {
  int pixel_x = 0, pixel_y = 0;
  double alpha = 0, depth = 0;   // at the pixel (depth: of the dominant feature group, else the ray's mean)
  Eigen::Vector3d point = Eigen::Vector3d::Zero();  // unprojected world point
  int seed = -1;                 // seed anchor
  int32_t dominant_anchor = -1;  // heaviest anchor of the feature group holding the most weight at the pixel
  double dominant_weight = 0;    // that group's weight
  std::vector<float> pixel_feature;  // [3] the dominant anchor's feature, else rendered F / alpha
  double seed_distance = 0;      // |point - anchor centre|
  std::vector<int32_t> selected;
  double ms = 0;                 // render + unproject + nearest + grow
};

struct TextResult {
  std::vector<double> scores;          // [C] NaN = cluster without language feature
  double best = 0;                     // the best score of a cluster the phrase wins (of any, when none)
  // With rival phrases: a cluster is the phrase's only if no rival scores
  // higher on it, and its score is at least config.text_threshold; none =
  // no cluster is (the phrase names nothing here), and the selection is
  // empty.
  bool none = false;
  size_t won = 0;                      // clusters the phrase wins against the rivals
  std::vector<int32_t> seed_clusters;  // ascending
  std::vector<int32_t> seeds;          // their anchors, ascending
  std::vector<int32_t> selected;
  double ms = 0;
};

// Everything a query needs, prepared once per model: the query graph, the
// k-d tree over anchor centres and the expanded Gaussians on the device (SH
// degree 0: queries need geometry, not colour); the constructor also renders
// once so that kernel compilation is not part of the first query.
class QueryEngine {
 public:
  QueryEngine(Runtime& rt, const AnchorModel& model, const QueryConfig& config = {});
  // Enables text queries; throws std::invalid_argument when the clustering or
  // language features do not fit the model.
  void set_language(const Clustering& clustering, const LanguageFeatures& language);
  bool has_language() const { return have_language_; }
  // Clicks select by the support plane (see the file comment) from now on.
  void set_support(const Plane& plane) { support_ = plane; }
  const std::optional<Plane>& support() const { return support_; }

  // x, y: pixel coordinates at the camera's size (column, row; the pixel
  // centre is at +0.5). Throws std::invalid_argument for a pixel outside the
  // image and std::runtime_error for background (alpha < min_click_alpha).
  ClickResult click(const Camera& camera, double x, double y);
  // The renderer of the last click or mask (its frame: Renderer::pixel_contributions).
  const Renderer& renderer() const { return renderer_; }
  // Throws std::logic_error without set_language, std::invalid_argument for
  // an embedding of the wrong dimension or when no cluster has a feature.
  // `rivals`: the embeddings of the vocabulary's other phrases. A cluster
  // can seed only if the phrase scores at least as high on it as every
  // rival (the phrase is its best description, as LERF and LangSplat rank a
  // phrase against others); when the phrase wins no cluster the answer is
  // "none" (TextResult::none, empty selection). Without rivals every
  // cluster with a feature can seed.
  TextResult text(const std::vector<float>& embedding, const std::vector<std::vector<float>>& rivals = {});

  // [H,W] 0/1 mask of `selected` (anchor ids) in the camera (see file comment).
  std::vector<uint8_t> mask(const Camera& camera, const std::vector<int32_t>& selected);

  const AnchorModel& model() const { return model_; }
  const AnchorGraph& graph() const { return graph_; }
  const QueryConfig& config() const { return config_; }
  double prepare_ms() const { return prepare_ms_; }

 private:
  Runtime& rt_;
  const AnchorModel& model_;
  QueryConfig config_;
  AnchorGraph graph_;
  PointKdTree tree_;
  GaussianSet gaussians_;
  Renderer renderer_;
  DeviceGaussians device_;
  std::vector<float> selection_features_;  // [N,3] of the last mask upload
  bool features_are_model_ = true;         // the device holds the model's features (not a selection)
  bool have_language_ = false;
  std::optional<Plane> support_;
  Clustering clustering_;
  LanguageFeatures language_;
  double prepare_ms_ = 0;
};

// The Gaussians of the anchors with keep[a] == want (expand_reference of the
// model at sh_degree, rows of those anchors' children in anchor order).
GaussianSet gaussians_of_anchors(const AnchorModel& model, int sh_degree, const std::vector<uint8_t>& in_selection,
                                 bool want);

}  // namespace ag2gs
