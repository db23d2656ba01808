// Double-precision reference of the baseline's densification decisions
// (train/baseline/free_trainer.h, plan_densification), written the way
// 3DGS's densify_and_prune is, with masks over a growing set rather than the
// library's single pass: the clone mask on the original rows (mean gradient
// grad_sum / count >= grad_threshold, max scale <= percent_dense x extent),
// clones appended (gradient 0, radius 0); the split mask on the grown set
// (same gradient, larger scale), two samples per split row appended (scale /
// 1.6), split rows removed; then the prune mask over what is left (opacity <
// prune_opacity; with prune_big also max radius > max_screen_size or max
// scale > max_world_size x extent). Scales, gradients and opacities in double.
#pragma once

#include <tuple>
#include <vector>

#include "train/baseline/free_trainer.h"

namespace ag2gs::ref {

// One surviving row: kind (0 kept, 1 clone, 2 split), source row, split sample.
using DensifyRow = std::tuple<int, int, int>;

// Every surviving row, in the reference's own order (not sorted).
std::vector<DensifyRow> densify_reference(const FreeGaussians& g, const DensifyStats& s, const FreeTrainConfig& c,
                                          double extent, bool prune_big);

}  // namespace ag2gs::ref
