// Device copies of an AnchorModel and the expansion kernels (kernels/expander.cl):
// forward anchors -> DeviceGaussians (what Renderer::forward consumes) and
// backward renderer gradients -> anchor-parameter gradients.
//
// One training step on the device:
//   DeviceAnchors anchors(rt);   anchors.upload(model);
//   Expander expander(rt);       DeviceGaussians gaussians(rt);
//   expander.forward(anchors, gaussians, sh_degree);
//   renderer.forward(gaussians, camera, settings);  ... loss ...
//   renderer.backward(output_grads);
//   expander.backward(anchors, renderer.device_grads(), grads);
//   adam.step(group_offset, anchors.offset, grads.offset, lr); ...
//   anchors.download(model);     // when the host needs the values
//
// Gaussian row g = a * K + i is child i of anchor a in every per-child
// buffer, in the expanded Gaussians and in the renderer's per-Gaussian
// outputs (radii, means2d), so per-child statistics need no index map.
//
// Growing and pruning happen on the host model: download the device values
// (anchors.download(model)), call add_anchor / remove_anchors, upload again,
// and carry the optimiser state over with AdamGroup::gather: the rows are
// remove_anchors()'s kept list (per anchor) or AnchorModel::child_rows() of it
// (per child), plus -1 for each added anchor or child.
#pragma once

#include <cstddef>
#include <vector>

#include "host/device/cl_runtime.h"
#include "host/render/renderer.h"
#include "train/anchors/anchor_model.h"

namespace ag2gs {

// SH coefficients per channel in the device's sh_rest buffers (degree 3 minus DC).
constexpr int kShRestCoeffs = kAnchorShCoeffs - 1;

// The model's arrays on the device. The trained arrays are separate buffers,
// one optimiser group each; SH are split into DC and rest (the host model's
// [N,16,3] interleaves them) so that the two get their own learning rates.
// layer and cell stay on the host: the kernels do not need them.
struct DeviceAnchors {
  explicit DeviceAnchors(Runtime& rt);
  DeviceAnchors(const DeviceAnchors&) = delete;
  DeviceAnchors& operator=(const DeviceAnchors&) = delete;

  // Uploads every array (buffers grow as needed; after add_anchor or
  // remove_anchors upload again, or gather rows on the device).
  void upload(const AnchorModel& model);
  // Writes the trained arrays back into `model`, which must have the anchor
  // and child counts of the last upload (std::invalid_argument otherwise).
  void download(AnchorModel& model);
  // Frees every buffer (the counts stay) until the next upload.
  void release();

  size_t anchors = 0;     // A
  int children = 0;       // K
  int sh_degree = 3;      // the model's highest degree (config().sh_degree)
  float scale_cap = 1.f;  // config().scale_cap
  float cap_edge = 0.f;   // anchors with voxel edge >= cap_edge are capped by scale_cap, finer ones by 1
  size_t gaussians() const { return anchors * static_cast<size_t>(children); }

  DeviceBuffer pos;            // [A,3] voxel centres (fixed)
  DeviceBuffer voxel;          // [A]   voxel edge l (fixed)
  DeviceBuffer feature;        // [A,3]
  DeviceBuffer offset;         // [N,3] N = A*K
  DeviceBuffer scale_logit;    // [N,3]
  DeviceBuffer quat;           // [N,4]
  DeviceBuffer opacity_logit;  // [N]
  DeviceBuffer sh_dc;          // [N,3]
  DeviceBuffer sh_rest;        // [N,15,3]
};

// Host copy of anchor gradients in the host model's layout (sh [N,16,3]).
struct AnchorGrads {
  std::vector<float> feature;        // [A,3]
  std::vector<float> offset;         // [N,3]
  std::vector<float> scale_logit;    // [N,3]
  std::vector<float> quat;           // [N,4]
  std::vector<float> opacity_logit;  // [N]
  std::vector<float> sh;             // [N,16,3], zero above the active degree
};

// Gradients of the trained arrays, buffer for buffer as in DeviceAnchors.
// Every entry is written by Expander::backward (inactive SH with zeros).
struct DeviceAnchorGrads {
  explicit DeviceAnchorGrads(Runtime& rt);
  DeviceAnchorGrads(const DeviceAnchorGrads&) = delete;
  DeviceAnchorGrads& operator=(const DeviceAnchorGrads&) = delete;

  AnchorGrads download();
  // Frees the buffers until the next backward pass reserves them again.
  void release();

  size_t anchors = 0;
  int children = 0;
  size_t gaussians() const { return anchors * static_cast<size_t>(children); }

  DeviceBuffer feature;        // [A,3]
  DeviceBuffer offset;         // [N,3]
  DeviceBuffer scale_logit;    // [N,3]
  DeviceBuffer quat;           // [N,4]
  DeviceBuffer opacity_logit;  // [N]
  DeviceBuffer sh_dc;          // [N,3]
  DeviceBuffer sh_rest;        // [N,15,3]
};

class Expander {
 public:
  explicit Expander(Runtime& rt);

  // Writes the A*K Gaussians of `anchors` into `out` (buffers grow as
  // needed) with out.sh_degree = active_sh_degree, so out.sh holds exactly
  // (d+1)^2 coefficients per Gaussian, as the renderer expects. Throws
  // std::invalid_argument unless 0 <= active_sh_degree <= anchors.sh_degree.
  void forward(const DeviceAnchors& anchors, DeviceGaussians& out, int active_sh_degree);

  // Maps the gradients of the expanded Gaussians (the renderer's
  // device_grads() after backward(), or any buffers of those shapes: n must
  // be anchors.gaussians(), sh holds (grads.sh_degree+1)^2 coefficients) to
  // the anchor parameters. v_feature(a) sums its children's feature
  // gradients in child order; no atomics, so results are bit-reproducible.
  // means2d is not used (the trainer reads it from the renderer directly).
  void backward(const DeviceAnchors& anchors, const DeviceGaussianGrads& grads, DeviceAnchorGrads& out);

 private:
  Runtime& rt_;
};

}  // namespace ag2gs
