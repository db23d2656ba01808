// The differentiable tile renderer: project -> bin -> blend on an OpenCL
// device, and the backward pass blend -> project, all without floating-point
// atomics (docs/rasterizer.md gives the exact function computed).
#pragma once

#include <initializer_list>
#include <map>
#include <string>

#include "host/core/gaussians.h"
#include "host/device/cl_runtime.h"
#include "host/device/device_policy.h"
#include "host/render/radix_sort.h"

namespace ag2gs {

// Gaussian parameters resident on the device.
struct DeviceGaussians {
  explicit DeviceGaussians(Runtime& rt);
  void upload(const GaussianSet& set);  // validates shapes first
  size_t n = 0;
  int sh_degree = 0;
  DeviceBuffer means, scales, quats, opacities, sh, features;
};

// Read-only view of per-Gaussian gradient buffers, shapes as in GaussianGrads
// with N = n and K = (sh_degree+1)^2 (Renderer::device_grads(); tests may
// point it at their own buffers).
struct DeviceGaussianGrads {
  size_t n = 0;
  int sh_degree = 0;
  const DeviceBuffer *means = nullptr, *scales = nullptr, *quats = nullptr, *opacities = nullptr, *sh = nullptr,
                     *features = nullptr, *means2d = nullptr;
};

// The camera block the kernels read (CAM_* of kernels/layout.h).
std::vector<float> pack_camera(const Camera& cam, const RenderSettings& settings);

struct FrameStats {
  size_t n_gaussians = 0;
  size_t n_intersections = 0;
  int width = 0, height = 0;
};

class Renderer {
 public:
  explicit Renderer(Runtime& rt);

  // Host-side convenience: upload, render, download.
  RenderOutput render(const GaussianSet& set, const Camera& cam, const RenderSettings& settings = {});
  // Gradients of the last render() with respect to its Gaussians.
  GaussianGrads render_backward(const OutputGrads& grads);

  // Device-side API for the trainer: the frame state stays on the device.
  void forward(const DeviceGaussians& g, const Camera& cam, const RenderSettings& settings);
  // forward() without the blend: projection, depth sort and binning only, so
  // device_frame() is valid and the images are not (download_output() and
  // backward() refuse); for passes that walk the lists themselves
  // (InstanceMapper::compute_with_images).
  void bin(const DeviceGaussians& g, const Camera& cam, const RenderSettings& settings);
  RenderOutput download_output();
  void backward(const OutputGrads& grads);
  GaussianGrads download_grads();
  // The gradient buffers of the last backward(), left on the device; valid
  // until the next forward()/backward().
  DeviceGaussianGrads device_grads() const {
    return {gaussians_ ? gaussians_->n : 0,
            gaussians_ ? gaussians_->sh_degree : 0,
            &v_means_,
            &v_scales_,
            &v_quats_,
            &v_opacities_,
            &v_sh_,
            &v_features_,
            &v_means2d_};
  }
  // [N] int radii of the last forward() (> 0 = visible), left on the device;
  // valid until the next forward().
  const DeviceBuffer& device_radii() const { return radii_; }
  // Images of the last forward() on the device, planar: rgb and feature
  // [3,H,W], alpha and distortion [H,W]; valid until the next forward().
  const DeviceBuffer& device_rgb() const { return out_rgb_; }
  const DeviceBuffer& device_feature() const { return out_feat_; }
  const DeviceBuffer& device_alpha() const { return out_alpha_; }
  const DeviceBuffer& device_distortion() const { return out_dist_; }

