#include "stages/propagation_loss.h"

#include <cmath>
#include <limits>
#include <map>
#include <stdexcept>
#include <string>

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
  for (DeviceBuffer* b : {&row_offsets_, &neighbours_, &partials_, &host_features_, &host_grads_}) b->bind(&rt_);
  wg_ = choose_launch_shape(rt_, "propagation loss", config_.work_group, 1, [&](int wg, int) {
          cl::Kernel k = rt_.kernel("prop.cl", "prop_loss", prop_defines(wg));
          return k.getWorkGroupInfo<CL_KERNEL_WORK_GROUP_SIZE>(rt_.info().device);
        }).work_group;
  set_graph(AnchorGraph());
}

void PropagationLoss::set_graph(const AnchorGraph& graph) {
  graph.validate("propagation loss: set_graph");
  anchors_ = graph.anchors();
  edges_ = graph.edges();
  row_offsets_.upload(graph.row_offsets());
  neighbours_.upload(graph.neighbours());  // upload() reserves at least 4 bytes, so an empty graph binds too
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
  groups_ = static_cast<int>((anchors_ + wg_ - 1) / wg_);
  if (groups_ == 0) return;  // no anchors: loss 0, nothing to write

  partials_.reserve(static_cast<size_t>(groups_) * sizeof(float));
  const double tau = config_.tau;
  const float inv_two_tau2 = static_cast<float>(1.0 / (2.0 * tau * tau));
  const float grad_scale = edges_ ? static_cast<float>(2.0 * weight / static_cast<double>(edges_)) : 0.f;
  const int want_grad = feature_grads && edges_ ? 1 : 0;  // no edges: gradients stay as they are
  cl::Kernel k = rt_.kernel("prop.cl", "prop_loss", prop_defines(wg_));
  DeviceBuffer& grads = feature_grads ? *feature_grads : partials_;  // never written without want_grad
  set_kernel_args(k, static_cast<cl_int>(anchors_), row_offsets_, neighbours_, features, grads, inv_two_tau2,
                  grad_scale, config_.differentiate_weights ? 1 : 0, want_grad, partials_);
  rt_.launch("prop_loss", k, cl::NDRange(static_cast<size_t>(groups_) * wg_), cl::NDRange(wg_));
}

double PropagationLoss::result() {
  if (groups_ < 0) throw std::logic_error("PropagationLoss::result() before enqueue()");
  if (groups_ == 0 || edges_ == 0) {
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
