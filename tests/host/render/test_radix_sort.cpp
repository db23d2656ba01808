// The device radix sort (host/render/radix_sort.h) against std::stable_sort:
// every plan the code can choose (the CPU block sort, the GPU work-group sort
// at every digit width, work-groups from the smallest to 1024, one to 32 keys
// per work-item, one group walking many tiles, a sort whole in one launch
// over one tile or many, by one work-group or in two halves merged) must
// give the one stable
// order, bit for bit, on keys with many duplicates, all-equal keys, the
// largest keys, and counts of 0, 1, odd and large. Values are the input
// index, so a tie broken the wrong way shows.
#include <gtest/gtest.h>

#include <algorithm>
#include <cstdint>
#include <numeric>
#include <random>
#include <string>
#include <vector>

#include "host/device/device_policy.h"
#include "host/render/radix_sort.h"
#include "tests/test_util.h"

namespace ag2gs {
namespace {

enum class KeyKind { Duplicates, Uniform, AllEqual, Largest, Descending };

std::vector<uint32_t> make_keys(size_t n, int bits, KeyKind kind, uint32_t seed) {
  const uint32_t mask = bits == 32 ? 0xFFFFFFFFu : (1u << bits) - 1u;
  std::mt19937 rng(seed);
  std::vector<uint32_t> k(n);
  for (size_t i = 0; i < n; ++i) {
    switch (kind) {
      case KeyKind::Duplicates:
        k[i] = (rng() % 37u) * (mask / 37u + 1u) & mask;
        break;
      case KeyKind::Uniform:
        k[i] = rng() & mask;
        break;
      case KeyKind::AllEqual:
        k[i] = mask / 3u;
        break;
      case KeyKind::Largest:
        k[i] = mask - (rng() % 3u);
        break;
      case KeyKind::Descending:
        k[i] = static_cast<uint32_t>((n - i) / 3) & mask;
        break;
    }
  }
  return k;
}

// Sorts on the device with `plan`; returns keys and values.
void device_sort(const RadixSortPlan& plan, const std::vector<uint32_t>& keys, int bits,
                 std::vector<uint32_t>* out_keys, std::vector<uint32_t>* out_vals) {
  Runtime& rt = test::runtime();
  const size_t n = keys.size();
  std::vector<uint32_t> vals(n);
  std::iota(vals.begin(), vals.end(), 0u);
  DeviceBuffer a(&rt), b(&rt), c(&rt), d(&rt);
  // Buffers a little longer than n: the sort must leave the tail alone.
  std::vector<uint32_t> pad_keys = keys, pad_vals = vals;
  pad_keys.resize(n + 5, 0xA5A5A5A5u);
  pad_vals.resize(n + 5, 0x5A5A5A5Au);
  a.upload(pad_keys);
  b.upload(pad_vals);
  c.upload(pad_keys);
  d.upload(pad_vals);
  DeviceBuffer *k = &a, *v = &b, *kt = &c, *vt = &d;
  RadixSort sort(rt, plan);
  sort.sort(k, v, kt, vt, n, bits);
  k->download(*out_keys, n + 5);
  v->download(*out_vals, n + 5);
  for (size_t i = n; i < n + 5; ++i) {
    EXPECT_EQ((*out_keys)[i], 0xA5A5A5A5u) << plan.describe() << ": wrote past the end";
    EXPECT_EQ((*out_vals)[i], 0x5A5A5A5Au) << plan.describe() << ": wrote past the end";
  }
  out_keys->resize(n);
  out_vals->resize(n);
}

void expect_stable_sorted(const RadixSortPlan& plan, const std::vector<uint32_t>& keys, int bits,
                          const std::string& what) {
  std::vector<uint32_t> order(keys.size());
  std::iota(order.begin(), order.end(), 0u);
  std::stable_sort(order.begin(), order.end(), [&](uint32_t x, uint32_t y) { return keys[x] < keys[y]; });
  std::vector<uint32_t> want_keys(keys.size());
  for (size_t i = 0; i < keys.size(); ++i) want_keys[i] = keys[order[i]];
  std::vector<uint32_t> got_keys, got_vals;
  device_sort(plan, keys, bits, &got_keys, &got_vals);
  size_t first_bad = keys.size();
  for (size_t i = 0; i < keys.size() && first_bad == keys.size(); ++i)
    if (got_keys[i] != want_keys[i] || got_vals[i] != order[i]) first_bad = i;
  EXPECT_EQ(first_bad, keys.size()) << plan.describe() << ", " << what << ", n " << keys.size() << ", " << bits
                                    << " bits: first wrong slot " << first_bad;
}

RadixSortPlan plan(const std::string& text) {
  return parse_radix_sort_plan(text);
}

// Every kind of key and count under the plans the renderer picks (CPU, GPU:
// sorts of one tile in one launch), a work-group plan whose groups each walk
// many tiles, and the one-launch sort over every count (up to 157 tiles),
// whole and in two halves merged.
TEST(RadixSort, MatchesStableSortOnEveryKeyKind) {
  const std::vector<std::string> plans{"block:4096",    "group:4:256:8",          "group:4:64:4:3",
                                       "group:4:32:32", "group:4:64:4:auto:1000", "group:4:64:4:auto:1000:2"};
  const std::vector<size_t> counts{0, 1, 2, 255, 2049, 40001};
  const std::vector<KeyKind> kinds{KeyKind::Duplicates, KeyKind::Uniform, KeyKind::AllEqual, KeyKind::Largest,
                                   KeyKind::Descending};
  for (const std::string& p : plans)
    for (size_t n : counts)
      for (int bits : {32, 13, 1})
        for (KeyKind kind : kinds)
          expect_stable_sorted(plan(p), make_keys(n, bits, kind, static_cast<uint32_t>(n * 7 + bits)), bits,
                               "key kind " + std::to_string(static_cast<int>(kind)));
}

// Every digit width, small and large work-groups, one to 32 keys per
// work-item, a single group, odd block sizes of the block sort, the
// one-launch sort and the three launches a pass at the same sizes: small
// counts, so the smallest plans stay quick (and the test runs under
// Oclgrind, whose automatic plan sorts up to 64 tiles in one launch).
// Under a simulator, which looks for races and accesses out of bounds (the
// order itself is checked on the real devices), each key width takes one
// kind of key: duplicates at 32 bits, the largest keys (the last digits'
// runs, at the ends of the buffers) at 11. That halves the sorts, whose
// accesses depend on the plan, the count and the width, not on the keys'
// kind.
TEST(RadixSort, EveryPlanGivesTheSameOrder) {
  const bool simulated = simulated_device(test::runtime().info());
  const std::vector<std::string> plans{"block:1",
                                       "block:33",
                                       "block:65536",
                                       "group",
                                       "group:1:2:1",
                                       "group:2:4:3",
                                       "group:3:8:32",
                                       "group:5:32:1",
                                       "group:5:64:2:1",
                                       "group:4:16:7:2",
                                       "group:1:128:5",
                                       "group:3:32:9:5",
                                       "group:4:32:32:auto:0",
                                       "group:5:64:2:1:0",
                                       "group:4:16:7:2:0",
                                       "group:4:32:32:auto:auto:1",
                                       "group:2:4:3:auto:1000:2",
                                       "group:5:32:1:auto:64:2",
                                       "group:3:8:32:auto:8:2"};
  for (const std::string& p : plans)
    for (size_t n : {size_t{1}, size_t{97}, size_t{1000}})
      for (int bits : {32, 11})
        for (KeyKind kind : {KeyKind::Duplicates, KeyKind::Largest}) {
          if (simulated && kind != (bits == 32 ? KeyKind::Duplicates : KeyKind::Largest)) continue;
          expect_stable_sorted(plan(p), make_keys(n, bits, kind, static_cast<uint32_t>(n + bits)), bits,
                               "key kind " + std::to_string(static_cast<int>(kind)));
        }
}

// Large counts under the GPU plan with the widest and narrowest digits and
// the largest work-group.
TEST(RadixSort, LargeCounts) {
  for (const std::string& p : {"group:4:256:8", "group:5:256:4", "group:2:1024:2", "block:4096"})
    expect_stable_sorted(plan(p), make_keys(600011, 32, KeyKind::Duplicates, 5), 32, "600011 duplicates");
  expect_stable_sorted(plan("group"), make_keys(1 << 20, 20, KeyKind::Uniform, 6), 20, "2^20 uniform");
}

TEST(RadixSort, PlansParseAndBadOnesAreRefused) {
  EXPECT_EQ(plan("block").describe(), "block:4096");
  EXPECT_EQ(plan("block:33").describe(), "block:33");
  EXPECT_EQ(plan("group").describe(), "group:4:auto:auto");
  EXPECT_EQ(plan("group:3:64:5").describe(), "group:3:64:5");
  EXPECT_EQ(plan("group:3:64:5:7").describe(), "group:3:64:5:7");
  EXPECT_EQ(plan("group:3:64:5:auto:0").describe(), "group:3:64:5:auto:0");
  EXPECT_EQ(plan("group:3:64:5:7:12").describe(), "group:3:64:5:7:12");
  EXPECT_EQ(plan("group:3:64:5:auto").describe(), "group:3:64:5");
  EXPECT_EQ(plan("group:3:64:5:auto:auto").describe(), "group:3:64:5");
  EXPECT_EQ(plan("group:3:64:5:auto:auto:2").describe(), "group:3:64:5:auto:auto:2");
  EXPECT_EQ(plan("group:3:64:5:7:12:1").describe(), "group:3:64:5:7:12:1");
  for (const char* bad : {"",
                          "blocks",
                          "block:0",
                          "block:65537",
                          "block:-1",
                          "block:1:2",
                          "group:4",
                          "group:4:256",
                          "group:0:256:8",
                          "group:6:256:8",
                          "group:4:8:8",
                          "group:4:96:8",
                          "group:4:2048:8",
                          "group:4:256:0",
                          "group:4:0:8",
                          "group:4:256:33",
                          "group:4:256:8:0",
                          "group:4:256:8:1:1:1:1",
                          "group:4:256:8:1:1:0",
                          "group:4:256:8:1:1:3",
                          "group:4:256:8:1:1:",
                          "group:4:256:8:auto:-1",
                          "group:4:256:8:auto:x",
                          "group:4:256:8:auto:",
                          "group:4:256:8:",
                          "group:x:256:8",
                          "radix"}) {
    try {
      plan(bad);
      ADD_FAILURE() << "'" << bad << "' was accepted";
    } catch (const std::invalid_argument& e) {
      EXPECT_NE(std::string(e.what()).find("AG2GS_SORT"), std::string::npos) << e.what();
      EXPECT_NE(std::string(e.what()).find("accepted forms"), std::string::npos) << e.what();
    }
  }
  Runtime& rt = test::runtime();
  RadixSort sort(rt, plan("group"));
  DeviceBuffer a(&rt);
  a.upload(std::vector<uint32_t>(4, 0u));
  DeviceBuffer *k = &a, *v = &a, *kt = &a, *vt = &a;
  EXPECT_THROW(sort.sort(k, v, kt, vt, 4, 0), std::invalid_argument);
  EXPECT_THROW(sort.sort(k, v, kt, vt, 4, 33), std::invalid_argument);
}

// The device's plan: the CPU block sort on CPUs, the work-group sort on
// GPUs; $AG2GS_SORT overrides, and a plan the device cannot hold is refused
// with the sizes.
TEST(RadixSort, DevicePlanAndOverride) {
  DeviceInfo cpu, gpu;
  cpu.is_cpu = true;
  cpu.max_work_group = 4096;
  cpu.local_mem = 64 * 1024;
  gpu.is_gpu = true;
  gpu.name = "a GPU";
  gpu.max_work_group = 1024;
  gpu.local_mem = 48 * 1024;
  unsetenv("AG2GS_SORT");
  EXPECT_EQ(radix_sort_plan_for(cpu).describe(), "block:4096");
  EXPECT_EQ(radix_sort_plan_for(gpu).describe(), "group:4:256:8");
  DeviceInfo small = gpu;
  small.max_work_group = 64;
  EXPECT_EQ(radix_sort_plan_for(small).describe(), "group:4:64:8");
  small = gpu;
  small.local_mem = 32 * 1024;  // Oclgrind's, and many GPUs'
  EXPECT_EQ(radix_sort_plan_for(small).describe(), "group:4:256:4");
  // The simulator: few work-items, many keys each; a GPU of one compute
  // unit keeps the wide groups.
  small.compute_units = 1;
  EXPECT_EQ(radix_sort_plan_for(small).describe(), "group:4:256:4");
  small.platform = "Oclgrind";
  small.name = "Oclgrind Simulator";
  EXPECT_EQ(radix_sort_plan_for(small).describe(), "group:4:32:32");
  setenv("AG2GS_SORT", "group:4:2048:8", 1);
  EXPECT_THROW(radix_sort_plan_for(gpu), std::invalid_argument);
  setenv("AG2GS_SORT", "group:5:256:16", 1);
  try {
    radix_sort_plan_for(gpu);
    ADD_FAILURE() << "a plan over 48 KiB of local memory was accepted";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("local memory"), std::string::npos) << e.what();
  }
  setenv("AG2GS_SORT", "group", 1);
  EXPECT_EQ(radix_sort_plan_for(cpu).describe(), "group:4:256:8");
  unsetenv("AG2GS_SORT");
}

}  // namespace
}  // namespace ag2gs
