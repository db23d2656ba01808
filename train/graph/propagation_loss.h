// The propagation loss of stage 2 on the device (kernels/propagation_loss.cl): a
// Dirichlet energy of the anchors' semantic features over the anchor graph
// with bilateral weights, never forming a Laplacian:
//
//   L_prop = (1 / |E|) sum_{(i,j) in E} w_ij |f_i - f_j|^2,
//   w_ij   = exp(-|f_i - f_j|^2 / (2 tau^2)),   tau = 0.05
//
// E: the undirected edges of an AnchorGraph (each counted once).
//
// Normalisation: a mean over edges, not a sum. The stage-1 terms it is added
// to are means (over pixels, over offsets). An anchor's share of a pixel-mean
// gradient shrinks as 1/A with the anchor count A; so does its gradient of
// the edge mean, ~ 4 |f_i - f_j| / A (|E| ~ A * degree / 2). The ratio of the
// two, and so the meaning of the weight, then depends neither on
// the scene's size nor on the graph's density (cell_scale 2 has ~4x the
// edges, not ~4x the loss). With a sum, the propagation gradient per anchor
// would stay constant while the photometric one shrinks: at 0.01 it would
// swamp large scenes and be weak on small ones. The loss is a mean edge
// energy in [0, 2 tau^2 / e] ~ [0, 1.8e-3] (w d peaks at d = 2 tau^2), easy to
// read in logs whatever the scene.
//
// Weight: the paper's 0.01 multiplies a sum over ordered pairs, 2 |E| times
// this mean (0.02 |E| ~ 3700 at the 185k edges of a 5k-anchor scene), so
// its number does not carry over. Measured on a generated hard scene
// (160x120, 3000 + 500 iterations, bench/query_benchmark.sh, features in
// the unit ball with the unmasked group, text / click mIoU): w 0 46.3 /
// 45.7, 0.01 64.1 / 64.8, 10 72.0 / 72.0, 100 69.0 / 69.0 (boundary IoU
// 53.9 vs 65.3 at 10). Before the features were bounded, ~2000 (the paper's
// sum) fragmented them into locally flat patches. Default 10.
//
// Gradient: by default the weights are held constant (stop-gradient), so
//   dL/df_i = (2 / |E|) sum_{j in N(i)} w_ij (f_i - f_j).
// Why: held constant, the weights act as an edge-stopping function and every
// edge only ever pulls its two features together, strongly when they are
// already close (same object) and hardly at all across a feature jump (an
// object boundary). Differentiated, d(w d)/dd = w (1 - d / (2 tau^2)) turns
// negative for |f_i - f_j| > sqrt(2) tau ~ 0.07: edges across boundaries push
// the features apart, a contrastive force whose strength is set by tau rather
// than by the mask losses, which already own that job (L_ic). Holding the
// weights constant is also what the official implementation does as far as
// we know (bilateral weights under no_grad). `differentiate_weights` gives
// the exact gradient of L_prop for experiments; both are tested.
//
// How the trainer uses it (stage 2 iterations):
//   AnchorGraph graph = AnchorGraph::build(model);       // at the start of stage 2
//   PropagationLoss prop(rt);  prop.set_graph(graph);
//   per iteration, after expander.backward(anchors, renderer.device_grads(), grads)
//   (which overwrites grads.feature) and before the Adam step of the feature group:
//     prop.enqueue(anchors.feature, &grads.feature, anchors.anchors, w);
//                                                 // grads.feature += w dL_prop/df
//     ... when logging: double l = prop.result();              // waits; unweighted L_prop
//   After every growing/pruning round (anchor ids change): rebuild and
//   set_graph again; enqueue() refuses a graph whose anchor count differs from
//   the buffers', and graph.matches(model) tells whether a graph is still
//   current (same anchors, same order). The model file
//   stores the graph with graph.to_archive(archive) next to model.to_archive.
// Buffers: features [A,3] float (DeviceAnchors::feature), gradients [A,3]
// float (DeviceAnchorGrads::feature), row i = anchor i.
//
// Deterministic: one work-item per undirected edge computes its weight once
// (the loss summed per work-group in a fixed tree, over groups on the host in
// order); one work-item per anchor then gathers over its own CSR row in a
// fixed order and writes only its own gradient row. No atomics: the same bits
// whatever the number of device threads. Device memory per graph: 4 bytes per
// CSR entry twice (neighbours, entry -> edge id) and 12 per undirected edge.
#pragma once

#include <cstdint>
#include <vector>

#include "host/device/cl_runtime.h"
#include "train/graph/anchor_graph.h"

namespace ag2gs {

constexpr float kPropagationTau = 0.05f;     // bilateral bandwidth tau
constexpr float kPropagationWeight = 10.0f;  // weight of the edge-mean L_prop in L_stage2 (see above)

struct PropagationLossConfig {
  float tau = kPropagationTau;         // > 0
  bool differentiate_weights = false;  // false: weights held constant in the gradient (see above)
  int work_group = 0;                  // a power of two; 0: the device's largest up to 256
};

class PropagationLoss {
 public:
  explicit PropagationLoss(Runtime& rt, PropagationLossConfig config = {});

  // Uploads the graph's CSR arrays, its undirected edge list and the edge id
  // of every CSR entry (linear time). Call again after every rebuild.
  void set_graph(const AnchorGraph& graph);
  size_t anchors() const { return anchors_; }
  size_t edges() const { return edges_; }

  // Device API; enqueues only, no host synchronisation.
  //   features: [A,3] floats
  //   feature_grads: [A,3] floats, accumulated: += weight * dL_prop/df
  //                  (null: loss only, nothing written)
  //   anchors: A of these buffers (DeviceAnchors::anchors); must equal the
  //            graph's anchor count, else std::invalid_argument saying to
  //            rebuild the graph (a stale graph after growing/pruning)
  // With no edges the loss is 0 and the gradients are left unchanged.
  void enqueue(const DeviceBuffer& features, DeviceBuffer* feature_grads, size_t anchors,
               float weight = kPropagationWeight);
  // L_prop (unweighted, the mean above) of the last enqueue(); waits for it.
  double result();

  // Host convenience (tests, tools): features [A,3]; with `grads` non-null it
  // must hold [A,3] values and receives grads += weight * dL/df. Returns L_prop.
  double forward_backward(const std::vector<float>& features, std::vector<float>* grads,
                          float weight = kPropagationWeight);

  const PropagationLossConfig& config() const { return config_; }
  int work_group() const { return wg_; }

 private:
  Runtime& rt_;
  PropagationLossConfig config_;
  int wg_ = 1;
  size_t anchors_ = 0, edges_ = 0;
  int edge_groups_ = 0;  // work-groups over the padded edge list
  int groups_ = -1;      // of the last enqueue, -1 before the first
  DeviceBuffer row_offsets_, neighbours_, entry_edge_, edge_i_, edge_j_, coef_, partials_;
  DeviceBuffer host_features_, host_grads_;  // for the host overload
};

}  // namespace ag2gs
