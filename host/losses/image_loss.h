// The photometric loss of 3DGS on the device (kernels/image_loss.cl):
//   L_rgb = (1 - lambda) L1 + lambda (1 - SSIM),  lambda = 0.2,
// SSIM with an 11x11 Gaussian window (sigma 1.5, C1 = 0.01^2, C2 = 0.03^2)
// applied per channel as a zero-padded "same" convolution, the map averaged
// over all pixels and channels; and its gradient with respect to the rendered
// image (the target gets none). Optional per-pixel weights w [H,W] turn both
// means into weighted means: sum_p w_p sum_c term / (3 sum_p w_p).
//
// Precision (float32, measured against a double reference in
// tests/host/losses/test_image_loss.cpp): loss within ~5e-7; gradient within ~2e-5 of
// its largest entry, up to ~1e-4 on smooth low-contrast images, whose small
// window variances make the SSIM partials large and cancelling (the same
// formulation, and error, as 3DGS's autograd SSIM).
//
// Deterministic: per work-group partial sums in a fixed tree order, summed on
// the host in double; no floating-point atomics. Same inputs, same device and
// same options give the same bits. Without weights the gradient is the same
// bits whatever the options; only the grouping of the partial sums (and,
// with weights, of sum w in the gradient's scale) depends on them.
#pragma once

#include <cmath>
#include <limits>
#include <vector>

#include "host/device/cl_runtime.h"

namespace ag2gs {

constexpr float kSsimLambda = 0.2f;  // 3DGS's weight of (1 - SSIM)

struct ImageLossResult {
  double loss = 0;  // (1 - lambda) l1 + lambda (1 - ssim)
  double l1 = 0;    // (weighted) mean |rendered - target|
  double ssim = 1;  // (weighted) mean of the SSIM map
  double mse = 0;   // (weighted) mean (rendered - target)^2
  double psnr() const;
};

// PSNR in dB of images in [0, 1]: 10 log10(1 / mse); +inf when mse is 0.
double psnr_from_mse(double mse);

// Buffer layout of the three images of one call.
enum class ImageLayout {
  kInterleaved,  // [H,W,3], as RenderOutput.rgb
  kPlanar,       // [3,H,W], as the renderer's device images
};

// How the kernels split the work; the defaults suit the device. Tests set
// them to exercise other devices' configurations on one device.
struct ImageLossOptions {
  int work_group = 0;  // work-items per group, a power of two; 0: the device's (at most 256)
  int lanes = 0;       // pixels per work-item, 1/2/4/8/16; 0: Runtime::vector_width() (16 CPU, 1 GPU)
};

class ImageLoss {
 public:
  explicit ImageLoss(Runtime& rt, ImageLossOptions options = {});

  // Device-level API for the trainer; enqueues only, no host synchronisation.
  //   rendered, target: [H,W,3] or [3,H,W] floats per `layout`
  //   grad_out: receives dL/d(rendered) in the same layout (grown as needed;
  //             must be another buffer than the inputs); null: forward only
  //   weights: [H,W] per-pixel weights (>= 0, not all 0), or null for none
  // The partial sums stay on the device until result() reads them.
  void enqueue(const DeviceBuffer& rendered, const DeviceBuffer& target, int width, int height,
               float lambda = kSsimLambda, DeviceBuffer* grad_out = nullptr, const DeviceBuffer* weights = nullptr,
               ImageLayout layout = ImageLayout::kInterleaved);
  // The loss of the last enqueue(): waits for it and sums the partials in
  // double. With all weights 0 it is 0 (l1 0, ssim 1) and the gradient is 0.
  ImageLossResult result();

  // enqueue() + result().
  ImageLossResult forward_backward(const DeviceBuffer& rendered, const DeviceBuffer& target, int width, int height,
                                   float lambda, DeviceBuffer* grad_out, const DeviceBuffer* weights = nullptr,
                                   ImageLayout layout = ImageLayout::kInterleaved);
  // Host convenience: [H,W,3] vectors in, [H,W,3] gradient out (when non-null).
  ImageLossResult forward_backward(const std::vector<float>& rendered, const std::vector<float>& target, int width,
                                   int height, float lambda = kSsimLambda, std::vector<float>* grad_out = nullptr,
                                   const std::vector<float>* weights = nullptr);

  int work_group() const { return wg_; }
  int lanes() const { return lanes_; }
  // The normalised 1D window, taps at offsets -5..5 (3DGS's gaussian(11, 1.5)).
  static std::vector<double> window();

 private:
  Runtime& rt_;
  int wg_ = 0, lanes_ = 1;
  int groups_ = 0;  // of the last enqueue, 0 before the first
  float lambda_ = kSsimLambda;
  DeviceBuffer blur_, coef_, partials_, norm_;
  DeviceBuffer host_x_, host_y_, host_w_, host_grad_;  // for the host overload
};

}  // namespace ag2gs
