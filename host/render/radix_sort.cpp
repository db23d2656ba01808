#include "host/render/radix_sort.h"

#include <algorithm>
#include <cstdlib>
#include <sstream>
#include <stdexcept>
#include <vector>

#include "host/device/device_policy.h"
#include "host/device/kernel_call.h"

namespace ag2gs {

namespace {

const char* kPlanForms =
    "'block', 'block:KEYS' (KEYS in [1, 65536]), 'group' or 'group:BITS:WG:IPT[:GROUPS[:ONE[:RUNS]]]' (BITS in "
    "[1, 5], WG a power of two in [2^BITS, 1024], IPT in [1, 32], GROUPS >= 1 or 'auto', ONE >= 0 or 'auto': sorts "
    "of at most ONE tiles in one launch, RUNS 1 or 2: such a sort by one work-group or by two and a merge)";

size_t ceil_div(size_t a, size_t b) {
  return (a + b - 1) / b;
}

// The automatic plan on a simulator (fit_to).
constexpr int kSimulatorSortGroup = 32, kSimulatorSortKeys = 32;
// Sorts of at most this many tiles run whole in one launch (rs_one_group):
// on a GPU a single tile, which one work-group would sort anyway, without
// 3 launches a pass; on a simulator, whose every launch has a cost of its
// own (Oclgrind's race detector clears a record of every allocated byte
// after each kernel), the frames of small scenes.
constexpr int kOneGroupTiles = 1, kSimulatorOneGroupTiles = 64;

bool is_pow2(int v) {
  return v > 0 && (v & (v - 1)) == 0;
}

// Local memory of rs_one_group, the largest of the kernels (radix_sort.cl):
// the counters, two arrays of a word per work-item, the tile, two of a word
// per digit.
uint64_t group_local_bytes(const RadixSortPlan& p) {
  const uint64_t cells = (uint64_t{1} << p.digit_bits) * p.work_group;
  return 4 * (cells + cells / 32 + 2 * uint64_t(p.work_group) + 2 * uint64_t(p.work_group) * p.keys_per_item +
              2 * (uint64_t{1} << p.digit_bits));
}

void check_plan(const RadixSortPlan& p, const std::string& where) {
  auto bad = [&](const std::string& what) {
    return std::invalid_argument(where + ": " + what + "; accepted forms: " + kPlanForms);
  };
  if (p.kind == RadixSortPlan::Kind::Block) {
    if (p.block < 1 || p.block > 65536) throw bad("block of " + std::to_string(p.block) + " keys");
    return;
  }
  if (p.digit_bits < 1 || p.digit_bits > 5) throw bad("digit of " + std::to_string(p.digit_bits) + " bits");
  if (p.work_group != 0 && (!is_pow2(p.work_group) || p.work_group < (1 << p.digit_bits) || p.work_group > 1024))
    throw bad("work-group of " + std::to_string(p.work_group));
  if (p.keys_per_item < 0 || p.keys_per_item > 32) throw bad(std::to_string(p.keys_per_item) + " keys per work-item");
  if (p.max_groups < 0) throw bad(std::to_string(p.max_groups) + " groups");
  if (p.one_group_tiles < -1) throw bad("one launch up to " + std::to_string(p.one_group_tiles) + " tiles");
  if (p.one_group_runs < 0 || p.one_group_runs > 2)
    throw bad("one-launch sorts in " + std::to_string(p.one_group_runs) + " runs");
}

// A scatter's keys and values, n of each: read from keys and vals, written to
// keys_out and vals_out.
KernelCall& scatter_buffers(KernelCall& call, const DeviceBuffer& keys, const DeviceBuffer& vals,
                            const DeviceBuffer& keys_out, const DeviceBuffer& vals_out, size_t n) {
  const size_t bytes = n * sizeof(cl_uint);
  return call.buffer("keys_in", keys, bytes)
      .buffer("vals_in", vals, bytes)
      .buffer("keys_out", keys_out, bytes)
      .buffer("vals_out", vals_out, bytes);
}

}  // namespace

std::string RadixSortPlan::describe() const {
  std::ostringstream s;
  if (kind == Kind::Block) {
    s << "block:" << block;
  } else {
    auto size = [](int v) { return v == 0 ? std::string("auto") : std::to_string(v); };
    s << "group:" << digit_bits << ":" << size(work_group) << ":" << size(keys_per_item);
    if (max_groups > 0 || one_group_tiles >= 0 || one_group_runs > 0) s << ":" << size(max_groups);
    if (one_group_tiles >= 0 || one_group_runs > 0)
      s << ":" << (one_group_tiles >= 0 ? std::to_string(one_group_tiles) : std::string("auto"));
    if (one_group_runs > 0) s << ":" << one_group_runs;
  }
  return s.str();
}

RadixSortPlan parse_radix_sort_plan(const std::string& text) {
  std::vector<std::string> parts;
  std::stringstream ss(text);
  for (std::string part; std::getline(ss, part, ':');) parts.push_back(part);
  auto fail = [&]() {
    return std::invalid_argument("AG2GS_SORT='" + text + "' is not a sort plan; accepted forms: " + kPlanForms);
  };
  auto number = [&](const std::string& s) {
    if (s.empty() || s.size() > 9 || s.find_first_not_of("0123456789") != std::string::npos) throw fail();
    return std::stoi(s);
  };
  RadixSortPlan p;
  if (parts.empty() || text.back() == ':') throw fail();
  if (parts[0] == "block") {
    if (parts.size() > 2) throw fail();
    p.kind = RadixSortPlan::Kind::Block;
    if (parts.size() == 2) p.block = number(parts[1]);
  } else if (parts[0] == "group") {
    if (parts.size() != 1 && (parts.size() < 4 || parts.size() > 7)) throw fail();
    p.kind = RadixSortPlan::Kind::Group;
    if (parts.size() >= 4) {
      p.digit_bits = number(parts[1]);
      p.work_group = number(parts[2]);
      p.keys_per_item = number(parts[3]);
      if (p.work_group == 0 || p.keys_per_item == 0) throw fail();
    }
    if (parts.size() >= 5 && parts[4] != "auto") {
      p.max_groups = number(parts[4]);
      if (p.max_groups == 0) throw fail();
    }
    if (parts.size() >= 6 && parts[5] != "auto") p.one_group_tiles = number(parts[5]);
    if (parts.size() == 7) {
      p.one_group_runs = number(parts[6]);
      if (p.one_group_runs == 0) throw fail();
    }
  } else {
    throw fail();
  }
  check_plan(p, "AG2GS_SORT='" + text + "'");
  return p;
}

RadixSortPlan RadixSortPlan::fit_to(const DeviceInfo& device) const {
  RadixSortPlan p = *this;
  check_plan(p, "sort plan " + describe());
  if (p.kind == Kind::Block) return p;
  const size_t device_wg = device.max_work_group > 0 ? device.max_work_group : 1024;
  // Each tile costs every work-item the same fixed work whatever its keys:
  // clearing and summing its 2^BITS counters, the rank scan's barriers.
  // Parallel hardware hides it; a simulator pays it work-item by work-item,
  // so few work-items with many keys each suit it (3,088 keys under
  // Oclgrind: 1.07 s with 256 x 4, 0.39 s with 32 x 32).
  const bool simulated = simulated_device(device);
  if (p.work_group == 0) {
    p.work_group = 1 << p.digit_bits;
    const size_t widest = simulated ? kSimulatorSortGroup : 256;
    while (static_cast<size_t>(p.work_group) * 2 <= std::min<size_t>(device_wg, widest)) p.work_group *= 2;
  }
  if (static_cast<size_t>(p.work_group) > device_wg || p.work_group < (1 << p.digit_bits))
    throw std::invalid_argument("sort plan " + describe() + ": work-group of " + std::to_string(p.work_group) +
                                " does not fit " + device.name + " (at most " + std::to_string(device_wg) +
                                " work-items); choose a smaller one in AG2GS_SORT");
  const uint64_t local = device.local_mem > 0 ? device.local_mem : 32768;
  if (p.keys_per_item == 0) {
    p.keys_per_item = simulated ? kSimulatorSortKeys : 8;
    while (p.keys_per_item > 1 && group_local_bytes(p) > local) p.keys_per_item /= 2;
  }
  if (group_local_bytes(p) > local)
    throw std::invalid_argument("sort plan " + p.describe() + " needs " + std::to_string(group_local_bytes(p)) +
                                " bytes of local memory, " + device.name + " has " + std::to_string(local) +
                                "; choose fewer bits, a smaller work-group or fewer keys per work-item in AG2GS_SORT");
  return p;
}

RadixSortPlan radix_sort_plan_for(const DeviceInfo& device) {
  RadixSortPlan p;
  if (const char* e = std::getenv("AG2GS_SORT"); e && *e) {
    p = parse_radix_sort_plan(e);
  } else if (!group_sort_for(device)) {  // CPUs: a few long blocks, one work-item each
    p.kind = RadixSortPlan::Kind::Block;
    p.block = kCpuSortBlockKeys;
  }
  return p.fit_to(device);
}

RadixSort::RadixSort(Runtime& rt) : RadixSort(rt, radix_sort_plan_for(rt.info())) {}

RadixSort::RadixSort(Runtime& rt, const RadixSortPlan& plan) : rt_(rt), plan_(plan.fit_to(rt.info())), counts_(&rt) {}

size_t RadixSort::one_launch_keys() const {
  if (plan_.kind != RadixSortPlan::Kind::Group) return 0;
  const int tiles = plan_.one_group_tiles >= 0     ? plan_.one_group_tiles
                    : simulated_device(rt_.info()) ? kSimulatorOneGroupTiles
                                                   : kOneGroupTiles;
  return static_cast<size_t>(tiles) * plan_.work_group * plan_.keys_per_item;
}

void RadixSort::sort(DeviceBuffer*& keys, DeviceBuffer*& vals, DeviceBuffer*& keys_tmp, DeviceBuffer*& vals_tmp,
                     size_t n, int bits, const std::string& label) {
  if (bits < 1 || bits > 32) throw std::invalid_argument("RadixSort: key bits must be in [1, 32]");
  if (n > 0xFFFFFFFFull) throw std::invalid_argument("RadixSort: more than 2^32 - 1 keys");
  if (n == 0) return;
  if (plan_.kind == RadixSortPlan::Kind::Block)
    sort_block(keys, vals, keys_tmp, vals_tmp, n, bits, label);
  else
    sort_group(keys, vals, keys_tmp, vals_tmp, n, bits, label);
}

void RadixSort::sort_block(DeviceBuffer*& keys, DeviceBuffer*& vals, DeviceBuffer*& keys_tmp, DeviceBuffer*& vals_tmp,
                           size_t n, int bits, const std::string& label) {
  const std::map<std::string, std::string> defs{{"RADIX_BLOCK", std::to_string(plan_.block)}};
  const int nblocks = static_cast<int>(ceil_div(n, plan_.block));
  counts_.reserve(sizeof(cl_uint) * 256 * nblocks);
  cl::Kernel hist = rt_.kernel("radix_sort.cl", "radix_hist", defs);
  cl::Kernel scan = rt_.kernel("radix_sort.cl", "radix_scan", defs);
  cl::Kernel scatter = rt_.kernel("radix_sort.cl", "radix_scatter", defs);
  const int ni = static_cast<int>(n);
  const size_t key_bytes = n * sizeof(cl_uint), count_bytes = sizeof(cl_uint) * 256 * nblocks;
  for (int shift = 0; shift < bits; shift += 8) {
    KernelCall(hist)
        .arg("n", ni)
        .arg("shift", shift)
        .buffer("keys", *keys, key_bytes)
        .buffer("counts", counts_, count_bytes)
        .arg("nblocks", nblocks)
        .done();
    rt_.launch(label, hist, cl::NDRange(nblocks));
    set_kernel_args(scan, nblocks, counts_);
    rt_.launch(label, scan, cl::NDRange(256), cl::NDRange(256));
    scatter_buffers(KernelCall(scatter).arg("n", ni).arg("shift", shift), *keys, *vals, *keys_tmp, *vals_tmp, n)
        .buffer("counts", counts_, count_bytes)
        .arg("nblocks", nblocks)
        .done();
    rt_.launch(label, scatter, cl::NDRange(nblocks));
    std::swap(keys, keys_tmp);
    std::swap(vals, vals_tmp);
  }
}

void RadixSort::sort_group(DeviceBuffer*& keys, DeviceBuffer*& vals, DeviceBuffer*& keys_tmp, DeviceBuffer*& vals_tmp,
                           size_t n, int bits, const std::string& label) {
  const std::map<std::string, std::string> defs{{"RS_BITS", std::to_string(plan_.digit_bits)},
                                                {"RS_WG", std::to_string(plan_.work_group)},
                                                {"RS_IPT", std::to_string(plan_.keys_per_item)}};
  const size_t tile = static_cast<size_t>(plan_.work_group) * plan_.keys_per_item;
  const size_t tiles = ceil_div(n, tile);
  const size_t max_groups = plan_.max_groups > 0 ? plan_.max_groups : 8 * std::max<size_t>(1, rt_.info().compute_units);
  const size_t tiles_per_group = ceil_div(tiles, std::min(tiles, max_groups));
  const size_t groups = ceil_div(tiles, tiles_per_group);
  const cl::NDRange global(groups * plan_.work_group), local(plan_.work_group);
  if (n <= one_launch_keys()) {
    const size_t passes = ceil_div(bits, plan_.digit_bits);
    // Two halves pay off where there is more than a tile to sort and more
    // than one pass to share: the merge costs about a pass and a launch.
    const int runs = plan_.one_group_runs > 0 ? plan_.one_group_runs : simulated_device(rt_.info()) ? 2 : 1;
    const bool halves = runs == 2 && n > tile && passes > 1;
    const cl_uint run = static_cast<cl_uint>(halves ? ceil_div(n, 2) : n);
    cl::Kernel one = rt_.kernel("radix_sort.cl", "rs_one_group", defs);
    scatter_buffers(KernelCall(one).arg("n", static_cast<cl_uint>(n)).arg("bits", bits).arg("run", run), *keys, *vals,
                    *keys_tmp, *vals_tmp, n)
        .done();
    rt_.launch(label, one, cl::NDRange((halves ? 2 : 1) * local[0]), local);
    if (passes % 2 == 1) {  // an odd number of passes ends in the tmp pair
      std::swap(keys, keys_tmp);
      std::swap(vals, vals_tmp);
    }
    if (halves) {
      cl::Kernel merge = rt_.kernel("radix_sort.cl", "rs_merge_runs", defs);
      scatter_buffers(KernelCall(merge).arg("n", static_cast<cl_uint>(n)).arg("run", run), *keys, *vals, *keys_tmp,
                      *vals_tmp, n)
          .done();
      rt_.launch(label, merge, cl::NDRange(n), local);
      std::swap(keys, keys_tmp);
      std::swap(vals, vals_tmp);
    }
    return;
  }
  const size_t bins = size_t{1} << plan_.digit_bits;
  counts_.reserve(sizeof(cl_uint) * bins * groups);
  cl::Kernel count = rt_.kernel("radix_sort.cl", "rs_count", defs);
  cl::Kernel scan = rt_.kernel("radix_sort.cl", "rs_scan", defs);
  cl::Kernel scatter = rt_.kernel("radix_sort.cl", "rs_scatter", defs);
  const cl_uint nu = static_cast<cl_uint>(n), tpg = static_cast<cl_uint>(tiles_per_group),
                gu = static_cast<cl_uint>(groups);
  const size_t key_bytes = n * sizeof(cl_uint), count_bytes = sizeof(cl_uint) * bins * groups;
  for (int shift = 0; shift < bits; shift += plan_.digit_bits) {
    KernelCall(count)
        .arg("n", nu)
        .arg("shift", shift)
        .arg("tiles_per_group", tpg)
        .buffer("keys", *keys, key_bytes)
        .buffer("counts", counts_, count_bytes)
        .done();
    rt_.launch(label, count, global, local);
    set_kernel_args(scan, gu, counts_);
    rt_.launch(label, scan, local, local);
    scatter_buffers(KernelCall(scatter).arg("n", nu).arg("shift", shift).arg("tiles_per_group", tpg), *keys, *vals,
                    *keys_tmp, *vals_tmp, n)
        .buffer("offsets", counts_, count_bytes)
        .done();
    rt_.launch(label, scatter, global, local);
    std::swap(keys, keys_tmp);
    std::swap(vals, vals_tmp);
  }
}

}  // namespace ag2gs
