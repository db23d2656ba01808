#include "host/losses/mask_loss.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <map>
#include <stdexcept>
#include <string>

#include "host/device/kernel_call.h"

namespace ag2gs {

namespace {

std::map<std::string, std::string> mask_defines(int wg, int lanes) {
  char alpha_min[40];
  std::snprintf(alpha_min, sizeof alpha_min, "%.9ef", static_cast<double>(kMaskAlphaMin));
  return {{"WG", std::to_string(wg)}, {"LANES", std::to_string(lanes)}, {"MASK_ALPHA_MIN", alpha_min}};
}

void check_capacity(const DeviceBuffer& b, size_t bytes, const char* what) {
  if (b.capacity() < bytes)
    throw std::invalid_argument(std::string("mask loss: buffer '") + what + "' holds " + std::to_string(b.capacity()) +
                                " bytes, the image needs " + std::to_string(bytes) + "; upload the full image first");
}

constexpr const char* kKernels[] = {"mask_chunk_sums", "mask_means", "mask_chunk_abs", "mask_coef", "mask_grad"};

}  // namespace

MaskLoss::MaskLoss(Runtime& rt, MaskLossOptions options) : rt_(rt) {
  for (DeviceBuffer* b : {&labels_, &pixels_, &chunk_table_, &mask_chunks_, &sums_, &means_, &stats_, &abs_, &coef_,
                          &terms_, &host_f_, &host_a_, &host_gf_, &host_ga_})
    b->bind(&rt_);
  const LaunchShape shape =
      choose_launch_shape(rt_, "mask loss", options.work_group, options.lanes, [&](int wg, int lanes) {
        size_t limit = ~size_t(0);
        for (const char* name : kKernels) {
          cl::Kernel k = rt_.kernel("mask_loss.cl", name, mask_defines(wg, lanes));
          limit = std::min(limit, k.getWorkGroupInfo<CL_KERNEL_WORK_GROUP_SIZE>(rt_.info().device));
        }
        return limit;
      });
  wg_ = shape.work_group;
  lanes_ = shape.lanes;
}

ViewMasks with_unmasked_group(const ViewMasks& masks) {
  ViewMasks out = masks;
  const size_t npix = static_cast<size_t>(masks.width) * masks.height;
  if (npix == 0 || masks.layers < 1 || masks.labels.size() != npix * masks.layers) return out;
  int64_t n = 0;
  for (size_t p = 0; p < npix; ++p) {
    bool covered = false;
    for (int l = 0; l < masks.layers && !covered; ++l) covered = masks.labels[static_cast<size_t>(l) * npix + p] >= 0;
    if (!covered) {
      out.labels[p] = masks.count;
      ++n;
    }
  }
  if (n == 0) return masks;
  ++out.count;
  out.pixels.push_back(n);
  if (out.feature_dim > 0) out.features.resize(out.features.size() + out.feature_dim, 0.f);
  return out;
}

bool MaskLoss::set_masks(const ViewMasks& masks, int64_t key) {
  if (key >= 0 && loaded_ && key == key_) return false;
  const int w = masks.width, h = masks.height, layers = masks.layers, count = masks.count;
  if (w <= 0 || h <= 0 || layers < 0 || count < 0)
    throw std::invalid_argument("mask loss: masks of size " + std::to_string(w) + "x" + std::to_string(h) + ", " +
                                std::to_string(layers) + " layers and " + std::to_string(count) +
                                " masks; the size must be positive");
  const size_t npix = static_cast<size_t>(w) * h;
  if (masks.labels.size() != npix * layers)
    throw std::invalid_argument("mask loss: the label maps hold " + std::to_string(masks.labels.size()) +
                                " values, expected layers x H x W = " + std::to_string(layers) + "x" +
                                std::to_string(h) + "x" + std::to_string(w));
  if (npix * std::max(layers, 1) > static_cast<size_t>(INT32_MAX))
    throw std::invalid_argument("mask loss: label maps of " + std::to_string(npix) + " pixels x " +
                                std::to_string(layers) + " layers exceed 2^31 entries; train at a lower resolution");
  // Per-mask pixel lists (ascending pixels; a pixel once per mask), by a
  // counting sort over the labels.
  std::vector<int> sizes(count + 1, 0);
  auto mask_at = [&](size_t p, int layer) -> int {
    const int j = masks.labels[static_cast<size_t>(layer) * npix + p];
    if (j < -1 || j >= count)
      throw std::invalid_argument("mask loss: label " + std::to_string(j) + " at pixel " + std::to_string(p) +
                                  " of layer " + std::to_string(layer) + " is outside -1.." +
                                  std::to_string(count - 1));
    if (j < 0) return -1;
    for (int b = 0; b < layer; ++b)
      if (masks.labels[static_cast<size_t>(b) * npix + p] == j) return -1;  // already counted
    return j;
  };
  for (size_t p = 0; p < npix; ++p)
    for (int a = 0; a < layers; ++a)
      if (int j = mask_at(p, a); j >= 0) ++sizes[j + 1];
  std::vector<int> begin(count + 1, 0);
  for (int j = 0; j < count; ++j) begin[j + 1] = begin[j] + sizes[j + 1];
  std::vector<int> pixels(begin[count]), fill(begin.begin(), begin.end() - 1);
  for (size_t p = 0; p < npix; ++p)
    for (int a = 0; a < layers; ++a)
      if (int j = mask_at(p, a); j >= 0) pixels[fill[j]++] = static_cast<int>(p);
  // Chunks of at most chunk() entries, never spanning two masks.
  std::vector<int> chunk_table, mask_chunks(count + 1, 0);
  const int c = chunk();
  for (int j = 0; j < count; ++j) {
    mask_chunks[j] = static_cast<int>(chunk_table.size() / 4);
    for (int b = begin[j]; b < begin[j + 1]; b += c) {
      chunk_table.insert(chunk_table.end(), {j, b, std::min(b + c, begin[j + 1]), 0});
    }
  }
  mask_chunks[count] = static_cast<int>(chunk_table.size() / 4);

  labels_.upload(masks.labels);
  pixels_.upload(pixels);
  chunk_table_.upload(chunk_table);
  mask_chunks_.upload(mask_chunks);
  width_ = w;
  height_ = h;
  layers_ = layers;
  count_ = count;
  chunks_ = mask_chunks[count];
  entries_ = static_cast<int>(pixels.size());
  key_ = key;
  loaded_ = true;
  return true;
}

void MaskLoss::enqueue(const DeviceBuffer& feature, const DeviceBuffer* alpha, int width, int height,
                       ImageLayout layout, float w_is, float w_ic, DeviceBuffer* grad_feature,
                       DeviceBuffer* grad_alpha) {
  if (!loaded_) throw std::logic_error("MaskLoss: forward_backward() or enqueue() before set_masks()");
  if (width != width_ || height != height_)
    throw std::invalid_argument("mask loss: the feature map is " + std::to_string(width) + "x" +
                                std::to_string(height) + " but the masks set last are " + std::to_string(width_) + "x" +
                                std::to_string(height_) + "; call set_masks() for this view");
  if (!std::isfinite(w_is) || !std::isfinite(w_ic))
    throw std::invalid_argument("mask loss: the loss weights must be finite");
  const size_t npix = static_cast<size_t>(width) * height;
  check_capacity(feature, npix * 3 * sizeof(float), "feature");
  if (alpha) check_capacity(*alpha, npix * sizeof(float), "alpha");
  for (const DeviceBuffer* out :
       {static_cast<const DeviceBuffer*>(grad_feature), static_cast<const DeviceBuffer*>(grad_alpha)})
    if (out && (out == &feature || out == alpha))
      throw std::invalid_argument("mask loss: the gradient buffers must differ from the input buffers");
  if (grad_feature && grad_feature == grad_alpha)
    throw std::invalid_argument("mask loss: grad_feature and grad_alpha must be different buffers");

  const int planar = layout == ImageLayout::kPlanar ? 1 : 0;
  const int has_alpha = alpha ? 1 : 0;
  const int n = static_cast<int>(npix);
  const DeviceBuffer& a = alpha ? *alpha : stats_;  // never read without alpha
  const size_t masks = std::max(count_, 1);
  const size_t chunks = std::max(chunks_, 1);
  sums_.reserve(chunks * 4 * sizeof(float));
  abs_.reserve(chunks * 4 * sizeof(float));
  means_.reserve(masks * 4 * sizeof(float));
  coef_.reserve(masks * 4 * sizeof(float));
  terms_.reserve(masks * 2 * sizeof(float));
  stats_.reserve(2 * sizeof(int));

  const auto defs = mask_defines(wg_, lanes_);
  const cl::NDRange local(wg_);
  const size_t f4 = sizeof(float), i4 = sizeof(int);
  const size_t mask_bytes = static_cast<size_t>(count_) * 4 * f4, chunk_bytes = static_cast<size_t>(chunks_) * 4 * f4;
  // Passes 1 and 3 gather the same mask pixels.
  auto gather_call = [&](cl::Kernel& k) {
    KernelCall call(k);
    call.arg("planar", planar)
        .arg("has_alpha", has_alpha)
        .arg("npix", n)
        .buffer("feature", feature, npix * 3 * f4)
        .buffer("alpha", a, alpha ? npix * f4 : 0)
        .buffer("pixels", pixels_, static_cast<size_t>(entries_) * i4)
        .buffer("chunks", chunk_table_, static_cast<size_t>(chunks_) * 4 * i4);
    return call;
  };
  if (chunks_ > 0) {
    cl::Kernel k = rt_.kernel("mask_loss.cl", "mask_chunk_sums", defs);
    gather_call(k).buffer("partials", sums_, chunk_bytes).done();
    rt_.launch("mask_chunk_sums", k, cl::NDRange(static_cast<size_t>(chunks_) * wg_), local);
  }
  {
    cl::Kernel k = rt_.kernel("mask_loss.cl", "mask_means", defs);
    KernelCall(k)
        .arg("masks", count_)
        .buffer("mask_chunks", mask_chunks_, (static_cast<size_t>(count_) + 1) * i4)
        .buffer("partials", sums_, chunk_bytes)
        .buffer("means", means_, mask_bytes)
        .buffer("stats", stats_, 2 * i4)
        .done();
    rt_.launch("mask_means", k, local, local);
  }
  if (chunks_ > 0) {
    cl::Kernel k = rt_.kernel("mask_loss.cl", "mask_chunk_abs", defs);
    gather_call(k).buffer("means", means_, mask_bytes).buffer("partials", abs_, chunk_bytes).done();
    rt_.launch("mask_chunk_abs", k, cl::NDRange(static_cast<size_t>(chunks_) * wg_), local);
  }
  if (count_ > 0) {
    cl::Kernel k = rt_.kernel("mask_loss.cl", "mask_coef", defs);
    KernelCall(k)
        .arg("masks", count_)
        .arg("w_is", w_is)
        .arg("w_ic", w_ic)
        .buffer("mask_chunks", mask_chunks_, (static_cast<size_t>(count_) + 1) * i4)
        .buffer("partials", abs_, chunk_bytes)
        .buffer("means", means_, mask_bytes)
        .buffer("stats", stats_, 2 * i4)
        .buffer("coef", coef_, mask_bytes)
        .buffer("terms", terms_, static_cast<size_t>(count_) * 2 * f4)
        .done();
    rt_.launch("mask_coef", k, cl::NDRange(count_), local);
  }
  if (grad_feature || grad_alpha) {
    // Both outputs are written by one kernel; a missing one gets a scratch.
    DeviceBuffer* gf = grad_feature ? grad_feature : &host_gf_;
    gf->reserve(npix * 3 * sizeof(float));
    if (grad_alpha) grad_alpha->reserve(npix * sizeof(float));
    const int want_alpha_grad = grad_alpha ? 1 : 0;
    DeviceBuffer& ga = grad_alpha ? *grad_alpha : terms_;  // never written without grad_alpha
    cl::Kernel k = rt_.kernel("mask_loss.cl", "mask_grad", defs);
    KernelCall(k)
        .arg("layers", layers_)
        .arg("npix", n)
        .arg("planar", planar)
        .arg("has_alpha", has_alpha)
        .arg("want_alpha_grad", want_alpha_grad)
        .arg("w_is", w_is)
        .buffer("feature", feature, npix * 3 * f4)
        .buffer("alpha", a, alpha ? npix * f4 : 0)
        .buffer("labels", labels_, static_cast<size_t>(layers_) * npix * i4)
        .buffer("means", means_, mask_bytes)
        .buffer("coef", coef_, mask_bytes)
        .buffer("stats", stats_, 2 * i4)
        .buffer("grad_feature", *gf, npix * 3 * f4)
        .buffer("grad_alpha", ga, grad_alpha ? npix * f4 : 0)
        .done();
    const size_t items = (npix + lanes_ - 1) / lanes_;
    rt_.launch("mask_grad", k, cl::NDRange(items), local);
  }

  enqueued_ = true;
  enqueued_count_ = count_;
}

MaskLossResult MaskLoss::result() {
  if (!enqueued_) throw std::logic_error("MaskLoss::result() before enqueue()");
  // The losses: per-mask terms summed on the host in double, in mask order.
  const int count = enqueued_count_;
  std::vector<int> stats;
  stats_.download(stats, 2);
  MaskLossResult r;
  r.masks = stats[0];
  r.mask_pixels = stats[1];
  if (count > 0 && r.mask_pixels > 0) {
    std::vector<float> terms;
    terms_.download(terms, static_cast<size_t>(count) * 2);
    double is = 0, ic = 0;
    for (int j = 0; j < count; ++j) {
      is += terms[2 * j];
      ic += terms[2 * j + 1];
    }
    r.l_is = is / static_cast<double>(r.mask_pixels);
    if (r.masks >= 2) r.l_ic = ic / (static_cast<double>(r.masks) * (r.masks - 1));
  }
  return r;
}

MaskLossResult MaskLoss::forward_backward(const DeviceBuffer& feature, const DeviceBuffer* alpha, int width, int height,
                                          ImageLayout layout, float w_is, float w_ic, DeviceBuffer* grad_feature,
                                          DeviceBuffer* grad_alpha) {
  enqueue(feature, alpha, width, height, layout, w_is, w_ic, grad_feature, grad_alpha);
  return result();
}

MaskLossResult MaskLoss::forward_backward(const std::vector<float>& feature, const std::vector<float>* alpha, int width,
                                          int height, float w_is, float w_ic, std::vector<float>* grad_feature,
                                          std::vector<float>* grad_alpha, ImageLayout layout) {
  const size_t npix = static_cast<size_t>(std::max(width, 0)) * std::max(height, 0);
  if (feature.size() != npix * 3)
    throw std::invalid_argument("mask loss: the feature map has " + std::to_string(feature.size()) +
                                " values, expected " + std::to_string(npix * 3) + " (" + std::to_string(height) + "x" +
                                std::to_string(width) + "x3)");
  if (alpha && alpha->size() != npix)
    throw std::invalid_argument("mask loss: alpha has " + std::to_string(alpha->size()) + " values, expected " +
                                std::to_string(npix));
  host_f_.upload(feature);
  if (alpha) host_a_.upload(*alpha);
  MaskLossResult r = forward_backward(host_f_, alpha ? &host_a_ : nullptr, width, height, layout, w_is, w_ic,
                                      grad_feature ? &host_gf_ : nullptr, grad_alpha ? &host_ga_ : nullptr);
  if (grad_feature) host_gf_.download(*grad_feature, npix * 3);
  if (grad_alpha) host_ga_.download(*grad_alpha, npix);
  return r;
}

}  // namespace ag2gs
