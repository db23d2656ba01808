// Binning: Gaussians -> (tile, depth)-ordered intersection lists.
//   0. the Gaussians on screen (a tile or more), in index order: a scan of
//      visible_flags, then compact_visible
//   1. sort them by depth (stable radix sort of float bits, ties by index;
//      only the bits in which the on-screen keys differ)
//   2. exclusive scan of tiles-per-Gaussian in that order -> offsets
//   3. emit one intersection per (Gaussian, tile) at the slots the scan gave
//      each Gaussian (isect_starts, then emit_isects in index order)
//   4. stable radix sort of the intersections by tile id -> per tile, depth order
//   5. per-tile [start, end) ranges
// The sorts (1 and 4) are radix_sort.cl's. Step 0 changes no order: a
// culled Gaussian emits nothing, and the stable sort keeps the others in the
// order it gave them among all. All integer work: the result is the same
// whatever the thread count.
// Defines: SCAN_BLOCK, SCAN_WG (the GPU scan's work-group, SCAN_BLOCK / SCAN_WG whole), SCAN_ONE_WG
// (the one-launch scan's, a power of two up to SCAN_BLOCK; SCAN_WG when not given).
#ifndef SCAN_ONE_WG
#define SCAN_ONE_WG SCAN_WG
#endif

// 0, 1, ..., n - 1 (the runtime's tests launch it).
__kernel void iota(int n, __global uint* out) {  // [n]
  int i = get_global_id(0);
  if (i < n) out[i] = (uint)i;
}

// Also the least and the greatest depth key on screen, into key_range
// (which the host sets to {0xFFFFFFFF, 0} first): min and max are the same
// in any order, so the integer atomics leave the same bits. The depth sort
// then sorts the keys minus the least over the bits their range spans,
// skipping the passes of digits that no key changes.
// VISIBLE_CHUNK > 1 (CPUs): each work-item takes that many Gaussians in a
// loop, keeping the least and greatest key in registers, and adds them to
// key_range with two atomics; a work-group's local atomics and barriers
// cost a CPU more than the flags themselves. 1 (GPUs): one Gaussian per
// work-item, the work-group's range gathered in local memory first.
#ifndef VISIBLE_CHUNK
#define VISIBLE_CHUNK 1
#endif
__kernel void visible_flags(int n, __global const uint* tile_counts,  // [N]
                            __global const uint* depth_keys,          // [N]
                            __global uint* flags,                     // [N] 1: on screen
                            __global uint* key_range) {               // [2] least, greatest
#if VISIBLE_CHUNK > 1
  const int begin = get_global_id(0) * VISIBLE_CHUNK;
  const int end = min(n, begin + VISIBLE_CHUNK);
  uint lo = 0xFFFFFFFFu, hi = 0u;
  for (int g = begin; g < end; ++g) {
    const uint on = tile_counts[g] > 0u ? 1u : 0u;
    flags[g] = on;
    const uint k = depth_keys[g];
    lo = on ? min(lo, k) : lo;
    hi = on ? max(hi, k) : hi;
  }
  if (lo <= hi) {
    atomic_min(key_range, lo);
    atomic_max(key_range + 1, hi);
  }
#else
  __local uint lo, hi;
  const int g = get_global_id(0);
  const int on = g < n && tile_counts[g] > 0u;
  if (g < n) flags[g] = on ? 1u : 0u;
  if (get_local_id(0) == 0) {
    lo = 0xFFFFFFFFu;
    hi = 0u;
  }
  barrier(CLK_LOCAL_MEM_FENCE);
  if (on) {
    atomic_min(&lo, depth_keys[g]);
    atomic_max(&hi, depth_keys[g]);
  }
  barrier(CLK_LOCAL_MEM_FENCE);
  if (get_local_id(0) == 0 && lo <= hi) {
    atomic_min(key_range, lo);
    atomic_max(key_range + 1, hi);
  }
#endif
}

