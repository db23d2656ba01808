// Plain-loop reference of region growing (queries/query.h, region_grow),
// written as a fixed point instead of the library's breadth-first queue:
// starting from the seed, add j whenever an edge (i, j) of the anchor graph
// leaves a selected i with bilateral weight
//   w_ij = exp(-|f_i - f_j|^2 / (2 tau^2)) > min_weight
// (the squared distance and the weight in double), and sweep over all
// anchors again until nothing changes.
#pragma once

#include <cstdint>
#include <vector>

#include "train/graph/anchor_graph.h"

namespace ag2gs::ref {

// features: [A,3]. Returns the selected anchor ids, ascending.
std::vector<int32_t> region_grow_reference(const AnchorGraph& g, const std::vector<float>& features, int32_t seed,
                                           float tau, float min_weight);

}  // namespace ag2gs::ref
