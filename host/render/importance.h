// How much each Gaussian draws: the sum, over every pixel of a set of views,
// of its blending weight w = alpha T (the share of the pixel's colour it
// gives). A Gaussian whose weights add up to a fraction of a pixel over all
// the training views changes no picture; pruning by it is the importance
// rule of LightGaussian and Mini-Splatting, here per anchor (the trainer
// sums the children).
//
// The weights come from one walk of each view's depth-sorted tile lists
// (Renderer::blend_weights, kernels/blend_bwd.cl): blend_fwd's weights,
// summed per Gaussian in the blend backward's fixed order, without atomics,
// so the result has the same bits on every run and thread count, and equals
// the backward of an upstream gradient of 1 on feature channel 0 (a rendered
// feature channel is sum_i w_i f_i, so that gradient of f_i is sum w_i);
// tests/host/render/test_render_backward.cpp checks both. Views are added on the host in
// double, in order.
#pragma once

#include <cstdint>
#include <vector>

#include "host/core/gaussians.h"
#include "host/render/renderer.h"

namespace ag2gs {

// One entry per Gaussian of `g` (g.n), in pixels: the sum of its blending
// weights over every pixel of every camera. The renderer's frame state is
// replaced (as by a forward()).
std::vector<double> blend_weight_sums(Renderer& renderer, const DeviceGaussians& g, const std::vector<Camera>& cameras,
                                      const RenderSettings& settings);

// The importance prune's choice: with the weight sums of A anchors' K
// children each (per_child, [A*K]), keep[a] = 0 for the anchors that draw
// least, taken from the least up while together they draw at most
// `share` of all the anchors' weight; ties go by index (deterministic).
// Never every anchor: with share >= 1 the most drawing one stays.
std::vector<uint8_t> least_drawing_anchors(const std::vector<double>& per_child, int children, double share);

}  // namespace ag2gs
