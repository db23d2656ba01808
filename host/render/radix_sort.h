// Stable LSD radix sort of (uint key, uint value) pairs on the device
// (kernels/radix_sort.cl), the renderer's two sorts: Gaussians by depth and
// intersections by tile. A stable sort has exactly one result, so the plan
// (which kernels, digit width, work-group size, tile) sets only the speed:
// every plan gives the same bits.
#pragma once

#include <cstddef>
#include <string>

#include "host/device/cl_runtime.h"

namespace ag2gs {

struct RadixSortPlan {
  enum class Kind {
    Block,  // one work-item per block of keys, 8-bit digits, no barriers (CPUs)
    Group,  // work-groups count, scan and rank in local memory (GPUs)
  };
  Kind kind = Kind::Group;
  int block = 4096;       // Block: keys per work-item
  int digit_bits = 4;     // Group: bits per pass, 1..5
  int work_group = 0;     // Group: work-items per group, a power of two >= 2^digit_bits; 0 = 256 or the device's
                          // most (32 under Oclgrind)
  int keys_per_item = 0;  // Group: keys per work-item and tile; 0 = 8 (32 under Oclgrind), or
                          // fewer where local memory is short
  int max_groups = 0;     // Group: work-groups per pass at most; 0 = 8 per compute unit
  int one_group_tiles = -1;  // Group: sorts of at most this many tiles run whole in one launch by one work-group
                             // (rs_one_group); -1 = 1 tile (64 under Oclgrind), 0 = never
  int one_group_runs = 0;    // Group: 2 = such a sort of more than a tile and more than one pass runs as two
                             // halves, a work-group each, then a merge (rs_merge_runs); 1 = one group;
                             // 0 = 2 under Oclgrind (its threads run work-groups side by side), else 1

  // "block:4096" or "group:4:256:8" (":G" appended when max_groups is set,
  // ":G:T" when one_group_tiles is, ":G:T:R" when one_group_runs is, G and T
  // maybe "auto"), the form $AG2GS_SORT takes; "group:4:auto:auto" before
  // fit_to().
  std::string describe() const;
  // Resolves the automatic sizes for a device and checks the plan fits it
  // (work-group size, local memory); throws std::invalid_argument naming
  // the sizes when it does not.
  RadixSortPlan fit_to(const DeviceInfo& device) const;
};

// Parses $AG2GS_SORT's form ("block", "block:N", "group",
// "group:BITS:WG:IPT[:GROUPS[:ONE[:RUNS]]]", GROUPS a number or "auto"); throws
// std::invalid_argument naming the variable and the accepted forms.
RadixSortPlan parse_radix_sort_plan(const std::string& text);

// The plan for a device, fitted to it: Group on GPUs, Block with 4096 keys
// on CPUs; $AG2GS_SORT overrides. Throws std::invalid_argument when the plan
// does not fit the device (work-group size, local memory).
RadixSortPlan radix_sort_plan_for(const DeviceInfo& device);

class RadixSort {
 public:
  explicit RadixSort(Runtime& rt);                    // radix_sort_plan_for(rt.info())
  RadixSort(Runtime& rt, const RadixSortPlan& plan);  // plan.fit_to(rt.info())

  // Sorts the first n pairs by the keys' low `bits` bits (1..32; higher bits
  // must be zero). Passes alternate between the buffers: on return `keys`
  // and `vals` point at the sorted ones (maybe the former tmp buffers).
  // Each buffer holds at least n uints.
  void sort(DeviceBuffer*& keys, DeviceBuffer*& vals, DeviceBuffer*& keys_tmp, DeviceBuffer*& vals_tmp, size_t n,
            int bits, const std::string& label = "sort");

  const RadixSortPlan& plan() const { return plan_; }
  // The most keys a Group plan sorts whole in one launch (0 for Block): the
  // renderer's scans of as many values take one launch too.
  size_t one_launch_keys() const;

 private:
  void sort_block(DeviceBuffer*& keys, DeviceBuffer*& vals, DeviceBuffer*& keys_tmp, DeviceBuffer*& vals_tmp, size_t n,
                  int bits, const std::string& label);
  void sort_group(DeviceBuffer*& keys, DeviceBuffer*& vals, DeviceBuffer*& keys_tmp, DeviceBuffer*& vals_tmp, size_t n,
                  int bits, const std::string& label);

  Runtime& rt_;
  RadixSortPlan plan_;
  DeviceBuffer counts_;
};

}  // namespace ag2gs