  // Upstream gradients already on the device, planar like the images above;
  // null = zero. Lets a trainer compute its losses on the device and feed
  // their gradients back without a host round trip.
  struct DeviceOutputGrads {
    const DeviceBuffer* rgb = nullptr;         // [3,H,W]
    const DeviceBuffer* feature = nullptr;     // [3,H,W]
    const DeviceBuffer* depth = nullptr;       // [H,W]
    const DeviceBuffer* alpha = nullptr;       // [H,W]
    const DeviceBuffer* distortion = nullptr;  // [H,W]
  };
  void backward(const DeviceOutputGrads& grads);
  // After bin() or forward(): each Gaussian's blending weights w = alpha T
  // summed over the frame's pixels, in device_weight_sums() ([N] floats).
  // Equal bit for bit to channel 0 of device_grads().features after
  // forward() and backward() with an upstream gradient of 1 on feature
  // channel 0 and none other, at the cost of one walk (kernels/blend_bwd.cl,
  // blend_weights) and a sum per Gaussian (no gradients are computed).
  // `upstream` ([H,W], or empty for 1 everywhere) multiplies each pixel's
  // weights: the sums are then that channel's gradient for this upstream
  // plane, bit for bit.
  void blend_weights(const std::vector<float>& upstream = {});
  const DeviceBuffer& device_weight_sums() const { return weight_sums_; }
  // Frees the output planes and the gradients of the last forward() and
  // backward() (the next ones allocate them again), for a stretch of bin()
  // and blend_weights() calls that need neither, such as the importance
  // sweep: a smaller footprint, and on a simulator cheaper launches.
  void release_images_and_gradients();

  // The blending inputs of the last forward(), read-only, for kernels that
  // walk the same depth-ordered per-tile lists as blend_fwd.cl (instance
  // maps, train/stage3/instance_map.h). Layouts as in kernels/blend_fwd.cl; valid
  // until the next forward(). Throws std::logic_error before the first.
  struct DeviceFrame {
    int width = 0, height = 0, tiles_x = 0, tiles_y = 0;
    size_t n_gaussians = 0;
    const DeviceBuffer* cam = nullptr;         // [CAM_SIZE] camera block
    const DeviceBuffer* ranges = nullptr;      // [tiles] int2 [start, end) into isect_vals
    const DeviceBuffer* isect_vals = nullptr;  // [M] uint intersection slots, sorted by (tile, depth)
    const DeviceBuffer* isect_gid = nullptr;   // [M] uint Gaussian id of each slot
    const DeviceBuffer* records = nullptr;     // [N, REC_SIZE] projected Gaussians
  };
  DeviceFrame device_frame() const {
    if (!have_frame_) throw std::logic_error("Renderer::device_frame() before forward()");
    return {cam_.width, cam_.height, tiles_x_,  tiles_y_, gaussians_->n,
            &cam_buf_,  &ranges_,    sorted_isect_vals_, &isect_gid_, &records_};
  }

  // The Gaussians blended at pixel (x, y) of the last forward(), front to
  // back, with their blending weights w = alpha T and camera depths: the
  // tile's list walked on the host in float with the kernels' rules (alpha
  // >= 1/255, at most 0.99, stop below T = 1e-4). The weights agree with the
  // rendered ones to float rounding (the host exp is not the device's), so
  // a decision at a threshold may rarely differ. For picking what a pixel
  // shows (QueryEngine::click). Throws std::logic_error before forward()
  // and std::out_of_range outside the image.
  struct PixelContribution {
    uint32_t gaussian = 0;
    float weight = 0, depth = 0;
  };
  std::vector<PixelContribution> pixel_contributions(int x, int y) const;

  const FrameStats& stats() const { return stats_; }
  // The blend backward's plan ("VW:BATCH:SEG"), or "cpu" for the CPU layout.
  std::string blend_bwd_plan() const { return staged_ ? bwd_plan_.describe() : "cpu"; }
  // Whether blending stages records through local memory (the GPU layout,
  // device_policy.h); kernels that walk the same lists follow it.
  bool staged() const { return staged_; }
  Runtime& runtime() { return rt_; }

