#include "train/train_common.h"

#include <algorithm>
#include <cmath>
#include <memory>

namespace ag2gs {

EvalStats evaluate_views(Renderer& renderer, ImageLoss& loss, const DeviceGaussians& gaussians, Scene& scene,
                         const std::vector<int>& views, const RenderSettings& settings, float lambda_ssim, Sky* sky) {
  EvalStats ev;
  if (views.empty()) return ev;
  for (int v : views) {
    renderer.forward(gaussians, scene.views()[v].camera, settings);
    RenderOutput out = renderer.download_output();
    if (sky) composite_sky(renderer, *sky, scene.views()[v].camera, out);
    for (float& x : out.rgb) x = std::clamp(x, 0.f, 1.f);
    std::shared_ptr<const Image> target = scene.image(v);
    ImageLossResult r =
        loss.forward_backward(out.rgb, target->rgb, out.width, out.height, lambda_ssim, nullptr, nullptr);
    ev.psnr += r.psnr();
    ev.ssim += r.ssim;
    ev.l1 += r.l1;
    ++ev.views;
  }
  ev.psnr /= ev.views;
  ev.ssim /= ev.views;
  ev.l1 /= ev.views;
  return ev;
}

void composite_sky(Renderer& renderer, Sky& sky, const Camera& camera, RenderOutput& out) {
  const DeviceBuffer& planar = sky.compose(renderer.device_rgb(), renderer.device_alpha(), camera);
  const size_t npix = static_cast<size_t>(camera.width) * camera.height;
  std::vector<float> p;
  planar.download(p, 3 * npix);
  out.rgb.resize(3 * npix);
  for (size_t i = 0; i < npix; ++i)
    for (size_t c = 0; c < 3; ++c) out.rgb[3 * i + c] = p[c * npix + i];
}

Camera downscaled_camera(const Camera& cam, int factor) {
  if (factor <= 1) return cam;
  Camera c = cam;
  c.width = std::max(1, cam.width / factor);
  c.height = std::max(1, cam.height / factor);
  // Pixel (x, y) of the small image covers [f x, f x + f) of the large one:
  // u_small = u_large / f exactly (a partial block at the right or bottom
  // edge is cropped, not resampled).
  c.fx = cam.fx / factor;
  c.fy = cam.fy / factor;
  c.cx = cam.cx / factor;
  c.cy = cam.cy / factor;
  return c;
}

void box_downscale_planar(const Image& img, int factor, float* out) {
  const int w = std::max(1, img.width / factor), h = std::max(1, img.height / factor);
  const size_t npix = static_cast<size_t>(w) * h;
  const int fx = std::min(factor, img.width), fy = std::min(factor, img.height);
  const float inv = 1.f / static_cast<float>(fx * fy);
  for (int y = 0; y < h; ++y)
    for (int x = 0; x < w; ++x)
      for (int c = 0; c < 3; ++c) {
        float sum = 0.f;
        for (int dy = 0; dy < fy; ++dy)
          for (int dx = 0; dx < fx; ++dx)
            sum += img.rgb[(static_cast<size_t>(y * fy + dy) * img.width + (x * fx + dx)) * 3 + c];
        out[c * npix + static_cast<size_t>(y) * w + x] = sum * inv;
      }
}

void upload_target(const Image& photo, int downscale, std::vector<float>& planar, DeviceBuffer& dst) {
  if (downscale > 1) {
    const size_t npix = static_cast<size_t>(std::max(1, photo.width / downscale)) *
                        static_cast<size_t>(std::max(1, photo.height / downscale));
    planar.resize(npix * 3);
    box_downscale_planar(photo, downscale, planar.data());
  } else {
    const size_t npix = static_cast<size_t>(photo.width) * photo.height;
    planar.resize(npix * 3);
    for (size_t p = 0; p < npix; ++p)
      for (int c = 0; c < 3; ++c) planar[c * npix + p] = photo.rgb[p * 3 + c];
  }
  dst.upload(planar);
}

void cap_opacity_logits(std::vector<float>& opacity_logit) {
  const float cap = std::log(0.01f / 0.99f);
  for (float& x : opacity_logit) x = std::min(x, cap);
}

double exp_decay_lr(double init, double final_value, double progress) {
  if (init <= 0) return 0;
  const double p = std::clamp(progress, 0.0, 1.0);
  return std::exp(std::log(init) * (1 - p) + std::log(final_value) * p);
}

}  // namespace ag2gs
