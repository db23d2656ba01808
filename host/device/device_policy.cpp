#include "host/device/device_policy.h"

#include <algorithm>
#include <cstdlib>
#include <sstream>
#include <stdexcept>
#include <vector>

#include "kernels/layout.h"

namespace ag2gs {
namespace {

bool is_pow2(int v) {
  return v > 0 && (v & (v - 1)) == 0;
}

constexpr int kTilePixels = TILE * TILE;

}  // namespace

int default_device_index(const std::vector<DeviceInfo>& devices) {
  for (auto& d : devices)
    if (d.is_gpu) return d.index;
  for (auto& d : devices)
    if (d.is_cpu) return d.index;
  return 0;
}

namespace {
int vector_width_from_env(const char* name) {
  const char* env = std::getenv(name);
  if (!env || !*env) return 0;
  const int v = std::atoi(env);
  if (v != 1 && v != 2 && v != 4 && v != 8 && v != 16)
    throw std::runtime_error(std::string(name) + "='" + env + "' must be 1, 2, 4, 8 or 16");
  return v;
}
}  // namespace

int vector_width_for(const DeviceInfo& device) {
  if (const int v = vector_width_from_env("AG2GS_VECTOR_WIDTH")) return v;
  return device.is_gpu ? 1 : 16;
}

int cpu_blend_bwd_vector_width(const DeviceInfo& device) {
  if (const int v = vector_width_from_env("AG2GS_VECTOR_WIDTH")) return v;
  if (const int v = vector_width_from_env("AG2GS_BWD_VECTOR_WIDTH")) return v;
  const unsigned n = device.native_float_width;
  return n >= 16 ? 16 : n >= 8 ? 8 : n >= 4 ? 4 : 16;
}

int instance_walk_vector_width(const DeviceInfo& device, int renderer_width) {
  if (const int v = vector_width_from_env("AG2GS_INSTANCE_VW")) return v;
  return simulated_device(device) ? 4 : renderer_width;
}

bool blend_staging_for(const DeviceInfo& device) {
  if (const char* e = std::getenv("AG2GS_BLEND_STAGING")) {
    if (std::string(e) == "1") return true;
    if (std::string(e) == "0") return false;
    throw std::invalid_argument(std::string("AG2GS_BLEND_STAGING must be 0 or 1, got '") + e + "'");
  }
  return device.is_gpu;
}

bool group_sort_for(const DeviceInfo& device) {
  return device.is_gpu;
}

bool simulated_device(const DeviceInfo& device) {
  return device.platform.find("Oclgrind") != std::string::npos || device.name.find("Oclgrind") != std::string::npos;
}

std::string BlendBwdPlan::describe() const {
  return std::to_string(vector_width) + ":" + std::to_string(batch) + ":" + std::to_string(seg);
}

size_t BlendBwdPlan::local_bytes() const {
  const size_t wg = kTilePixels / vector_width, rows = static_cast<size_t>(batch) * G2_SIZE;
  // s_rec, s_slot and s_rows per staged record (kernels/blend_bwd.cl).
  return 4 * (static_cast<size_t>(batch) * (REC_SIZE + 2) + rows * (wg + seg) + (seg > 1 ? rows * seg : 0) + 1);
}

size_t BlendBwdPlan::weights_local_bytes() const {
  const size_t wg = kTilePixels / vector_width, b = static_cast<size_t>(weights_batch);
  // s_rec, s_slot, s_reach, s_part (and s_seg), the lists and s_alive
  // (kernels/blend_bwd.cl, blend_weights).
  const size_t lists = (TILE + TILE / vector_width) * ((b + 31) / 32);
  return 4 * (b * (REC_SIZE + 2) + b * (wg + seg) + (seg > 1 ? b * seg : 0) + lists + 1);
}

BlendBwdPlan parse_blend_bwd_plan(const std::string& text) {
  BlendBwdPlan p;
  std::stringstream in(text);
  std::string part;
  std::vector<int> v;
  while (std::getline(in, part, ':')) {
    char* end = nullptr;
    long x = std::strtol(part.c_str(), &end, 10);
    if (part.empty() || *end != '\0' || x < 1 || x > 65536) {
      v.clear();
      break;
    }
    v.push_back(static_cast<int>(x));
  }
  const int wg = v.size() == 3 && is_pow2(v[0]) ? kTilePixels / v[0] : 0;
  if (v.size() != 3 || v[0] > 16 || !is_pow2(v[0]) || !is_pow2(v[2]) || v[2] > wg)
    throw std::invalid_argument("AG2GS_BLEND_BWD='" + text +
                                "' must be VW:BATCH:SEG: VW 1, 2, 4, 8 or 16 pixels per work-item, BATCH >= 1 "
                                "Gaussians per staging batch, SEG a power of two up to 256 / VW (e.g. 1:2:8)");
  p.vector_width = v[0];
  p.batch = v[1];
  p.seg = v[2];
  return p;
}

BlendBwdPlan blend_bwd_plan_for(const DeviceInfo& d) {
  BlendBwdPlan p;
  const uint64_t local = d.local_mem > 0 ? d.local_mem : 32768;
  if (const char* e = std::getenv("AG2GS_BLEND_BWD"); e && *e) {
    p = parse_blend_bwd_plan(e);
  } else {
    // Measured on an NVIDIA H100 beside 9 other plans (docs/benchmarks.md,
    // "The blend backward's plans"): 4 pixels per work-item sum their
    // partials in registers, so a batch of 8 Gaussians leaves 64 values per
    // summed value in local memory instead of 256 (1M Gaussians at 1920x1080:
    // blend backward 5.5 -> 3.0 ms). A device with less local memory than the
    // 28 KB this takes stages fewer Gaussians per batch.
    p = BlendBwdPlan{};  // 4:8:2
    while (p.batch > 1 && p.local_bytes() > local) p.batch /= 2;
  }
  while (p.weights_batch > p.batch && p.weights_local_bytes() > local) p.weights_batch /= 2;
  p.weights_batch = std::max(p.weights_batch, p.batch);
  if (p.local_bytes() > local)
    throw std::invalid_argument("blend backward plan " + p.describe() + " needs " + std::to_string(p.local_bytes()) +
                                " bytes of local memory, " + d.name + " has " + std::to_string(local) +
                                "; choose a smaller BATCH or a wider VW in AG2GS_BLEND_BWD");
  const size_t wg = kTilePixels / p.vector_width;
  if (d.max_work_group > 0 && wg > d.max_work_group)
    throw std::invalid_argument("blend backward plan " + p.describe() + " needs work-groups of " + std::to_string(wg) +
                                ", " + d.name + " allows " + std::to_string(d.max_work_group) +
                                "; choose a wider VW in AG2GS_BLEND_BWD");
  return p;
}

}  // namespace ag2gs