 private:
  // The defines of kernels/bin.cl (SCAN_BLOCK, VISIBLE_CHUNK, ...).
  std::map<std::string, std::string> bin_defines() const;
  // Gaussians per work-item of bin.cl's visible_flags: 1 in the GPU layout
  // (work-groups of 64), more on CPUs (work-groups of 1, no barriers).
  int visible_chunk() const;
  // Exclusive scan of n uints of `in` into `out` (bin.cl); returns the total.
  size_t exclusive_scan(DeviceBuffer& in, DeviceBuffer& out, size_t n);
  void upload_plane(DeviceBuffer& buf, const std::vector<float>& host_hwc, int channels, const char* what);
  // Which upstream gradients were given (the others are zero buffers): the
  // CPU blend kernel leaves the terms of absent ones out.
  // The blend backward's layout: its defines (staging, the plan) and work-group
  // size (GPUs: the plan's work-items per tile; CPUs: one work-item per tile at
  // the runtime's vector width, see blend_bwd.cl); sizes the slots' gradients.
  cl::NDRange blend_bwd_layout(std::map<std::string, std::string>& defs);
  void project_backward();  // isect_grads_ -> the Gaussians' gradients
  struct GradsPresent {
    bool rgb = true, feature = true, depth = true, alpha = true, distortion = true;
  };
  // The backward pass proper, from planar device gradients.
  void backward_from(const DeviceBuffer& g_rgb, const DeviceBuffer& g_feat, const DeviceBuffer& g_depth,
                     const DeviceBuffer& g_alpha, const DeviceBuffer& g_dist, const GradsPresent& present);

  Runtime& rt_;
  RadixSort sort_;  // depth order and tile order (the device's plan)
  bool staged_;     // blending stages through local memory (device_policy.h), read once
  BlendBwdPlan bwd_plan_;
  int cpu_bwd_vector_width_;                // the CPU layout's (cpu_blend_bwd_vector_width)
  std::unique_ptr<DeviceGaussians> owned_;  // for render()
  const DeviceGaussians* gaussians_ = nullptr;
  Camera cam_;
  RenderSettings settings_;
  int sh_active_ = 0;
  int tiles_x_ = 0, tiles_y_ = 0;
  FrameStats stats_;
  bool have_frame_ = false;     // device_frame() valid (bin() or forward())
  bool have_images_ = false;    // the images and the backward's inputs (forward())
  bool frame_features_ = true;  // the last forward() blended the feature planes

  // A buffer and its bytes per item (Gaussian, intersection or pixel): the
  // buffers of one size class are reserved together, as a table.
  struct SizedBuffer {
    DeviceBuffer* buffer;
    size_t bytes_per_item;
  };
  static void reserve_each(size_t items, std::initializer_list<SizedBuffer> buffers);

  DeviceBuffer cam_buf_, records_, rects_, tile_counts_, depth_keys_, radii_;
  DeviceBuffer order_keys_, order_keys_tmp_, order_vals_, order_vals_tmp_, counts_sorted_, offsets_, block_sums_;
  DeviceBuffer key_range_;  // [2] the least and greatest on-screen depth key (bin.cl visible_flags)
  cl_uint key_range_host_[2] = {0u, 0u};  // key_range_ read back in bin()
  DeviceBuffer tile_keys_, tile_keys_tmp_, isect_vals_, isect_vals_tmp_, isect_gid_, isect_start_, ranges_;
  DeviceBuffer out_rgb_, out_feat_, out_depth_, out_alpha_, out_dist_, out_aux_, out_last_, out_count_;
  DeviceBuffer g_rgb_, g_feat_, g_depth_, g_alpha_, g_dist_, isect_grads_;
  DeviceBuffer v_means_, v_scales_, v_quats_, v_opacities_, v_sh_, v_features_, v_means2d_;
  DeviceBuffer isect_weights_;            // blend_weights(): [M] each slot's weights summed over its tile
  DeviceBuffer weight_sums_;              // blend_weights(): [N]
  DeviceBuffer* sorted_order_ = nullptr;  // the on-screen Gaussians' ids in depth order
  size_t visible_ = 0;                    // how many (sorted_order_'s length)
  DeviceBuffer* sorted_tile_keys_ = nullptr;
  DeviceBuffer* sorted_isect_vals_ = nullptr;
};

}  // namespace ag2gs