// The on-screen Gaussians' depth keys (minus the least, key_base) and ids,
// packed in index order.
__kernel void compact_visible(int n, __global const uint* tile_counts,  // [N]
                              __global const uint* depth_keys,          // [N]
                              __global const uint* slots,               // [N] exclusive scan of the flags
                              uint key_base,                            // the least on-screen key
                              __global uint* keys,                      // [V]
                              __global uint* ids) {                     // [V]
  int g = get_global_id(0);
  if (g >= n || tile_counts[g] == 0u) return;
  const uint s = slots[g];
  keys[s] = depth_keys[g] - key_base;
  ids[s] = (uint)g;
}

__kernel void gather_counts(int n,
                            __global const uint* order,        // [N] Gaussian ids in depth order
                            __global const uint* tile_counts,  // [N]
                            __global uint* counts_sorted) {    // [N]
  int s = get_global_id(0);
  if (s < n) counts_sorted[s] = tile_counts[order[s]];
}

// ---------------------------------------------------------------- scan
// Three-step exclusive scan: per-block scans, a scan of block sums, add-back.
__kernel void scan_blocks(int n, __global const uint* in, __global uint* out,  // [n]
                          __global uint* block_sums) {                         // [nblocks + 1]
  int b = get_global_id(0);
  int begin = b * SCAN_BLOCK;
  if (begin >= n) return;
  int end = min(n, begin + SCAN_BLOCK);
  uint acc = 0;
  for (int i = begin; i < end; ++i) {
    uint v = in[i];
    out[i] = acc;
    acc += v;
  }
  block_sums[b] = acc;
}

__kernel void scan_block_sums(int nblocks, __global uint* block_sums) {  // [nblocks + 1], total at the end
  if (get_global_id(0) != 0) return;
  uint acc = 0;
  for (int b = 0; b < nblocks; ++b) {
    uint v = block_sums[b];
    block_sums[b] = acc;
    acc += v;
  }
  block_sums[nblocks] = acc;
}

// The same sums for GPUs: a work-group of SCAN_WG per block, loads and
// stores coalesced through local memory, and one work-group for the block
// sums (integer sums: the same bits as the two kernels above).
// scan_block_wg: out[begin, begin + SCAN_BLOCK) = carry + the exclusive sums
// of in over the block (within n) by a work-group of any power of two up to
// SCAN_BLOCK; returns the block's sum to every work-item. vals: [SCAN_BLOCK]
// (free again after a barrier), tmp: [local size].
uint scan_block_wg(int n, int begin, uint carry, __global const uint* in, __global uint* out, __local uint* vals,
                   __local uint* tmp) {
  const int lid = get_local_id(0), wg = get_local_size(0);
  for (int i = lid; i < SCAN_BLOCK; i += wg) vals[i] = begin + i < n ? in[begin + i] : 0u;
  barrier(CLK_LOCAL_MEM_FENCE);
  const int per = SCAN_BLOCK / wg;
  uint s = 0;
  for (int j = 0; j < per; ++j) s += vals[lid * per + j];
  uint total;
  uint acc = carry + group_exclusive_scan(s, tmp, &total);
  for (int j = 0; j < per; ++j) {
    uint v = vals[lid * per + j];
    vals[lid * per + j] = acc;
    acc += v;
  }
  barrier(CLK_LOCAL_MEM_FENCE);
  for (int i = lid; i < SCAN_BLOCK; i += wg)
    if (begin + i < n) out[begin + i] = vals[i];
  return total;
}

__kernel __attribute__((reqd_work_group_size(SCAN_WG, 1, 1)))
void scan_blocks_wg(int n, __global const uint* in, __global uint* out,  // [n]
                    __global uint* block_sums) {                         // [nblocks + 1]
  __local uint vals[SCAN_BLOCK];
  __local uint tmp[SCAN_WG];
  const int b = get_group_id(0);
  const uint total = scan_block_wg(n, b * SCAN_BLOCK, 0u, in, out, vals, tmp);
  if (get_local_id(0) == 0) block_sums[b] = total;
}

