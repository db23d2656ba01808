// Plain-loop reference of the anchor graph's construction
// (train/graph/anchor_graph.h, AnchorGraph::build), O(N^2) from the
// definition instead of the library's hashing of neighbourhood cells: through
// the voxel centres in double, the neighbourhood cell of an anchor is
// floor((centre - origin) / (scale * top_voxel)); i ~ j when i != j and the
// cells differ by at most 1 on every axis. Integer output, no rounding beyond
// the floor.
#pragma once

#include <vector>

#include "train/anchors/anchor_model.h"

namespace ag2gs::ref {

// [A] rows of neighbour ids, each ascending.
std::vector<std::vector<int>> anchor_graph_rows_reference(const AnchorModel& m, int scale);

}  // namespace ag2gs::ref
