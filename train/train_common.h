// Pieces both trainers (train/trainer.h, train/baseline/free_trainer.h) share:
// evaluation on held-out views, the upload of a view's target image, the
// 3DGS opacity reset and the exponential learning-rate schedule. The
// optimiser groups are in train/param_groups.h.
#pragma once

#include <vector>

#include "host/device/cl_runtime.h"
#include "host/losses/image_loss.h"
#include "host/render/renderer.h"
#include "host/render/sky.h"
#include "host/scene/scene.h"

namespace ag2gs {

struct EvalStats {
  int views = 0;
  double psnr = 0, ssim = 0, l1 = 0;  // means over the views
};

// Mean PSNR/SSIM/L1 over `views`, each rendered from `gaussians` with
// `settings` (and composited over `sky` when given), colours clamped to
// [0, 1], against the scene's photo.
EvalStats evaluate_views(Renderer& renderer, ImageLoss& loss, const DeviceGaussians& gaussians, Scene& scene,
                         const std::vector<int>& views, const RenderSettings& settings, float lambda_ssim,
                         Sky* sky = nullptr);

// The renderer's last frame composited over `sky` (Sky::compose), read
// back into out.rgb ([H, W, 3], as RenderOutput holds it).
void composite_sky(Renderer& renderer, Sky& sky, const Camera& camera, RenderOutput& out);

// The photo as the losses read it, planar [3, H, W] on the device: each
// pixel the mean of its downscale x downscale block (1 = the photo as
// loaded). `planar` is host scratch space kept between calls.
void upload_target(const Image& photo, int downscale, std::vector<float>& planar, DeviceBuffer& dst);

// 3DGS's opacity reset: every opacity becomes min(opacity, 0.01), through
// the logit (the caller zeroes the opacity group's moments).
void cap_opacity_logits(std::vector<float>& opacity_logit);

// The camera of an image downscaled by an integer factor: width / factor
// (rounded down, at least 1) and every intrinsic divided by the factor.
Camera downscaled_camera(const Camera& cam, int factor);
// That image's pixels, each the mean of its factor x factor block of `img`,
// written planar [3, H, W] to `out` (room for 3 x the small image's pixels).
void box_downscale_planar(const Image& img, int factor, float* out);

// init * (final / init)^progress, progress clamped to [0, 1] (init <= 0: 0).
double exp_decay_lr(double init, double final_value, double progress);

}  // namespace ag2gs
