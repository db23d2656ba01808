#include "host/losses/image_loss.h"

#include <algorithm>
#include <cstdio>
#include <map>
#include <stdexcept>
#include <string>

#include "host/device/kernel_call.h"

namespace ag2gs {

namespace {

constexpr int kRadius = 5;
constexpr double kSigma = 1.5;
constexpr double kC1 = 0.01 * 0.01, kC2 = 0.03 * 0.03;
constexpr int kBlurPlanes = 15;  // (x, y, xx, yy, xy) x channel
constexpr int kCoefPlanes = 9;   // (dS/dmx, dS/dExx, dS/dExy) x channel

std::string float_literal(double v) {
  char buf[40];
  std::snprintf(buf, sizeof buf, "%.9ef", v);
  return buf;
}

std::map<std::string, std::string> loss_defines(int wg, int lanes) {
  std::map<std::string, std::string> d{{"WG", std::to_string(wg)},
                                       {"LANES", std::to_string(lanes)},
                                       {"SSIM_C1", float_literal(kC1)},
                                       {"SSIM_C2", float_literal(kC2)}};
  const std::vector<double> g = ImageLoss::window();
  for (int k = 0; k <= kRadius; ++k) d["GW" + std::to_string(k)] = float_literal(g[kRadius + k]);
  return d;
}

void check_capacity(const DeviceBuffer& b, size_t bytes, const char* what) {
  if (b.capacity() < bytes)
    throw std::invalid_argument(std::string("image loss: buffer '") + what + "' holds " + std::to_string(b.capacity()) +
                                " bytes, the image needs " + std::to_string(bytes) + "; upload the full image first");
}

}  // namespace

double psnr_from_mse(double mse) {
  return mse > 0 ? 10.0 * std::log10(1.0 / mse) : std::numeric_limits<double>::infinity();
}

double ImageLossResult::psnr() const {
  return psnr_from_mse(mse);
}

std::vector<double> ImageLoss::window() {
  std::vector<double> g(2 * kRadius + 1);
  double sum = 0;
  for (int t = -kRadius; t <= kRadius; ++t) sum += g[t + kRadius] = std::exp(-t * t / (2 * kSigma * kSigma));
  for (double& v : g) v /= sum;
  return g;
}

ImageLoss::ImageLoss(Runtime& rt, ImageLossOptions options) : rt_(rt) {
  for (DeviceBuffer* b : {&blur_, &coef_, &partials_, &norm_, &host_x_, &host_y_, &host_w_, &host_grad_}) b->bind(&rt_);
  const LaunchShape shape =
      choose_launch_shape(rt_, "image loss", options.work_group, options.lanes, [&](int wg, int lanes) {
        size_t limit = ~size_t(0);
        for (const char* name : {"ssim_blur_h", "ssim_map", "loss_norm", "coef_blur_h", "image_loss_grad"}) {
          cl::Kernel k = rt_.kernel("image_loss.cl", name, loss_defines(wg, lanes));
          limit = std::min(limit, k.getWorkGroupInfo<CL_KERNEL_WORK_GROUP_SIZE>(rt_.info().device));
        }
        return limit;
      });
  wg_ = shape.work_group;
  lanes_ = shape.lanes;
}

void ImageLoss::enqueue(const DeviceBuffer& rendered, const DeviceBuffer& target, int width, int height, float lambda,
                        DeviceBuffer* grad_out, const DeviceBuffer* weights, ImageLayout layout) {
  if (width <= 0 || height <= 0)
    throw std::invalid_argument("image loss: image size " + std::to_string(width) + "x" + std::to_string(height) +
                                " must be positive");
  if (!(lambda >= 0.f && lambda <= 1.f))
    throw std::invalid_argument("image loss: lambda (the SSIM weight) must lie in [0, 1], got " +
                                std::to_string(lambda));
  const size_t npix = static_cast<size_t>(width) * height;
  if (npix * kBlurPlanes * sizeof(float) > rt_.info().max_alloc)
    throw std::invalid_argument("image loss: a " + std::to_string(width) + "x" + std::to_string(height) +
                                " image needs more scratch memory than one device allocation allows; "
                                "train at a lower resolution (-r)");
  check_capacity(rendered, npix * 3 * sizeof(float), "rendered");
  check_capacity(target, npix * 3 * sizeof(float), "target");
  if (weights) check_capacity(*weights, npix * sizeof(float), "weights");
  if (grad_out && (grad_out == &rendered || grad_out == &target || grad_out == weights))
    throw std::invalid_argument("image loss: the gradient buffer must differ from the input buffers");

  const bool want_grad = grad_out != nullptr;
  const int planar = layout == ImageLayout::kPlanar ? 1 : 0;
  const int has_weights = weights ? 1 : 0;
  // One work-item per segment of `lanes_` pixels of a row.
  const size_t items = static_cast<size_t>(height) * ((width + lanes_ - 1) / lanes_);
  groups_ = static_cast<int>((items + wg_ - 1) / wg_);
  lambda_ = lambda;
  blur_.reserve(npix * kBlurPlanes * sizeof(float));
  coef_.reserve(want_grad ? npix * kCoefPlanes * sizeof(float) : 4);
  partials_.reserve(static_cast<size_t>(groups_) * 4 * sizeof(float));
  norm_.reserve(sizeof(float));
  const DeviceBuffer& w = weights ? *weights : norm_;  // never read without weights

  const auto defs = loss_defines(wg_, lanes_);
  const cl::NDRange global(items), local(wg_);
  cl::Kernel blur_h = rt_.kernel("image_loss.cl", "ssim_blur_h", defs);
  const size_t f4 = sizeof(float);
  KernelCall(blur_h)
      .arg("width", width)
      .arg("height", height)
      .arg("planar", planar)
      .buffer("x", rendered, npix * 3 * f4)
      .buffer("y", target, npix * 3 * f4)
      .buffer("h", blur_, npix * kBlurPlanes * f4)
      .done();
  rt_.launch("loss_blur_h", blur_h, global, local);
  cl::Kernel map = rt_.kernel("image_loss.cl", "ssim_map", defs);
  KernelCall(map)
      .arg("width", width)
      .arg("height", height)
      .arg("planar", planar)
      .arg("lambda", lambda)
      .arg("want_grad", want_grad ? 1 : 0)
      .arg("has_weights", has_weights)
      .buffer("x", rendered, npix * 3 * f4)
      .buffer("y", target, npix * 3 * f4)
      .buffer("h", blur_, npix * kBlurPlanes * f4)
      .buffer("weights", w, weights ? npix * f4 : 0)
      .buffer("coef", coef_, want_grad ? npix * kCoefPlanes * f4 : 0)
      .buffer("partials", partials_, static_cast<size_t>(groups_) * 4 * f4)
      .done();
  rt_.launch("loss_map", map, global, local);
  if (!want_grad) return;

  grad_out->reserve(npix * 3 * sizeof(float));
  cl::Kernel norm = rt_.kernel("image_loss.cl", "loss_norm", defs);
  set_kernel_args(norm, groups_, partials_, norm_);
  rt_.launch("loss_norm", norm, local, local);
  // The forward blurs are consumed: the backward blurs reuse their buffer.
  cl::Kernel coef_h = rt_.kernel("image_loss.cl", "coef_blur_h", defs);
  set_kernel_args(coef_h, width, height, coef_, blur_);
  rt_.launch("loss_coef_blur_h", coef_h, global, local);
  cl::Kernel grad = rt_.kernel("image_loss.cl", "image_loss_grad", defs);
  KernelCall(grad)
      .arg("width", width)
      .arg("height", height)
      .arg("planar", planar)
      .arg("lambda", lambda)
      .arg("has_weights", has_weights)
      .buffer("x", rendered, npix * 3 * f4)
      .buffer("y", target, npix * 3 * f4)
      .buffer("weights", w, weights ? npix * f4 : 0)
      .buffer("hc", blur_, npix * kCoefPlanes * f4)
      .buffer("norm", norm_, f4)
      .buffer("grad", *grad_out, npix * 3 * f4)
      .done();
  rt_.launch("loss_grad", grad, global, local);
}

ImageLossResult ImageLoss::result() {
  if (groups_ == 0) throw std::logic_error("ImageLoss::result() before enqueue()");
  std::vector<float> part;
  partials_.download(part, static_cast<size_t>(groups_) * 4);
  double s[4] = {0, 0, 0, 0};
  for (int g = 0; g < groups_; ++g)
    for (int k = 0; k < 4; ++k) s[k] += part[4 * g + k];
  ImageLossResult r;
  if (s[3] > 0 || std::isnan(s[3])) {
    const double n = 3 * s[3];
    r.l1 = s[0] / n;
    r.ssim = s[1] / n;
    r.mse = s[2] / n;
  }
  r.loss = (1.0 - lambda_) * r.l1 + lambda_ * (1.0 - r.ssim);
  return r;
}

ImageLossResult ImageLoss::forward_backward(const DeviceBuffer& rendered, const DeviceBuffer& target, int width,
                                            int height, float lambda, DeviceBuffer* grad_out,
                                            const DeviceBuffer* weights, ImageLayout layout) {
  enqueue(rendered, target, width, height, lambda, grad_out, weights, layout);
  return result();
}

ImageLossResult ImageLoss::forward_backward(const std::vector<float>& rendered, const std::vector<float>& target,
                                            int width, int height, float lambda, std::vector<float>* grad_out,
                                            const std::vector<float>* weights) {
  if (width <= 0 || height <= 0)
    throw std::invalid_argument("image loss: image size " + std::to_string(width) + "x" + std::to_string(height) +
                                " must be positive");
  const size_t npix = static_cast<size_t>(width) * height;
  auto check = [&](const std::vector<float>& v, size_t want, const char* what) {
    if (v.size() != want)
      throw std::invalid_argument(std::string("image loss: '") + what + "' has " + std::to_string(v.size()) +
                                  " values, expected " + std::to_string(want) + " (" + std::to_string(height) + "x" +
                                  std::to_string(width) + (want == npix ? ")" : "x3)"));
  };
  check(rendered, npix * 3, "rendered");
  check(target, npix * 3, "target");
  if (weights) check(*weights, npix, "weights");
  host_x_.upload(rendered);
  host_y_.upload(target);
  if (weights) host_w_.upload(*weights);
  enqueue(host_x_, host_y_, width, height, lambda, grad_out ? &host_grad_ : nullptr, weights ? &host_w_ : nullptr);
  ImageLossResult r = result();
  if (grad_out) host_grad_.download(*grad_out, npix * 3);
  return r;
}

}  // namespace ag2gs
