// Plain-loop reference of stage 3's clustering (train/stage3/clustering.h):
// connected components by breadth-first search instead of union-find. The
// edges that pass ClusterConfig's test (distance < max_distance or weight >
// min_weight, compared in double) are made symmetric; components are visited
// from the smallest unvisited anchor up and numbered in that order, and those
// smaller than min_cluster_size give their anchors -1. Integer output, no
// rounding.
#pragma once

#include <cstdint>
#include <vector>

#include "train/stage3/clustering.h"

namespace ag2gs::ref {

// [A] cluster id per anchor, -1 in a skipped cluster (Clustering::anchor_cluster).
std::vector<int32_t> clustering_reference(const AnchorGraphView& g, const ClusterConfig& cfg);

}  // namespace ag2gs::ref
