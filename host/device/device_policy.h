// Every choice ag2gs makes by the kind of OpenCL device, in one place, each
// with the measurement behind it (docs/benchmarks.md) and the environment
// variable that overrides it (docs/usage.md). The kernels are the same on
// every device; these rules pick their layout and the host's plans.
#pragma once

#include <string>
#include <vector>

#include "host/device/cl_runtime.h"

namespace ag2gs {

// The device used without --device or $AG2GS_DEVICE: the first GPU, else
// the first CPU, else device 0.
int default_device_index(const std::vector<DeviceInfo>& devices);

// Pixels per work-item in blending (VW): GPUs 1 (a float per lane of a
// warp), CPUs 16 (a vfloat fills PoCL's SIMD registers). AG2GS_VECTOR_WIDTH
// (1, 2, 4, 8 or 16) overrides.
int vector_width_for(const DeviceInfo& device);

// Pixels per work-item of the CPU layout's blend backward (blend_bwd and
// blend_weights without staging): the device's native float width, 4 to 16.
// Its 13 per-intersection sums then stay in SIMD registers (AVX2 has 16 of
// 8 floats; at 16 pixels they spill), where the forward keeps 16 (a tile
// row per vector; at 8 it was slower). AG2GS_VECTOR_WIDTH sets both;
// AG2GS_BWD_VECTOR_WIDTH this one alone.
int cpu_blend_bwd_vector_width(const DeviceInfo& device);

// Whether blending stages Gaussians through local memory in work-groups of a
// tile's pixels (GPUs) or walks the lists without barriers, one work-item
// per tile (CPUs: PoCL keeps values that live across a barrier in
// memory). AG2GS_BLEND_STAGING=1 or 0 overrides (the tests run the GPU
// layout on the CPU with it).
bool blend_staging_for(const DeviceInfo& device);

// The radix sort: GPUs a work-group sort (radix_sort.cl rs_*), CPUs the
// block sort of this many keys per work-item (the work-group sort's barriers
// cost more than its parallelism gives on a few cores: 13.5 against 5.5 ms
// for 100k Gaussians at 800x600 on 2 cores). AG2GS_SORT overrides
// (host/render/radix_sort.h).
bool group_sort_for(const DeviceInfo& device);
inline constexpr int kCpuSortBlockKeys = 4096;

// Oclgrind, the simulated GPU the tests prove the GPU layout on. It
// interprets each work-item's instructions one by one and runs the groups
// one after another, so plans whose fixed work per work-item repeats over
// many work-items cost it what parallel hardware would hide.
bool simulated_device(const DeviceInfo& device);

// Pixels per work-item of the GPU layout's instance walk (kernels/
// instance_map.cl with staging). Its arithmetic is per pixel, so every width
// gives the same bits. The renderer's width (vector_width_for: 1 on GPUs),
// except on a simulator, which interprets a vector operation as one step:
// 4 pixels per work-item (the blend backward's GPU width) halve its time
// there. AG2GS_INSTANCE_VW (1, 2, 4, 8 or 16) overrides.
int instance_walk_vector_width(const DeviceInfo& device, int renderer_width);

// How the GPU layout of the blend backward (kernels/blend_bwd.cl) sums each
// intersection's per-pixel partials: pixels per work-item (its own vector
// width), Gaussians staged per batch, and work-items per summed value (SEG).
// Every plan is deterministic; plans differ in rounding (the order of the
// sums), so a device keeps one. AG2GS_BLEND_BWD="VW:BATCH:SEG" overrides;
// the CPU layout (no staging) has no plan.
struct BlendBwdPlan {
  int vector_width = 4, batch = 8, seg = 2;
  // blend_weights (the same kernel file) sums one value per Gaussian, not
  // 13: it stages more Gaussians per batch, so a tile passes 4x fewer
  // barriers. Its sums run over the work-items in the same order whatever
  // the batch, so the bits do not depend on it.
  int weights_batch = 32;
  std::string describe() const;
  size_t local_bytes() const;          // blend_bwd's local memory
  size_t weights_local_bytes() const;  // blend_weights'
};
BlendBwdPlan parse_blend_bwd_plan(const std::string& text);  // "VW:BATCH:SEG"; throws naming AG2GS_BLEND_BWD
BlendBwdPlan blend_bwd_plan_for(const DeviceInfo& device);   // the default or AG2GS_BLEND_BWD, checked

}  // namespace ag2gs
