#include "train/anchors/expander.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <map>
#include <stdexcept>
#include <string>

#include "host/render/gaussian_buffers.h"

namespace ag2gs {

namespace {

constexpr int kWorkGroup = 64;

// The expansion kernels' defines: the child count and the scale cap (as a
// float literal that reads back as the same float).
std::map<std::string, std::string> expand_defines(const DeviceAnchors& anchors) {
  char cap[32];
  std::snprintf(cap, sizeof cap, "%.9ef", static_cast<double>(anchors.scale_cap));
  return {{"CHILDREN", std::to_string(anchors.children)}, {"SCALE_CAP", cap}};
}

// Throws unless `b` holds at least `floats` floats.
void need_floats(const DeviceBuffer* b, size_t floats, const char* what) {
  if (!b) throw std::invalid_argument(std::string("expand backward: gradient buffer '") + what + "' is missing");
  if (b->capacity() < floats * sizeof(float))
    throw std::invalid_argument(std::string("expand backward: gradient buffer '") + what + "' holds " +
                                std::to_string(b->capacity() / sizeof(float)) + " floats, expected " +
                                std::to_string(floats));
}

void reserve_floats(DeviceBuffer& b, size_t floats) {
  b.reserve(std::max<size_t>(floats * sizeof(float), 4));
}

// [N,16,3] -> [N,3] DC and [N,15,3] rest, and back.
void split_sh(const std::vector<float>& sh, size_t n, std::vector<float>& dc, std::vector<float>& rest) {
  dc.resize(n * 3);
  rest.resize(n * kShRestCoeffs * 3);
  for (size_t g = 0; g < n; ++g) {
    const float* src = &sh[g * kAnchorShCoeffs * 3];
    std::copy_n(src, 3, &dc[g * 3]);
    std::copy_n(src + 3, kShRestCoeffs * 3, &rest[g * kShRestCoeffs * 3]);
  }
}
void merge_sh(const std::vector<float>& dc, const std::vector<float>& rest, size_t n, std::vector<float>& sh) {
  sh.resize(n * kAnchorShCoeffs * 3);
  for (size_t g = 0; g < n; ++g) {
    float* dst = &sh[g * kAnchorShCoeffs * 3];
    std::copy_n(&dc[g * 3], 3, dst);
    std::copy_n(&rest[g * kShRestCoeffs * 3], kShRestCoeffs * 3, dst + 3);
  }
}

}  // namespace

// ---------------------------------------------------------------- DeviceAnchors

DeviceAnchors::DeviceAnchors(Runtime& rt)
    : pos(&rt),
      voxel(&rt),
      feature(&rt),
      offset(&rt),
      scale_logit(&rt),
      quat(&rt),
      opacity_logit(&rt),
      sh_dc(&rt),
      sh_rest(&rt) {}

void DeviceAnchors::upload(const AnchorModel& model) {
  model.check();
  anchors = model.size();
  children = model.children();
  sh_degree = model.config().sh_degree;
  scale_cap = model.config().scale_cap;
  // Between the edges of the last capped layer and the next: layers differ by
  // a factor >= 2 (layer_ratio), so the comparison in float is unambiguous.
  const AnchorConfig& c = model.config();
  cap_edge = c.scale_cap_layers >= model.grid().layers
                 ? 0.f
                 : static_cast<float>(
                       std::sqrt(model.grid().voxel(c.scale_cap_layers - 1) * model.grid().voxel(c.scale_cap_layers)));
  pos.upload(model.pos());
  voxel.upload(model.voxel());
  feature.upload(model.feature());
  offset.upload(model.offset());
  scale_logit.upload(model.scale_logit());
  quat.upload(model.quat());
  opacity_logit.upload(model.opacity_logit());
  std::vector<float> dc, rest;
  split_sh(model.sh(), gaussians(), dc, rest);
  sh_dc.upload(dc);
  sh_rest.upload(rest);
}

void DeviceAnchors::download(AnchorModel& model) {
  if (model.size() != anchors || model.children() != children)
    throw std::invalid_argument("DeviceAnchors::download: the model has " + std::to_string(model.size()) + " x " +
                                std::to_string(model.children()) + " Gaussians, the device copy " +
                                std::to_string(anchors) + " x " + std::to_string(children));
  const size_t n = gaussians();
  feature.download(model.feature(), anchors * 3);
  offset.download(model.offset(), n * 3);
  scale_logit.download(model.scale_logit(), n * 3);
  quat.download(model.quat(), n * 4);
  opacity_logit.download(model.opacity_logit(), n);
  std::vector<float> dc, rest;
  sh_dc.download(dc, n * 3);
  sh_rest.download(rest, n * kShRestCoeffs * 3);
  merge_sh(dc, rest, n, model.sh());
}

// ---------------------------------------------------------------- DeviceAnchorGrads

DeviceAnchorGrads::DeviceAnchorGrads(Runtime& rt)
    : feature(&rt), offset(&rt), scale_logit(&rt), quat(&rt), opacity_logit(&rt), sh_dc(&rt), sh_rest(&rt) {}

void DeviceAnchors::release() {
  for (DeviceBuffer* b : {&pos, &voxel, &feature, &offset, &scale_logit, &quat, &opacity_logit, &sh_dc, &sh_rest})
    b->release();
}

void DeviceAnchorGrads::release() {
  for (DeviceBuffer* b : {&feature, &offset, &scale_logit, &quat, &opacity_logit, &sh_dc, &sh_rest}) b->release();
}

AnchorGrads DeviceAnchorGrads::download() {
  const size_t n = gaussians();
  AnchorGrads g;
  feature.download(g.feature, anchors * 3);
  offset.download(g.offset, n * 3);
  scale_logit.download(g.scale_logit, n * 3);
  quat.download(g.quat, n * 4);
  opacity_logit.download(g.opacity_logit, n);
  std::vector<float> dc, rest;
  sh_dc.download(dc, n * 3);
  sh_rest.download(rest, n * kShRestCoeffs * 3);
  merge_sh(dc, rest, n, g.sh);
  return g;
}

// ---------------------------------------------------------------- Expander

Expander::Expander(Runtime& rt) : rt_(rt) {}

void Expander::forward(const DeviceAnchors& anchors, DeviceGaussians& out, int active_sh_degree) {
  if (active_sh_degree < 0 || active_sh_degree > anchors.sh_degree)
    throw std::invalid_argument("expand: active SH degree " + std::to_string(active_sh_degree) + " is outside 0.." +
                                std::to_string(anchors.sh_degree) + " (the model's SH degree)");
  const size_t n = anchors.gaussians();
  if (n > static_cast<size_t>(INT32_MAX))
    throw std::invalid_argument("expand: " + std::to_string(n) + " Gaussians exceed the 32-bit index range");
  const int sh_out = sh_coeffs_for_degree(active_sh_degree);
  out.n = n;
  out.sh_degree = active_sh_degree;
  reserve_floats(out.means, n * 3);
  reserve_floats(out.scales, n * 3);
  reserve_floats(out.quats, n * 4);
  reserve_floats(out.opacities, n);
  reserve_floats(out.sh, n * sh_out * 3);
  reserve_floats(out.features, n * 3);
  if (n == 0) return;
  cl::Kernel k = rt_.kernel("expander.cl", "expand_fwd", expand_defines(anchors));
  const size_t a = anchors.anchors, f4 = sizeof(float);
  KernelCall call(k);
  call.arg("n", static_cast<int>(n))
      .buffer("pos", anchors.pos, a * 3 * f4)
      .buffer("voxel", anchors.voxel, a * f4)
      .buffer("feature", anchors.feature, a * 3 * f4)
      .buffer("offset", anchors.offset, n * 3 * f4)
      .buffer("scale_logit", anchors.scale_logit, n * 3 * f4)
      .buffer("quat", anchors.quat, n * 4 * f4)
      .buffer("opacity_logit", anchors.opacity_logit, n * f4)
      .buffer("sh_dc", anchors.sh_dc, n * 3 * f4)
      .buffer("sh_rest", anchors.sh_rest, sh_out > 1 ? n * kShRestCoeffs * 3 * f4 : 0)
      .arg("sh_out", sh_out)
      .arg("cap_edge", anchors.cap_edge);
  gaussian_buffers(call, out).done();
  rt_.launch("expand", k, cl::NDRange(n), cl::NDRange(kWorkGroup));
}

void Expander::backward(const DeviceAnchors& anchors, const DeviceGaussianGrads& grads, DeviceAnchorGrads& out) {
  const size_t n = anchors.gaussians();
  if (grads.n != n)
    throw std::invalid_argument("expand backward: the gradients are for " + std::to_string(grads.n) +
                                " Gaussians, the anchors expand to " + std::to_string(n));
  if (grads.sh_degree < 0 || grads.sh_degree > 3)
    throw std::invalid_argument("expand backward: gradient SH degree " + std::to_string(grads.sh_degree) +
                                " is outside 0..3");
  const int sh_in = sh_coeffs_for_degree(grads.sh_degree);
  need_floats(grads.means, n * 3, "means");
  need_floats(grads.scales, n * 3, "scales");
  need_floats(grads.quats, n * 4, "quats");
  need_floats(grads.opacities, n, "opacities");
  need_floats(grads.sh, n * sh_in * 3, "sh");
  need_floats(grads.features, n * 3, "features");
  out.anchors = anchors.anchors;
  out.children = anchors.children;
  reserve_floats(out.feature, anchors.anchors * 3);
  reserve_floats(out.offset, n * 3);
  reserve_floats(out.scale_logit, n * 3);
  reserve_floats(out.quat, n * 4);
  reserve_floats(out.opacity_logit, n);
  reserve_floats(out.sh_dc, n * 3);
  reserve_floats(out.sh_rest, n * kShRestCoeffs * 3);
  if (n == 0) return;
  const std::map<std::string, std::string> defines = expand_defines(anchors);
  cl::Kernel k = rt_.kernel("expander.cl", "expand_bwd", defines);
  const size_t f4 = sizeof(float);
  KernelCall(k)
      .arg("n", static_cast<int>(n))
      .buffer("voxel", anchors.voxel, anchors.anchors * f4)
      .buffer("scale_logit", anchors.scale_logit, n * 3 * f4)
      .buffer("opacity_logit", anchors.opacity_logit, n * f4)
      .buffer("v_means", *grads.means, n * 3 * f4)
      .buffer("v_scales", *grads.scales, n * 3 * f4)
      .buffer("v_quats", *grads.quats, n * 4 * f4)
      .buffer("v_opacities", *grads.opacities, n * f4)
      .buffer("v_sh", *grads.sh, n * sh_in * 3 * f4)
      .arg("sh_in", sh_in)
      .arg("cap_edge", anchors.cap_edge)
      .buffer("v_offset", out.offset, n * 3 * f4)
      .buffer("v_scale_logit", out.scale_logit, n * 3 * f4)
      .buffer("v_quat", out.quat, n * 4 * f4)
      .buffer("v_opacity_logit", out.opacity_logit, n * f4)
      .buffer("v_sh_dc", out.sh_dc, n * 3 * f4)
      .buffer("v_sh_rest", out.sh_rest, n * kShRestCoeffs * 3 * f4)
      .done();
  rt_.launch("expand_bwd", k, cl::NDRange(n), cl::NDRange(kWorkGroup));
  cl::Kernel kf = rt_.kernel("expander.cl", "expand_bwd_feature", defines);
  set_kernel_args(kf, static_cast<int>(anchors.anchors), *grads.features, out.feature);
  rt_.launch("expand_bwd", kf, cl::NDRange(anchors.anchors), cl::NDRange(kWorkGroup));
}

}  // namespace ag2gs
