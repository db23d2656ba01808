// Stage 3, part 2: the instance maps of every anchor cluster of a view in one
// pass over the renderer's last frame (kernels/instance_map.cl).
//
// Definition. With w_i = alpha_i T_i the blending weight of Gaussian i at
// pixel p exactly as the forward pass blends it (same occlusion by every
// Gaussian, same alpha clamp, skip and early-termination rules), and
// W_c(p) = sum of w_i over the Gaussians of cluster c (Gaussian g belongs to
// the cluster of anchor g / K),
//   id(p) = c   when W_c(p) > min_fraction (>= 0.5; at most one c can pass),
//           -1  otherwise.
// So the map of cluster c is the binary render "c white, the rest black,
// normal occlusion" thresholded at min_fraction, for all clusters at once.
// weight(p) is the weight of the only possible candidate (a weighted majority
// vote along the ray, see kernels/instance_map.cl): W_id(p) where id >= 0, else
// a number <= min_fraction: the candidate's W_c(p), or, where the vote itself
// proves that no cluster passes (a cluttered ray), an upper bound of it (0
// when no clustered Gaussian blends).
//
// Precision: the weights are the rendered float weights bit for bit; W_c is
// their float sum in blending order (tests/train/stage3/test_clustering.cpp measures it
// against a double reference). Pixels whose exact W_c lies within that
// rounding of min_fraction may go either way.
//
// Usage, per view:
//   renderer.forward(gaussians, camera, settings);   // gaussians from Expander: row g = a*K + i
//   mapper.compute(renderer);                         // after set_clusters()
//   InstanceMap m = mapper.download();                // or device_ids()/device_weights()
// or, when the view's feature and alpha are all that is read besides the ids:
//   renderer.bin(gaussians, camera, settings);       // no blend
//   mapper.compute_with_images(renderer);             // + device_feature()/device_alpha()
#pragma once

#include <cstdint>
#include <vector>

#include "host/device/cl_runtime.h"
#include "host/render/renderer.h"

namespace ag2gs {

struct InstanceMap {
  int width = 0, height = 0;
  std::vector<int32_t> ids;   // [H,W] cluster id, -1 = none
  std::vector<float> weight;  // [H,W] see above
};

class InstanceMapper {
 public:
  explicit InstanceMapper(Runtime& rt);

  // anchor_cluster: [A] cluster id per anchor (-1 = none), K children per
  // anchor; the rendered Gaussians must number A*K. min_fraction in [0.5, 1).
  void set_clusters(const std::vector<int32_t>& anchor_cluster, int children, float min_fraction = 0.5f);
  // Runs on the renderer's last forward(). Throws std::invalid_argument when
  // the frame's Gaussian count is not A*K, std::logic_error before set_clusters.
  void compute(const Renderer& renderer);
  // compute() that also writes the feature planes [3,H,W] and the alpha
  // [H,W] bit for bit as Renderer::forward() blends them (settings.features
  // on), from the same walk: after Renderer::bin() the view needs no blend
  // pass (stage 3 renders each view once instead of twice).
  void compute_with_images(const Renderer& renderer);
  InstanceMap download() const;

  // Results of the last compute(), [H,W], valid until the next compute().
  const DeviceBuffer& device_ids() const { return ids_; }
  const DeviceBuffer& device_weights() const { return weights_; }
  // After compute_with_images(): planar like Renderer::device_feature()/device_alpha().
  const DeviceBuffer& device_feature() const { return feat_; }
  const DeviceBuffer& device_alpha() const { return alpha_; }
  int width() const { return width_; }
  int height() const { return height_; }

 private:
  Runtime& rt_;
  void run(const Renderer& renderer, bool with_images);
  DeviceBuffer anchor_cluster_, ids_, weights_, feat_, alpha_;
  size_t anchors_ = 0;
  int children_ = 0;
  float min_fraction_ = 0.5f;
  bool have_clusters_ = false;
  int width_ = 0, height_ = 0;
};

}  // namespace ag2gs