// A short scan whole, by one work-group of SCAN_ONE_WG (the sort's) in one
// launch: the blocks in order, each starting from the sum of those before
// (the same integer sums as the three launches). The total goes where
// scan_block_sums_wg puts it.
__kernel __attribute__((reqd_work_group_size(SCAN_ONE_WG, 1, 1)))
void scan_one_group_wg(int n, __global const uint* in, __global uint* out,  // [n]
                       __global uint* block_sums) {                         // [nblocks + 1]
  __local uint vals[SCAN_BLOCK];
  __local uint tmp[SCAN_ONE_WG];
  const int nblocks = (n + SCAN_BLOCK - 1) / SCAN_BLOCK;
  uint carry = 0;
  for (int b = 0; b < nblocks; ++b) {
    carry += scan_block_wg(n, b * SCAN_BLOCK, carry, in, out, vals, tmp);
    barrier(CLK_LOCAL_MEM_FENCE);  // the block's vals are written out before the next one loads
  }
  if (get_local_id(0) == 0) block_sums[nblocks] = carry;
}

__kernel __attribute__((reqd_work_group_size(SCAN_WG, 1, 1)))
void scan_block_sums_wg(int nblocks, __global uint* block_sums) {  // [nblocks + 1], total at the end
  __local uint tmp[SCAN_WG];
  const uint total = group_scan_in_place(block_sums, (uint)nblocks, tmp);
  if (get_local_id(0) == 0) block_sums[nblocks] = total;
}

__kernel void scan_add(int n, __global uint* out, __global const uint* block_sums) {
  int i = get_global_id(0);
  if (i < n) out[i] += block_sums[i / SCAN_BLOCK];
}

// ---------------------------------------------------------------- emit
// Each on-screen Gaussian's first intersection slot: the exclusive scan of
// the tile counts in depth order, scattered back to the Gaussians' ids.
__kernel void isect_starts(int n,
                           __global const uint* order,    // [V] depth order
                           __global const uint* offsets,  // [V] exclusive scan in depth order
                           __global uint* isect_start) {  // [N] first slot of each Gaussian on screen
  const int s = get_global_id(0);
  if (s < n) isect_start[order[s]] = offsets[s];
}

// One intersection per (Gaussian, tile it reaches) from slot isect_start[g]
// on. The Gaussians are taken in index order, so their rects and records
// are read in the order they lie in memory (in depth order every Gaussian
// was a cache miss); the slots, and so every list, are those of the depth
// order.
__kernel void emit_isects(int n,
                          __global const uint* tile_counts,  // [N] 0: off screen
                          __global const int4* rects,        // [N]
                          __global const float* records,     // [N,REC_SIZE] of project_fwd
                          __global const uint* isect_start,  // [N] isect_starts
                          int tiles_x,
                          __global uint* tile_keys,          // [M] tile id per intersection
                          __global uint* isect_vals,         // [M] identity: the intersection's slot
                          __global uint* isect_gid) {        // [M] Gaussian id
  const int g = get_global_id(0);
  if (g >= n || tile_counts[g] == 0u) return;
  const int4 r = rects[g];
  uint e = isect_start[g];
  // The tiles project_fwd counted: the same test on the same floats.
  __global const float* q = records + (size_t)g * REC_SIZE;
  const float k = fmax(2.f * q[REC_THR], 0.f);
  for (int ty = r.y; ty <= r.w; ++ty)
    for (int tx = r.x; tx <= r.z; ++tx) {
      if (!tile_touched(q[REC_U], q[REC_V], q[REC_CA], q[REC_CB], q[REC_CC], k, tx, ty)) continue;
      tile_keys[e] = (uint)(ty * tiles_x + tx);
      isect_vals[e] = e;
      isect_gid[e] = (uint)g;
      ++e;
    }
}

// ---------------------------------------------------------------- ranges
// The blend kernels read ranges as int2, but here start and end of one tile
// are written by different work-items, so each is written as its own int:
// a store to one component of an int2 may be compiled as a load and store of
// the whole pair (NVIDIA's OpenCL does), which loses the other work-item's
// value.
__kernel void tile_ranges(int m, __global const uint* sorted_tile_keys,  // [M]
                          __global int* ranges) {                       // [tiles, 2], zeroed before
  int i = get_global_id(0);
  if (i >= m) return;
  uint t = sorted_tile_keys[i];
  if (i == 0 || sorted_tile_keys[i - 1] != t) ranges[2 * (size_t)t] = i;
  if (i == m - 1 || sorted_tile_keys[i + 1] != t) ranges[2 * (size_t)t + 1] = i + 1;
}
