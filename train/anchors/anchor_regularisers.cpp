#include "train/anchors/anchor_regularisers.h"

#include "host/device/kernel_call.h"

namespace ag2gs {

void enqueue_offset_regulariser(Runtime& rt, size_t n, float weight, const DeviceBuffer& offset, DeviceBuffer& grad,
                                DeviceBuffer& value) {
  if (n == 0) return;
  value.reserve(n * 4);
  cl::Kernel k = rt.kernel("anchor_regularisers.cl", "offset_reg", {});
  KernelCall(k)
      .arg("n", static_cast<cl_int>(n))
      .arg("scale", weight / static_cast<float>(n))
      .buffer("offset", offset, n * 3 * sizeof(float))
      .buffer("grad", grad, n * 3 * sizeof(float))
      .buffer("value", value, n * sizeof(float))
      .done();
  rt.launch("offset_reg", k, cl::NDRange(n), cl::NDRange(64));
}

void enqueue_feature_ball(Runtime& rt, size_t anchors, DeviceBuffer& feature) {
  if (anchors == 0) return;
  cl::Kernel k = rt.kernel("anchor_regularisers.cl", "feature_ball", {});
  set_kernel_args(k, static_cast<cl_int>(anchors), feature);
  rt.launch("feature_ball", k, cl::NDRange((anchors + 63) / 64 * 64), cl::NDRange(64));
}

}  // namespace ag2gs
