// The SAM mask losses of one view on the device (kernels/mask_loss.cl,
// docs/design.md section 4): L_is pulls the rendered features of each mask
// together, L_ic pushes the mask means apart, and their gradient with respect
// to the rendered feature map F (and its accumulated alpha).
//
// Definitions. Masks M_j are the pixels with label j in any layer of the view's
// label maps (a pixel in several layers with the same label counts once).
// G = F, or with alpha given ("normalise_by_alpha", the official code's
// feature / accumulated alpha): G = F / alpha where alpha >= kMaskAlphaMin and
// the pixel is excluded from every mask where alpha < kMaskAlphaMin (or NaN).
// N_j = number of (valid) pixels of M_j; Gbar_j = mean of G over M_j; a mask
// is present when N_j > 0, m = number of present masks.
//   L_is = sum_j sum_{p in M_j} |G(p) - Gbar_j|_1 / sum_j N_j
//   L_ic = 1 / (m (m - 1)) sum_{j != k} 1 / (|Gbar_j - Gbar_k|_1 + 1)
// Normalisation: L_is is divided by the number of (mask, pixel) memberships
// sum_j N_j, so it is the mean L1 distance (summed over the 3 channels) of a
// mask pixel to its mask mean: independent of resolution and of the number of
// masks. L_ic uses the L1 norm, as the paper's |.| and L_is: it is bounded in
// (0, 1], and with L1 its gradient never divides by a distance (L2 would be
// singular where two means coincide). Degenerate views (no masks, empty masks,
// masks with every pixel excluded, m = 1) give 0 losses and 0 gradients for
// the terms that do not exist; nothing is ever NaN unless the inputs are.
// Gradients use sign(0) = 0; the full chain through Gbar_j is included.
//
// Precision (float32 against the double reference, tests/host/losses/test_mask_loss.cpp,
// up to 160x120 and 40 masks): losses within ~1e-7 relative, gradients within
// ~2e-7 of their largest entry. Means are float sums over a mask's pixels, so
// the error grows slowly with mask size; where a pixel's feature lies within
// that error of its mask mean, sign(G - Gbar) may differ from a double
// computation (a kink of |.|, as in any float implementation).
//
// Deterministic: the mask pixel lists are built once per view on the host;
// per-chunk sums in a fixed order, per-mask sums in chunk order, the losses
// summed on the host in double. No floating-point atomics. The same inputs,
// device and options give the same bits.
#pragma once

#include <cstdint>
#include <vector>

#include "host/device/cl_runtime.h"
#include "host/losses/image_loss.h"  // ImageLayout
#include "host/scene/scene.h"        // ViewMasks

namespace ag2gs {

constexpr float kMaskAlphaMin = 0.1f;  // the official code's alpha threshold

struct MaskLossResult {
  double l_is = 0;          // mask-internal (smoothness) loss
  double l_ic = 0;          // mask-contrast loss
  int masks = 0;            // m: masks with at least one (valid) pixel
  int64_t mask_pixels = 0;  // sum_j N_j, the normaliser of L_is
  double loss(double w_is, double w_ic) const { return w_is * l_is + w_ic * l_ic; }
};

// `masks` plus one more mask: the pixels that no mask of any layer covers
// (id count, in layer 0; a zero CLIP row when the masks carry features).
// Training with it makes L_ic push every object's feature away from the
// unmasked surroundings (ground, walls that SAM left out), which otherwise
// nothing constrains; L_is pulls the surroundings together. Masks of size
// 0 x 0 or without unmasked pixels come back unchanged.
ViewMasks with_unmasked_group(const ViewMasks& masks);

// How the kernels split the work; the defaults suit the device.
struct MaskLossOptions {
  int work_group = 0;  // a power of two; 0: the device's (at most 256)
  int lanes = 0;       // entries per work-item, 1/2/4/8/16; 0: Runtime::vector_width()
};

class MaskLoss {
 public:
  explicit MaskLoss(Runtime& rt, MaskLossOptions options = {});

  // Uploads the label maps of a view and the per-mask pixel lists built from
  // them. With key >= 0 (e.g. the view index) a call with the key of the
  // masks already loaded returns at once (no upload); key -1 always uploads.
  // Returns whether it uploaded. Throws std::invalid_argument when the labels
  // do not match width x height x layers or lie outside -1..count-1.
  bool set_masks(const ViewMasks& masks, int64_t key = -1);
  int64_t masks_key() const { return key_; }
  int mask_count() const { return count_; }

  // Device API for the trainer: enqueues the kernels only, no host
  // synchronisation; result() then reads the losses of the last enqueue().
  //   feature: [3,H,W] or [H,W,3] per `layout`, the rendered feature map F
  //   alpha: [H,W] accumulated alpha; non-null switches on normalise_by_alpha
  //   grad_feature: receives w_is dL_is/dF + w_ic dL_ic/dF in F's layout
  //                 (overwritten, grown as needed); null: forward only
  //   grad_alpha: [H,W] receives the same for alpha (0 without alpha);
  //               overwritten; may be null
  // width and height must be those of the masks set last.
  void enqueue(const DeviceBuffer& feature, const DeviceBuffer* alpha, int width, int height, ImageLayout layout,
               float w_is, float w_ic, DeviceBuffer* grad_feature, DeviceBuffer* grad_alpha = nullptr);
  // The losses of the last enqueue(): waits for it and sums the per-mask
  // terms in double, in mask order.
  MaskLossResult result();

  // enqueue() + result().
  MaskLossResult forward_backward(const DeviceBuffer& feature, const DeviceBuffer* alpha, int width, int height,
                                  ImageLayout layout, float w_is, float w_ic, DeviceBuffer* grad_feature,
                                  DeviceBuffer* grad_alpha = nullptr);
  // Host convenience: feature [H,W,3] or [3,H,W] per `layout`, alpha [H,W] or
  // null; gradients returned in the same layouts when non-null.
  MaskLossResult forward_backward(const std::vector<float>& feature, const std::vector<float>* alpha, int width,
                                  int height, float w_is, float w_ic, std::vector<float>* grad_feature,
                                  std::vector<float>* grad_alpha = nullptr,
                                  ImageLayout layout = ImageLayout::kInterleaved);

  int work_group() const { return wg_; }
  int lanes() const { return lanes_; }
  int chunk() const { return wg_ * lanes_; }  // mask pixels per work-group in the gathers

 private:
  Runtime& rt_;
  int wg_ = 0, lanes_ = 1;
  int64_t key_ = -1;
  bool loaded_ = false, enqueued_ = false;
  int enqueued_count_ = 0;  // masks of the last enqueue()
  int entries_ = 0;         // pixels_ entries, every mask's pixel list
  int width_ = 0, height_ = 0, layers_ = 0, count_ = 0, chunks_ = 0;
  DeviceBuffer labels_, pixels_, chunk_table_, mask_chunks_;  // per view
  DeviceBuffer sums_, means_, stats_, abs_, coef_, terms_;    // per call
  DeviceBuffer host_f_, host_a_, host_gf_, host_ga_;          // for the host overload
};

}  // namespace ag2gs
