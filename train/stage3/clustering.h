// Stage 3, part 1 (docs/design.md section 7): anchors -> object instances by
// union-find over the anchor-graph edges whose semantic features are close.
//
// The graph comes in as plain CSR arrays (AnchorGraphView), so any CSR of
// anchor ids plugs in: row a lists the neighbours of anchor a, and every edge
// carries one value, the feature distance d_ij = |f_i - f_j|_2 or the
// bilateral weight w_ij = exp(-d_ij^2 / (2 tau^2)) (say which in
// ClusterConfig::edge_value). An edge joins its anchors when
//   distance: d_ij < max_distance          (official: 0.01)
//   weight:   w_ij > min_weight
// The two are the same test when min_weight = exp(-max_distance^2 / (2 tau^2))
// (0.01 and tau = 0.05: w > 0.98020), see weight_threshold_for_distance().
// Rows need not be sorted, and an edge may be listed once or in both rows:
// components do not depend on either. Self-loops are ignored.
//
// Output is deterministic and independent of edge order: clusters are
// numbered 0, 1, ... in increasing order of their smallest anchor id, and the
// anchors of clusters with fewer than min_cluster_size anchors get -1
// (official: clusters of 4 or fewer anchors are skipped, min_cluster_size 5).
#pragma once

#include <cstddef>
#include <cstdint>
#include <vector>

#include "host/io/model_io.h"

namespace ag2gs {

// A CSR graph over anchor ids, borrowed (nothing is copied). The stage-2
// AnchorGraph's arrays plug in as they are: {graph.anchors(),
// graph.row_offsets().data(), graph.neighbours().data(), values.data()}.
struct AnchorGraphView {
  size_t anchors = 0;                    // A
  const int32_t* row_offsets = nullptr;  // [A+1] edges of anchor a: [row_offsets[a], row_offsets[a+1])
  const int32_t* neighbours = nullptr;   // [E] anchor ids in [0, A)
  const float* edge_values = nullptr;    // [E] distance or weight of each edge (ClusterConfig::edge_value)

  size_t edges() const { return anchors == 0 ? 0 : static_cast<size_t>(row_offsets[anchors]); }
  // Throws std::invalid_argument naming the first problem: null arrays,
  // offsets not starting at 0 or decreasing, a neighbour out of range, a
  // non-finite edge value.
  void validate() const;
};

enum class EdgeValue { feature_distance, bilateral_weight };

struct ClusterConfig {
  EdgeValue edge_value = EdgeValue::feature_distance;
  float max_distance = 0.01f;  // feature_distance: join when d_ij < max_distance
  float min_weight = 0.98f;    // bilateral_weight: join when w_ij > min_weight
  int min_cluster_size = 5;    // smaller clusters are skipped (anchors get -1); >= 1

  // Throws std::invalid_argument naming the field out of range.
  void validate() const;
  bool joins(float value) const {
    return edge_value == EdgeValue::feature_distance ? value < max_distance : value > min_weight;
  }
};

// exp(-d^2 / (2 tau^2)): the weight threshold equivalent to a distance threshold.
double weight_threshold_for_distance(double max_distance, double tau);

struct Clustering {
  std::vector<int32_t> anchor_cluster;  // [A] cluster id, -1 = in a skipped cluster
  std::vector<int32_t> cluster_size;    // [C] anchors per kept cluster
  size_t components = 0;                // connected components before skipping (C + skipped)
  size_t skipped_anchors = 0;           // anchors with -1

  int clusters() const { return static_cast<int>(cluster_size.size()); }
};

// Union-find with union by size and path halving: O(E alpha(A)).
Clustering cluster_anchors(const AnchorGraphView& graph, const ClusterConfig& config);

// |f_i - f_j|_2 for every edge of the graph (its edge_values are not read):
// the distances cluster_anchors tests. features: [A,3] (AnchorModel::feature()).
std::vector<float> edge_feature_distances(const AnchorGraphView& graph, const std::vector<float>& features);

// Archive entries: "clusters/anchor_cluster" i32 [A], "clusters/size" i32 [C],
// meta["clusters"] = {count, components, skipped_anchors, edge_value,
// max_distance, min_weight, min_cluster_size}. Other entries are left alone.
void clustering_to_archive(ModelArchive& archive, const Clustering& clustering, const ClusterConfig& config);
// Reads and validates what clustering_to_archive wrote for a model of
// `anchors` anchors (ids in [-1, C), sizes matching the ids). Throws
// std::runtime_error naming the archive and the entry at fault; a model
// without clusters says to run stage 3.
Clustering clustering_from_archive(const ModelArchive& archive, size_t anchors);

}  // namespace ag2gs
