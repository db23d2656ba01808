// Double-precision reference of the expansion's backward pass
// (train/anchors/expander.h, kernels/expander.cl): the gradients of the
// anchors' parameters from those of the expanded Gaussians, written from the
// expansion's definition (expand_reference_double, the forward reference):
//   mean = pos + offset l          v_offset = v_mean l
//   scale = sigmoid(x) cap l       v_x = v_scale cap l sigmoid(x) sigmoid(-x)
//   opacity = sigmoid(y)           v_y = v_opacity sigmoid(y) sigmoid(-y)
//   quat, SH copied                v_quat, v_sh copied (SH above the degree 0)
//   feature shared by K children   v_feature = sum over the children
// l is the anchor's voxel edge, cap its layer's scale cap.
#pragma once

#include <vector>

#include "tests/reference/reference_renderer.h"
#include "train/anchors/anchor_model.h"

namespace ag2gs::ref {

// The layout of AnchorGrads: feature [A,3], offset and scale_logit [N,3],
// quat [N,4], opacity_logit [N], sh [N,48] (N = A K children).
struct RefAnchorGrads {
  std::vector<double> feature, offset, scale_logit, quat, opacity_logit, sh;
};

// v: the gradients of the expanded Gaussians at SH degree sh_degree.
RefAnchorGrads expand_backward_reference(const AnchorModel& m, const RefGrads& v, int sh_degree);

}  // namespace ag2gs::ref
