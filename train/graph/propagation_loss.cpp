#include "train/graph/propagation_loss.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <map>
#include <stdexcept>
#include <string>

#include "host/device/kernel_call.h"

namespace ag2gs {

namespace {

std::map<std::string, std::string> prop_defines(int wg) {
  return {{"WG", std::to_string(wg)}};
}

void check_capacity(const DeviceBuffer& b, size_t bytes, const char* what) {
  if (b.capacity() < bytes)
    throw std::invalid_argument(std::string("propagation loss: buffer '") + what + "' holds " +
                                std::to_string(b.capacity()) + " bytes, the graph's anchors need " +
                                std::to_string(bytes) + "; upload all the anchors' features first");
}

}  // namespace

PropagationLoss::PropagationLoss(Runtime& rt, PropagationLossConfig config) : rt_(rt), config_(config) {
  if (!(config_.tau > 0.f) || !std::isfinite(config_.tau))
    throw std::invalid_argument("propagation loss: tau must be positive and finite, got " +
                                std::to_string(config_.tau));
  for (DeviceBuffer* b : {&row_offsets_, &neighbours_, &entry_edge_, &edge_i_, &edge_j_, &coef_, &partials_,
                          &host_features_, &host_grads_})
    b->bind(&rt_);
  wg_ = choose_launch_shape(rt_, "propagation loss", config_.work_group, 1, [&](int wg, int) {
          size_t limit = ~size_t(0);
          for (const char* name : {"prop_edges", "prop_grad"}) {
            cl::Kernel k = rt_.kernel("propagation_loss.cl", name, prop_defines(wg));
            limit = std::min(limit, k.getWorkGroupInfo<CL_KERNEL_WORK_GROUP_SIZE>(rt_.info().device));
          }
          return limit;
        }).work_group;
  set_graph(AnchorGraph());
}

void PropagationLoss::set_graph(const AnchorGraph& graph) {
  // No validate(): an AnchorGraph only comes from build() or a validated
  // from_archive(), so it is symmetric and sorted (the cursor walk relies on it).
  anchors_ = graph.anchors();
  edges_ = graph.edges();
  // Undirected edges (i < j) in row order, padded to whole work-groups with
  // (0, 0), and the edge id of every CSR entry. Linear time: the entries of
  // row j naming i > j are met in ascending i, so cursor[j] walks row j.
  const std::vector<int32_t>& off = graph.row_offsets();
  const std::vector<int32_t>& nb = graph.neighbours();
  edge_groups_ = static_cast<int>((edges_ + wg_ - 1) / wg_);
  std::vector<int32_t> ei(static_cast<size_t>(edge_groups_) * wg_, 0), ej(ei.size(), 0), entry_edge(nb.size());
  std::vector<int32_t> cursor(off.begin(), off.end() - 1);
  int32_t next = 0;
  for (size_t i = 0; i < anchors_; ++i)
    for (int32_t k = off[i]; k < off[i + 1]; ++k) {
      const int32_t j = nb[k];
      if (j > static_cast<int32_t>(i)) {
        ei[next] = static_cast<int32_t>(i);
        ej[next] = j;
        entry_edge[k] = next++;
      } else {
        while (nb[cursor[j]] < static_cast<int32_t>(i)) ++cursor[j];  // skips row j's entries below j
        entry_edge[k] = entry_edge[cursor[j]++];
      }
    }
  row_offsets_.upload(off);
  neighbours_.upload(nb);  // upload() reserves at least 4 bytes, so an empty graph binds too
  entry_edge_.upload(entry_edge);
  edge_i_.upload(ei);
  edge_j_.upload(ej);
  coef_.reserve(std::max<size_t>(ei.size(), 1) * sizeof(float));
  partials_.reserve(std::max(edge_groups_, 1) * sizeof(float));
  groups_ = -1;
}

void PropagationLoss::enqueue(const DeviceBuffer& features, DeviceBuffer* feature_grads, size_t anchors, float weight) {
  if (anchors != anchors_)
    throw std::invalid_argument("propagation loss: the features are of " + std::to_string(anchors) +
                                " anchors, the graph of " + std::to_string(anchors_) +
                                "; rebuild the graph after growing/pruning (AnchorGraph::build) and call set_graph");
  if (!std::isfinite(weight))
    throw std::invalid_argument("propagation loss: the weight must be finite, got " + std::to_string(weight));
  if (feature_grads == &features)
    throw std::invalid_argument("propagation loss: the gradient buffer must differ from the feature buffer");
  const size_t bytes = anchors_ * 3 * sizeof(float);
  check_capacity(features, bytes, "features");
  if (feature_grads) check_capacity(*feature_grads, bytes, "feature_grads");
  groups_ = edge_groups_;
  if (edges_ == 0) return;  // loss 0, gradients unchanged

  const double tau = config_.tau;
  const float inv_two_tau2 = static_cast<float>(1.0 / (2.0 * tau * tau));
  const auto defs = prop_defines(wg_);
  cl::Kernel edges = rt_.kernel("propagation_loss.cl", "prop_edges", defs);
  const size_t padded_edges = static_cast<size_t>(groups_) * wg_;
  KernelCall(edges)
      .buffer("edge_i", edge_i_, padded_edges * sizeof(int32_t))
      .buffer("edge_j", edge_j_, padded_edges * sizeof(int32_t))
      .buffer("feature", features, bytes)
      .buffer("coef", coef_, padded_edges * sizeof(float))
      .arg("inv_two_tau2", inv_two_tau2)
      .arg("full_gradient", config_.differentiate_weights ? 1 : 0)
      .buffer("partials", partials_, static_cast<size_t>(groups_) * sizeof(float))
      .done();
  rt_.launch("prop_edges", edges, cl::NDRange(static_cast<size_t>(groups_) * wg_), cl::NDRange(wg_));
  if (!feature_grads) return;
  const float grad_scale = static_cast<float>(2.0 * weight / static_cast<double>(edges_));
  cl::Kernel grad = rt_.kernel("propagation_loss.cl", "prop_grad", defs);
  const size_t entries = 2 * edges_;  // each edge in the rows of both its anchors
  KernelCall(grad)
      .arg("n", static_cast<cl_int>(anchors_))
      .buffer("row_offsets", row_offsets_, (anchors_ + 1) * sizeof(int32_t))
      .buffer("neighbours", neighbours_, entries * sizeof(int32_t))
      .buffer("entry_edge", entry_edge_, entries * sizeof(int32_t))
      .buffer("feature", features, bytes)
      .buffer("coef", coef_, padded_edges * sizeof(float))
      .arg("grad_scale", grad_scale)
      .buffer("grad", *feature_grads, bytes)
      .done();
  rt_.launch("prop_grad", grad, cl::NDRange(anchors_), cl::NDRange(wg_));
}

double PropagationLoss::result() {
  if (groups_ < 0) throw std::logic_error("PropagationLoss::result() before enqueue()");
  if (edges_ == 0) {
    AG2GS_CL_CHECK(rt_.queue().finish());
    return 0.0;
  }
  std::vector<float> part;
  partials_.download(part, static_cast<size_t>(groups_));
  double sum = 0;
  for (float p : part) sum += p;
  return sum / static_cast<double>(edges_);
}

double PropagationLoss::forward_backward(const std::vector<float>& features, std::vector<float>* grads, float weight) {
  const size_t n = anchors_ * 3;
  if (features.size() != n)
    throw std::invalid_argument("propagation loss: " + std::to_string(features.size()) +
                                " feature values for a graph of " + std::to_string(anchors_) + " anchors (expected " +
                                std::to_string(n) + ")");
  if (grads && grads->size() != n)
    throw std::invalid_argument("propagation loss: " + std::to_string(grads->size()) +
                                " gradient values for a graph of " + std::to_string(anchors_) + " anchors (expected " +
                                std::to_string(n) + ")");
  host_features_.upload(features);
  if (grads) host_grads_.upload(*grads);
  enqueue(host_features_, grads ? &host_grads_ : nullptr, anchors_, weight);
  const double loss = result();
  if (grads) host_grads_.download(*grads, n);
  return loss;
}

}  // namespace ag2gs
