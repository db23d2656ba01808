// devices: the OpenCL platforms and devices, and which one runs by default.
#include <cstdint>
#include <cstdio>
#include <string>

#include "cli/commands.h"
#include "host/device/cl_runtime.h"
#include "host/device/device_policy.h"

namespace ag2gs::cli {
namespace {

std::string human_bytes(uint64_t b) {
  char buf[32];
  if (b >= (1ull << 30))
    std::snprintf(buf, sizeof buf, "%.1f GiB", b / double(1ull << 30));
  else if (b >= (1ull << 20))
    std::snprintf(buf, sizeof buf, "%.1f MiB", b / double(1ull << 20));
  else
    std::snprintf(buf, sizeof buf, "%.0f KiB", b / 1024.0);
  return buf;
}

void cmd_devices(const GlobalOptions& global) {
  auto devices = list_devices();
  if (devices.empty()) {
    resolve_device_index(-1, devices);  // throws the install hint
  }
  int def = default_device_index(devices);
  int selected = resolve_device_index(global.device, devices);
  for (auto& d : devices) {
    std::printf("[%d]%s %s\n", d.index,
                d.index == selected ? (d.index == def ? " (default, selected)" : " (selected)")
                                    : (d.index == def ? " (default)" : ""),
                d.name.c_str());
    std::printf("    platform: %s\n", d.platform.c_str());
    std::printf("    type: %s   compute units: %u   global memory: %s   local memory: %s\n",
                d.is_gpu   ? "GPU"
                : d.is_cpu ? "CPU"
                           : "other",
                d.compute_units, human_bytes(d.global_mem).c_str(), human_bytes(d.local_mem).c_str());
    std::printf("    fp64: %s   max work-group: %zu   version: %s   driver: %s\n", d.fp64 ? "yes" : "no",
                d.max_work_group, d.version.c_str(), d.driver.c_str());
  }
}

}  // namespace

void register_devices(CLI::App& app, GlobalOptions& global) {
  auto* dev = app.add_subcommand("devices", "List OpenCL platforms and devices");
  set_action(dev, [&global] { cmd_devices(global); });
}

}  // namespace ag2gs::cli
