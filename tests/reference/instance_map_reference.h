// Double-precision reference of the instance maps (train/stage3/instance_map.h,
// kernels/instance_map.cl), written from their definition: the Gaussians
// projected by the reference renderer (ref::project) and blended per pixel in
// (z, index) order with the rules of docs/rasterizer.md (alpha clamp at 0.99,
// skip below 1/255, stop when T would fall below 1e-4), every cluster's weight
// W_c(p) = sum of alpha_i T_i over its Gaussians summed exactly in double (one
// map entry per cluster), instead of the device's weighted majority vote.
// Gaussian g belongs to the cluster of anchor g / K.
#pragma once

#include <cstdint>
#include <map>
#include <vector>

#include "host/core/gaussians.h"
#include "tests/reference/reference_renderer.h"

namespace ag2gs::ref {

// Per pixel: the weight of every cluster, the reference id (> min_fraction)
// and the largest weight.
struct RefInstance {
  std::vector<std::map<int, double>> W;  // [H*W] cluster -> weight (cluster >= 0 only)
  std::vector<int> id;                   // [H*W] the cluster with W > min_fraction, -1 for none
  std::vector<double> best;              // [H*W] the largest W over clusters, 0 for none
};

// anchor_cluster: [A] cluster id per anchor, -1 for none; K children per anchor.
RefInstance instance_map_reference(const GaussianSet& set, const Camera& cam,
                                   const std::vector<int32_t>& anchor_cluster, int K, double min_fraction = 0.5);

}  // namespace ag2gs::ref
