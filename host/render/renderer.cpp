#include "host/render/renderer.h"

#include <spdlog/spdlog.h>

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <stdexcept>

#include "host/device/kernel_call.h"
#include "host/render/gaussian_buffers.h"
#include "kernels/layout.h"

namespace ag2gs {

namespace {

constexpr int kTile = TILE;
constexpr int kScanBlock = 1024;
// Gaussians per work-item of visible_flags in the CPU layout.
constexpr int kVisibleChunk = 256;
constexpr int kScanWg = 256;  // the GPU scan's work-group (bin.cl)

size_t ceil_div(size_t a, size_t b) {
  return (a + b - 1) / b;
}

// The bits a radix sort of keys in [0, range] needs (0: all keys equal).
int key_bits(cl_uint range) {
  int bits = 0;
  while (bits < 32 && (range >> bits) != 0u) ++bits;
  return bits;
}

// [H,W,C] -> [C,H,W]
std::vector<float> to_planar(const std::vector<float>& hwc, size_t npix, int c) {
  std::vector<float> out(npix * c);
  for (size_t p = 0; p < npix; ++p)
    for (int k = 0; k < c; ++k) out[k * npix + p] = hwc[p * c + k];
  return out;
}
std::vector<float> to_interleaved(const std::vector<float>& chw, size_t npix, int c) {
  std::vector<float> out(npix * c);
  for (size_t p = 0; p < npix; ++p)
    for (int k = 0; k < c; ++k) out[p * c + k] = chw[k * npix + p];
  return out;
}

}  // namespace

DeviceGaussians::DeviceGaussians(Runtime& rt)
    : means(&rt), scales(&rt), quats(&rt), opacities(&rt), sh(&rt), features(&rt) {}

void DeviceGaussians::upload(const GaussianSet& set) {
  set.validate();
  n = set.size();
  sh_degree = set.sh_degree;
  means.upload(set.means);
  scales.upload(set.scales);
  quats.upload(set.quats);
  opacities.upload(set.opacities);
  sh.upload(set.sh);
  features.upload(set.features);
}

Renderer::Renderer(Runtime& rt)
    : rt_(rt),
      sort_(rt),
      staged_(blend_staging_for(rt.info())),
      bwd_plan_(staged_ ? blend_bwd_plan_for(rt.info()) : BlendBwdPlan{}),
      cpu_bwd_vector_width_(staged_ ? 0 : cpu_blend_bwd_vector_width(rt.info())) {
  for (DeviceBuffer* b :
       {&cam_buf_,       &records_,    &rects_,          &tile_counts_,   &depth_keys_,  &radii_,      &order_keys_tmp_,
        &order_keys_,    &order_vals_, &order_vals_tmp_, &counts_sorted_, &offsets_,     &block_sums_, &tile_keys_,
        &tile_keys_tmp_, &isect_vals_, &isect_vals_tmp_, &isect_gid_,     &isect_start_, &ranges_,     &key_range_,
        &out_rgb_,       &out_feat_,   &out_depth_,      &out_alpha_,     &out_dist_,    &out_aux_,    &out_last_,
        &out_count_,     &g_rgb_,      &g_feat_,         &g_depth_,       &g_alpha_,     &g_dist_,     &isect_grads_,
        &v_means_,       &v_scales_,   &v_quats_,        &v_opacities_,   &v_sh_,        &v_features_, &v_means2d_,
        &isect_weights_, &weight_sums_})
    b->bind(&rt_);
}

void Renderer::reserve_each(size_t items, std::initializer_list<SizedBuffer> buffers) {
  for (const SizedBuffer& b : buffers) b.buffer->reserve(items * b.bytes_per_item);
}

int Renderer::visible_chunk() const {
  return staged_ ? 1 : kVisibleChunk;
}

std::map<std::string, std::string> Renderer::bin_defines() const {
  // The one-launch scan takes the sort plan's work-group: few work-items
  // with many values each under a simulator, which pays every barrier work-item
  // by work-item.
  const int one_wg = sort_.plan().kind == RadixSortPlan::Kind::Group ? sort_.plan().work_group : kScanWg;
  return {{"VISIBLE_CHUNK", std::to_string(visible_chunk())},
          {"SCAN_BLOCK", std::to_string(kScanBlock)},
          {"SCAN_WG", std::to_string(kScanWg)},
          {"SCAN_ONE_WG", std::to_string(one_wg)}};
}

std::vector<float> pack_camera(const Camera& cam, const RenderSettings& settings) {
  std::vector<float> cb(CAM_SIZE, 0.f);
  for (int i = 0; i < 9; ++i) cb[CAM_R + i] = static_cast<float>(cam.R(i / 3, i % 3));
  for (int i = 0; i < 3; ++i) cb[CAM_T + i] = static_cast<float>(cam.t[i]);
  cb[CAM_FX] = static_cast<float>(cam.fx);
  cb[CAM_FY] = static_cast<float>(cam.fy);
  cb[CAM_CX] = static_cast<float>(cam.cx);
  cb[CAM_CY] = static_cast<float>(cam.cy);
  cb[CAM_W] = static_cast<float>(cam.width);
  cb[CAM_H] = static_cast<float>(cam.height);
  cb[CAM_NEAR] = settings.near_plane;
  const Eigen::Vector3d c = cam.center();
  for (int i = 0; i < 3; ++i) cb[CAM_POS + i] = static_cast<float>(c[i]);
  cb[CAM_DNEAR] = settings.dist_near;
  cb[CAM_DFAR] = settings.dist_far;
  for (int i = 0; i < 3; ++i) cb[CAM_BG + i] = settings.background[i];
  cb[CAM_LOWPASS] = settings.lowpass;
  return cb;
}

std::vector<Renderer::PixelContribution> Renderer::pixel_contributions(int x, int y) const {
  if (!have_frame_) throw std::logic_error("Renderer::pixel_contributions() before forward()");
  if (x < 0 || y < 0 || x >= cam_.width || y >= cam_.height)
    throw std::out_of_range("Renderer::pixel_contributions: pixel outside the image");
  std::vector<PixelContribution> out;
  const size_t M = stats_.n_intersections;
  if (M == 0 || gaussians_->n == 0) return out;
  const int tile = (y / kTile) * tiles_x_ + x / kTile;
  std::vector<int32_t> ranges;
  ranges_.download(ranges, static_cast<size_t>(tile + 1) * 2);
  const int begin = ranges[2 * tile], end = ranges[2 * tile + 1];
  if (end <= begin) return out;
  std::vector<uint32_t> vals, gid;
  std::vector<float> rec;
  sorted_isect_vals_->download(vals, static_cast<size_t>(end));
  isect_gid_.download(gid, M);
  records_.download(rec, gaussians_->n * REC_SIZE);
  const float px = x + 0.5f, py = y + 0.5f;
  float T = 1.f;
  for (int j = begin; j < end; ++j) {
    const uint32_t g = gid[vals[j]];
    const float* q = &rec[static_cast<size_t>(g) * REC_SIZE];
    const float dx = q[REC_U] - px, dy = q[REC_V] - py;
    const float sigma = 0.5f * (q[REC_CA] * dx * dx + q[REC_CC] * dy * dy) + q[REC_CB] * dx * dy;
    const float alpha = std::min(ALPHA_MAX, q[REC_OPACITY] * std::exp(-std::min(sigma, 40.f)));
    if (!(sigma >= 0.f) || !(alpha >= ALPHA_MIN)) continue;
    const float Tn = T * (1.f - alpha);
    if (Tn < T_MIN) break;
    out.push_back({g, alpha * T, q[REC_Z]});
    T = Tn;
  }
  return out;
}

void Renderer::bin(const DeviceGaussians& g, const Camera& cam, const RenderSettings& settings) {
  cam.validate();
  if (settings.sh_degree > 3) throw std::invalid_argument("render: SH degree must be 0..3");
  if (!(settings.near_plane > 0.f) || !(settings.dist_far > settings.dist_near) || !(settings.dist_near > 0.f))
    throw std::invalid_argument("render: near plane and distortion depth range must be positive and ordered");
  gaussians_ = &g;
  cam_ = cam;
  settings_ = settings;
  sh_active_ = settings.sh_degree < 0 ? g.sh_degree : std::min(settings.sh_degree, g.sh_degree);
  tiles_x_ = static_cast<int>(ceil_div(cam.width, kTile));
  tiles_y_ = static_cast<int>(ceil_div(cam.height, kTile));
  const size_t n = g.n;
  const int ni = static_cast<int>(n);
  const int ntiles = tiles_x_ * tiles_y_;
  stats_ = FrameStats{n, 0, cam.width, cam.height};
  visible_ = 0;

  cam_buf_.upload(pack_camera(cam, settings));

  const size_t nn = std::max<size_t>(n, 1);
  // Per Gaussian: bytes each.
  reserve_each(nn, {{&records_, REC_SIZE * 4},
                    {&rects_, 16},
                    {&tile_counts_, 4},
                    {&depth_keys_, 4},
                    {&radii_, 4},
                    {&order_keys_, 4},
                    {&order_keys_tmp_, 4},
                    {&order_vals_, 4},
                    {&order_vals_tmp_, 4},
                    {&counts_sorted_, 4},
                    {&offsets_, 4},
                    {&isect_start_, 4}});
  const int nscan = static_cast<int>(ceil_div(nn, kScanBlock));
  block_sums_.reserve((nscan + 1) * 4);

  std::map<std::string, std::string> pdef{{"SH_K", std::to_string(sh_coeffs_for_degree(g.sh_degree))},
                                          {"SH_ACTIVE", std::to_string(sh_active_)}};
  size_t M = 0;
  if (n > 0) {
    cl::Kernel project = rt_.kernel("project.cl", "project_fwd", pdef);
    const size_t f4 = sizeof(float);
    gaussian_buffers(KernelCall(project).arg("n", ni).buffer("cam", cam_buf_, CAM_SIZE * f4), g)
        .arg("tiles_x", tiles_x_)
        .arg("tiles_y", tiles_y_)
        .buffer("records", records_, n * REC_SIZE * f4)
        .buffer("rects", rects_, n * 4 * f4)
        .buffer("tile_counts", tile_counts_, n * 4)
        .buffer("depth_keys", depth_keys_, n * 4)
        .buffer("radii", radii_, n * 4)
        .done();
    rt_.launch("project", project, cl::NDRange(n), cl::NDRange(64));

    // Only the Gaussians on screen are sorted (in index order first, so the
    // stable sort orders them as it would among all; a culled one emits
    // nothing): a view that sees half of them sorts half.
    // {least, greatest} before the flags pass narrows them; a static
    // source, so the write need not block the queue.
    static const cl_uint kKeyRangeStart[2] = {0xFFFFFFFFu, 0u};
    key_range_.reserve(sizeof(kKeyRangeStart));
    AG2GS_CL_CHECK(
        rt_.queue().enqueueWriteBuffer(key_range_.get(), CL_FALSE, 0, sizeof(kKeyRangeStart), kKeyRangeStart));
    cl::Kernel flags = rt_.kernel("bin.cl", "visible_flags", bin_defines());
    set_kernel_args(flags, ni, tile_counts_, depth_keys_, counts_sorted_, key_range_);
    const size_t chunk = visible_chunk();
    rt_.launch("bin", flags, cl::NDRange(chunk > 1 ? ceil_div(n, chunk) : n), cl::NDRange(chunk > 1 ? 1 : 64));
    // Read back with the scan's total: the in-order queue has finished this
    // read when the scan's blocking one returns, so the frame waits once (a
    // member, so a read left pending by an error never writes a dead frame).
    cl_uint* range = key_range_host_;
    AG2GS_CL_CHECK(rt_.queue().enqueueReadBuffer(key_range_.get(), CL_FALSE, 0, sizeof(key_range_host_), range));
    const size_t visible = exclusive_scan(counts_sorted_, offsets_, n);
    visible_ = visible;
    if (visible > 0) {
      const int nv = static_cast<int>(visible);
      cl::Kernel compact = rt_.kernel("bin.cl", "compact_visible", bin_defines());
      set_kernel_args(compact, ni, tile_counts_, depth_keys_, offsets_, range[0], order_keys_, order_vals_);
      rt_.launch("bin", compact, cl::NDRange(n), cl::NDRange(64));
      // Depth order (stable: ties keep index order). The keys minus the
      // least span key_bits(range): a view whose depths lie within a factor
      // of two sorts 24 bits or fewer, and keys all equal need no sort.
      DeviceBuffer *keys = &order_keys_, *vals = &order_vals_, *ktmp = &order_keys_tmp_, *vtmp = &order_vals_tmp_;
      if (const int bits = key_bits(range[1] - range[0]); bits > 0) sort_.sort(keys, vals, ktmp, vtmp, visible, bits);
      sorted_order_ = vals;

      cl::Kernel gather = rt_.kernel("bin.cl", "gather_counts", bin_defines());
      set_kernel_args(gather, nv, *sorted_order_, tile_counts_, counts_sorted_);
      rt_.launch("bin", gather, cl::NDRange(visible), cl::NDRange(64));
      M = exclusive_scan(counts_sorted_, offsets_, visible);
    }
  }
  stats_.n_intersections = M;
  if (M > 0xF0000000ull)
    throw std::runtime_error("render: " + std::to_string(M) +
                             " tile intersections exceed the 32-bit index range; "
                             "render at a lower resolution (-r)");

  // Intersection buffers grow with the frame; nothing is dropped.
  const size_t mm = std::max<size_t>(M, 1);
  reserve_each(mm,
               {{&tile_keys_, 4}, {&tile_keys_tmp_, 4}, {&isect_vals_, 4}, {&isect_vals_tmp_, 4}, {&isect_gid_, 4}});
  ranges_.fill_zero(static_cast<size_t>(ntiles) * 8);
  sorted_tile_keys_ = &tile_keys_;
  sorted_isect_vals_ = &isect_vals_;
  if (M > 0) {
    cl::Kernel starts = rt_.kernel("bin.cl", "isect_starts", bin_defines());
    set_kernel_args(starts, static_cast<int>(visible_), *sorted_order_, offsets_, isect_start_);
    rt_.launch("bin", starts, cl::NDRange(visible_), cl::NDRange(64));
    cl::Kernel emit = rt_.kernel("bin.cl", "emit_isects", bin_defines());
    const size_t f4 = sizeof(float);
    KernelCall(emit)
        .arg("n", ni)
        .buffer("tile_counts", tile_counts_, n * 4)
        .buffer("rects", rects_, n * 4 * f4)
        .buffer("records", records_, n * REC_SIZE * f4)
        .buffer("isect_start", isect_start_, n * 4)
        .arg("tiles_x", tiles_x_)
        .buffer("tile_keys", tile_keys_, M * 4)
        .buffer("isect_vals", isect_vals_, M * 4)
        .buffer("isect_gid", isect_gid_, M * 4)
        .done();
    rt_.launch("bin", emit, cl::NDRange(n), cl::NDRange(64));
    int bits = 1;
    while ((1 << bits) < ntiles) ++bits;
    DeviceBuffer *keys = &tile_keys_, *vals = &isect_vals_, *ktmp = &tile_keys_tmp_, *vtmp = &isect_vals_tmp_;
    sort_.sort(keys, vals, ktmp, vtmp, M, bits);
    sorted_tile_keys_ = keys;
    sorted_isect_vals_ = vals;
    cl::Kernel tr = rt_.kernel("bin.cl", "tile_ranges", bin_defines());
    set_kernel_args(tr, static_cast<int>(M), *sorted_tile_keys_, ranges_);
    rt_.launch("bin", tr, cl::NDRange(M), cl::NDRange(64));
  }
  have_frame_ = true;
  have_images_ = false;
}

size_t Renderer::exclusive_scan(DeviceBuffer& in, DeviceBuffer& out, size_t n) {
  // GPUs scan with work-groups (the work-group sort's devices), CPUs with
  // one work-item per block: the same integer sums.
  const int ni = static_cast<int>(n);
  const int nscan = static_cast<int>(ceil_div(n, kScanBlock));
  const bool wg_scan = sort_.plan().kind == RadixSortPlan::Kind::Group;
  if (wg_scan && n <= sort_.one_launch_keys()) {  // a short scan: one work-group, one launch
    cl::Kernel one = rt_.kernel("bin.cl", "scan_one_group_wg", bin_defines());
    set_kernel_args(one, ni, in, out, block_sums_);
    const size_t wg = sort_.plan().work_group;
    rt_.launch("bin", one, cl::NDRange(wg), cl::NDRange(wg));
  } else {
    cl::Kernel sb = rt_.kernel("bin.cl", wg_scan ? "scan_blocks_wg" : "scan_blocks", bin_defines());
    set_kernel_args(sb, ni, in, out, block_sums_);
    if (wg_scan)
      rt_.launch("bin", sb, cl::NDRange(static_cast<size_t>(nscan) * kScanWg), cl::NDRange(kScanWg));
    else
      rt_.launch("bin", sb, cl::NDRange(nscan));
    cl::Kernel ss = rt_.kernel("bin.cl", wg_scan ? "scan_block_sums_wg" : "scan_block_sums", bin_defines());
    set_kernel_args(ss, nscan, block_sums_);
    if (wg_scan)
      rt_.launch("bin", ss, cl::NDRange(kScanWg), cl::NDRange(kScanWg));
    else
      rt_.launch("bin", ss, cl::NDRange(1), cl::NDRange(1));
    cl::Kernel sa = rt_.kernel("bin.cl", "scan_add", bin_defines());
    set_kernel_args(sa, ni, out, block_sums_);
    rt_.launch("bin", sa, cl::NDRange(n), cl::NDRange(64));
  }
  cl_uint total = 0;
  AG2GS_CL_CHECK(rt_.queue().enqueueReadBuffer(block_sums_.get(), CL_TRUE, nscan * 4, 4, &total));
  return total;
}

void Renderer::forward(const DeviceGaussians& g, const Camera& cam, const RenderSettings& settings) {
  bin(g, cam, settings);
  const size_t npix = static_cast<size_t>(cam.width) * cam.height;
  const int ntiles = tiles_x_ * tiles_y_;
  // Per pixel: the planes of kernels/blend_fwd.cl.
  reserve_each(npix, {{&out_rgb_, 12},
                      {&out_feat_, 12},
                      {&out_depth_, 4},
                      {&out_alpha_, 4},
                      {&out_dist_, 4},
                      {&out_aux_, 16},
                      {&out_last_, 4},
                      {&out_count_, 4}});
  const int wg = 256 / rt_.vector_width();
  // CPUs: no local-memory staging (records come from cache), see blend_fwd.cl.
  cl::Kernel blend = rt_.kernel("blend_fwd.cl", "blend_fwd",
                                {{"BATCH", std::to_string(std::max(64, wg))},
                                 {"NO_STAGING", staged_ ? "0" : "1"},
                                 {"WITH_FEAT", settings.features ? "1" : "0"}});
  const size_t M = stats_.n_intersections, f4 = sizeof(float);
  KernelCall(blend)
      .arg("width", cam.width)
      .arg("height", cam.height)
      .arg("tiles_x", tiles_x_)
      .buffer("cam", cam_buf_, CAM_SIZE * f4)
      .buffer("ranges", ranges_, static_cast<size_t>(ntiles) * 8)
      .buffer("isect_vals", *sorted_isect_vals_, M * 4)
      .buffer("isect_gid", isect_gid_, M * 4)
      .buffer("records", records_, gaussians_->n * REC_SIZE * f4)
      .buffer("out_rgb", out_rgb_, npix * 3 * f4)
      .buffer("out_feat", out_feat_, npix * 3 * f4)
      .buffer("out_depth", out_depth_, npix * f4)
      .buffer("out_alpha", out_alpha_, npix * f4)
      .buffer("out_dist", out_dist_, npix * f4)
      .buffer("out_aux", out_aux_, npix * 4 * f4)
      .buffer("out_last", out_last_, npix * 4)
      .buffer("out_count", out_count_, npix * 4)
      .done();
  // CPU layout: one work-item per tile (blend_fwd.cl).
  const size_t items = staged_ ? wg : 1;
  rt_.launch("blend_fwd", blend, cl::NDRange(static_cast<size_t>(ntiles) * items), cl::NDRange(items));
  have_images_ = true;
  frame_features_ = settings.features;
}

RenderOutput Renderer::download_output() {
  if (!have_images_) throw std::logic_error("download_output() before forward()");
  RenderOutput out;
  out.width = cam_.width;
  out.height = cam_.height;
  const size_t npix = static_cast<size_t>(cam_.width) * cam_.height;
  std::vector<float> tmp;
  out_rgb_.download(tmp, npix * 3);
  out.rgb = to_interleaved(tmp, npix, 3);
  out_feat_.download(tmp, npix * 3);
  out.feature = to_interleaved(tmp, npix, 3);
  out_depth_.download(out.depth, npix);
  out_alpha_.download(out.alpha, npix);
  out_dist_.download(out.distortion, npix);
  out_count_.download(out.n_contrib, npix);
  radii_.download(out.radii, gaussians_->n);
  return out;
}

void Renderer::upload_plane(DeviceBuffer& buf, const std::vector<float>& hwc, int channels, const char* what) {
  const size_t npix = static_cast<size_t>(cam_.width) * cam_.height;
  if (hwc.empty()) {
    buf.fill_zero(npix * channels * 4);
    return;
  }
  if (hwc.size() != npix * channels)
    throw std::invalid_argument(std::string("render_backward: gradient '") + what + "' has " +
                                std::to_string(hwc.size()) + " values, expected " + std::to_string(npix * channels) +
                                " (H*W*" + std::to_string(channels) + ")");
  buf.upload(channels == 1 ? hwc : to_planar(hwc, npix, channels));
}

void Renderer::backward(const OutputGrads& grads) {
  if (!have_images_) throw std::logic_error("backward() before forward()");
  upload_plane(g_rgb_, grads.rgb, 3, "rgb");
  upload_plane(g_feat_, grads.feature, 3, "feature");
  upload_plane(g_depth_, grads.depth, 1, "depth");
  upload_plane(g_alpha_, grads.alpha, 1, "alpha");
  upload_plane(g_dist_, grads.distortion, 1, "distortion");
  backward_from(g_rgb_, g_feat_, g_depth_, g_alpha_, g_dist_,
                {!grads.rgb.empty(), !grads.feature.empty(), !grads.depth.empty(), !grads.alpha.empty(),
                 !grads.distortion.empty()});
}

void Renderer::backward(const DeviceOutputGrads& grads) {
  if (!have_images_) throw std::logic_error("backward() before forward()");
  const size_t npix = static_cast<size_t>(cam_.width) * cam_.height;
  // A given buffer is used in place; a missing one is a zeroed internal plane.
  auto pick = [&](const DeviceBuffer* given, DeviceBuffer& zero, int channels,
                  const char* what) -> const DeviceBuffer& {
    const size_t bytes = npix * channels * sizeof(float);
    if (!given) {
      zero.fill_zero(bytes);
      return zero;
    }
    if (given->capacity() < bytes)
      throw std::invalid_argument(std::string("render backward: device gradient '") + what + "' holds " +
                                  std::to_string(given->capacity()) + " bytes, the frame needs " +
                                  std::to_string(bytes));
    return *given;
  };
  backward_from(pick(grads.rgb, g_rgb_, 3, "rgb"), pick(grads.feature, g_feat_, 3, "feature"),
                pick(grads.depth, g_depth_, 1, "depth"), pick(grads.alpha, g_alpha_, 1, "alpha"),
                pick(grads.distortion, g_dist_, 1, "distortion"),
                {grads.rgb != nullptr, grads.feature != nullptr, grads.depth != nullptr, grads.alpha != nullptr,
                 grads.distortion != nullptr});
}

void Renderer::backward_from(const DeviceBuffer& g_rgb, const DeviceBuffer& g_feat, const DeviceBuffer& g_depth,
                             const DeviceBuffer& g_alpha, const DeviceBuffer& g_dist,
                             const GradsPresent& present) {
  if (present.feature && !frame_features_)
    throw std::logic_error(
        "render backward: a feature gradient for a frame rendered without features "
        "(RenderSettings::features false)");
  auto flag = [](bool b) { return std::string(b ? "1" : "0"); };
  std::map<std::string, std::string> defs{{"GRAD_RGB", flag(present.rgb)},
                                          {"GRAD_FEAT", flag(present.feature)},
                                          {"GRAD_DEPTH", flag(present.depth)},
                                          {"GRAD_ALPHA", flag(present.alpha)},
                                          {"GRAD_DIST", flag(present.distortion)}};
  const cl::NDRange local = blend_bwd_layout(defs);
  isect_grads_.reserve(std::max<size_t>(stats_.n_intersections, 1) * G2_SIZE * 4);
  cl::Kernel blend = rt_.kernel("blend_bwd.cl", "blend_bwd", defs);
  // An upstream gradient that is not present is not read (its term is
  // compiled out): any buffer will do there.
  const size_t npix = static_cast<size_t>(cam_.width) * cam_.height, M = stats_.n_intersections, f4 = sizeof(float);
  auto plane = [&](bool present, size_t channels) { return present ? npix * channels * f4 : 0; };
  KernelCall(blend)
      .arg("width", cam_.width)
      .arg("height", cam_.height)
      .arg("tiles_x", tiles_x_)
      .buffer("cam", cam_buf_, CAM_SIZE * f4)
      .buffer("ranges", ranges_, static_cast<size_t>(tiles_x_) * tiles_y_ * 8)
      .buffer("isect_vals", *sorted_isect_vals_, M * 4)
      .buffer("isect_gid", isect_gid_, M * 4)
      .buffer("records", records_, gaussians_->n * REC_SIZE * f4)
      .buffer("out_rgb", out_rgb_, npix * 3 * f4)
      .buffer("out_feat", out_feat_, npix * 3 * f4)
      .buffer("out_depth", out_depth_, npix * f4)
      .buffer("out_aux", out_aux_, npix * 4 * f4)
      .buffer("out_last", out_last_, npix * 4)
      .buffer("v_rgb", g_rgb, plane(present.rgb, 3))
      .buffer("v_feat", g_feat, plane(present.feature, 3))
      .buffer("v_depth", g_depth, plane(present.depth, 1))
      .buffer("v_alpha", g_alpha, plane(present.alpha, 1))
      .buffer("v_dist", g_dist, plane(present.distortion, 1))
      .buffer("isect_grads", isect_grads_, M * G2_SIZE * f4)
      .done();
  rt_.launch("blend_bwd", blend, cl::NDRange(static_cast<size_t>(tiles_x_) * tiles_y_ * local[0]), local);
  project_backward();
}

void Renderer::blend_weights(const std::vector<float>& upstream) {
  if (!have_frame_) throw std::logic_error("blend_weights() before bin() or forward()");
  const size_t npix = static_cast<size_t>(cam_.width) * cam_.height;
  if (!upstream.empty() && upstream.size() != npix)
    throw std::invalid_argument("blend_weights: " + std::to_string(upstream.size()) + " upstream factors for " +
                                std::to_string(npix) + " pixels");
  std::map<std::string, std::string> defs;
  const cl::NDRange local = blend_bwd_layout(defs);
  if (staged_) defs["BATCH"] = std::to_string(bwd_plan_.weights_batch);
  defs["UPSTREAM"] = upstream.empty() ? "0" : "1";
  if (!upstream.empty())
    g_feat_.upload(upstream);
  else
    g_feat_.reserve(4);  // not read
  isect_weights_.reserve(std::max<size_t>(stats_.n_intersections, 1) * 4);
  cl::Kernel weights = rt_.kernel("blend_bwd.cl", "blend_weights", defs);
  const size_t M = stats_.n_intersections, f4 = sizeof(float);
  KernelCall(weights)
      .arg("width", cam_.width)
      .arg("height", cam_.height)
      .arg("tiles_x", tiles_x_)
      .buffer("ranges", ranges_, static_cast<size_t>(tiles_x_) * tiles_y_ * 8)
      .buffer("isect_vals", *sorted_isect_vals_, M * 4)
      .buffer("isect_gid", isect_gid_, M * 4)
      .buffer("records", records_, gaussians_->n * REC_SIZE * f4)
      .buffer("upstream", g_feat_, upstream.empty() ? 4 : npix * f4)
      .buffer("isect_weights", isect_weights_, M * f4)
      .done();
  rt_.launch("blend_weights", weights, cl::NDRange(static_cast<size_t>(tiles_x_) * tiles_y_ * local[0]), local);
  const DeviceGaussians& g = *gaussians_;
  weight_sums_.reserve(std::max<size_t>(g.n, 1) * 4);
  if (g.n == 0) return;
  // Only the feature channel's per-Gaussian sum: project_bwd's chain rule
  // would be wasted on it.
  std::map<std::string, std::string> pdef{{"SH_K", std::to_string(sh_coeffs_for_degree(g.sh_degree))},
                                          {"SH_ACTIVE", std::to_string(sh_active_)}};
  cl::Kernel sums = rt_.kernel("project_bwd.cl", "weight_sums", pdef);
  KernelCall(sums)
      .arg("n", static_cast<int>(g.n))
      .buffer("tile_counts", tile_counts_, g.n * 4)
      .buffer("isect_start", isect_start_, g.n * 4)
      .buffer("isect_weights", isect_weights_, M * f4)
      .buffer("sums", weight_sums_, g.n * f4)
      .done();
  rt_.launch("blend_weights", sums, cl::NDRange(g.n), cl::NDRange(64));
}

void Renderer::release_images_and_gradients() {
  for (DeviceBuffer* b :
       {&out_rgb_,   &out_feat_, &out_depth_,   &out_alpha_, &out_dist_,   &out_aux_,   &out_last_,
        &out_count_, &g_rgb_,    &g_feat_,      &g_depth_,   &g_alpha_,    &g_dist_,    &v_means_,
        &v_scales_,  &v_quats_,  &v_opacities_, &v_sh_,      &v_features_, &v_means2d_, &isect_grads_})
    b->release();
  have_images_ = false;
}

cl::NDRange Renderer::blend_bwd_layout(std::map<std::string, std::string>& defs) {
  defs["NO_STAGING"] = staged_ ? "0" : "1";
  if (!staged_) {
    defs["VW"] = std::to_string(cpu_bwd_vector_width_);
    return cl::NDRange(1);
  }
  defs["VW"] = std::to_string(bwd_plan_.vector_width);
  defs["BATCH"] = std::to_string(bwd_plan_.batch);
  defs["SEG"] = std::to_string(bwd_plan_.seg);
  return cl::NDRange(static_cast<size_t>(kTile * kTile / bwd_plan_.vector_width));
}

void Renderer::project_backward() {
  const DeviceGaussians& g = *gaussians_;
  const size_t n = std::max<size_t>(g.n, 1);
  const int K = sh_coeffs_for_degree(g.sh_degree);
  reserve_each(n, {{&v_means_, 12},
                   {&v_scales_, 12},
                   {&v_quats_, 16},
                   {&v_opacities_, 4},
                   {&v_sh_, static_cast<size_t>(K) * 12},
                   {&v_features_, 12},
                   {&v_means2d_, 8}});
  if (g.n == 0) return;
  std::map<std::string, std::string> pdef{{"SH_K", std::to_string(K)}, {"SH_ACTIVE", std::to_string(sh_active_)}};
  cl::Kernel pb = rt_.kernel("project_bwd.cl", "project_bwd", pdef);
  const size_t f4 = sizeof(float), M = stats_.n_intersections;
  KernelCall(pb)
      .arg("n", static_cast<int>(g.n))
      .buffer("cam", cam_buf_, CAM_SIZE * f4)
      .buffer("means", g.means, g.n * 3 * f4)
      .buffer("scales", g.scales, g.n * 3 * f4)
      .buffer("quats", g.quats, g.n * 4 * f4)
      .buffer("sh", g.sh, g.n * K * 3 * f4)
      .buffer("records", records_, g.n * REC_SIZE * f4)
      .buffer("tile_counts", tile_counts_, g.n * 4)
      .buffer("isect_start", isect_start_, g.n * 4)
      .buffer("isect_grads", isect_grads_, M * G2_SIZE * f4)
      .buffer("v_means", v_means_, g.n * 3 * f4)
      .buffer("v_scales", v_scales_, g.n * 3 * f4)
      .buffer("v_quats", v_quats_, g.n * 4 * f4)
      .buffer("v_opacities", v_opacities_, g.n * f4)
      .buffer("v_sh", v_sh_, g.n * K * 3 * f4)
      .buffer("v_features", v_features_, g.n * 3 * f4)
      .buffer("v_means2d", v_means2d_, g.n * 2 * f4)
      .done();
  rt_.launch("project_bwd", pb, cl::NDRange(g.n), cl::NDRange(64));
}

GaussianGrads Renderer::download_grads() {
  const size_t n = gaussians_->n;
  const int K = sh_coeffs_for_degree(gaussians_->sh_degree);
  GaussianGrads out;
  v_means_.download(out.means, n * 3);
  v_scales_.download(out.scales, n * 3);
  v_quats_.download(out.quats, n * 4);
  v_opacities_.download(out.opacities, n);
  v_sh_.download(out.sh, n * K * 3);
  v_features_.download(out.features, n * 3);
  v_means2d_.download(out.means2d, n * 2);
  return out;
}

RenderOutput Renderer::render(const GaussianSet& set, const Camera& cam, const RenderSettings& settings) {
  if (!owned_) owned_ = std::make_unique<DeviceGaussians>(rt_);
  owned_->upload(set);
  forward(*owned_, cam, settings);
  return download_output();
}

GaussianGrads Renderer::render_backward(const OutputGrads& grads) {
  backward(grads);
  return download_grads();
}

}  // namespace ag2gs
