// A work-group-parallel LSD radix sort of (key, value) pairs for GPUs: one
// pass per digit of RS_BITS bits, three launches a pass.
//   rs_count:   each work-group owns a contiguous range of keys (whole tiles
//               of TILE_KEYS keys) and counts its digits in local memory.
//   rs_scan:    one work-group turns the counts, digit-major
//               (counts[digit * groups + group]), into exclusive offsets:
//               where the group's first key of each digit goes.
//   rs_scatter: each work-group walks its tiles in order; inside a tile every
//               key gets its rank among the tile's keys of lower digits and of
//               the same digit at lower indices, so the pass is stable.
//   rs_one_group: all of it, every pass, by one work-group in one launch,
//               for sorts of a few tiles (or two halves by two groups,
//               joined by rs_merge_runs: a simulator runs them on two
//               threads).
// Everything is integer counting, so the result is the one stable order:
// the same whatever the digit width, work-group size, tile or group count.
// No global atomics; the counters in local memory belong to one work-item
// each.
// Defines: RS_BITS (digit bits), RS_WG (work-group size, a multiple of
// 1 << RS_BITS and a power of two), RS_IPT (keys per work-item and tile).
//
// CPUs take the block sort at the end of the file instead (define
// RADIX_BLOCK): 8-bit digits, one work-item per block of RADIX_BLOCK keys,
// no barriers; a few long blocks suit a few cores.

#ifdef RS_BITS

#define BINS (1 << RS_BITS)
#define TILE_KEYS (RS_WG * RS_IPT)
// A work-item's counters form a column of cnt[digit][work-item]; the scan
// reads rows in runs of BINS. One padding word per 32 keeps both patterns
// free of bank conflicts.
#define PAD(i) ((i) + ((i) >> 5))
#define CNT_WORDS PAD(BINS * RS_WG)

// The keys of group g: [begin, end) of n, tiles_per_group tiles.
void rs_range(uint n, uint tiles_per_group, uint g, uint* begin, uint* end) {
  const ulong b = (ulong)g * tiles_per_group * TILE_KEYS;
  const ulong e = b + (ulong)tiles_per_group * TILE_KEYS;
  *begin = (uint)min(b, (ulong)n);
  *end = (uint)min(e, (ulong)n);
}

// Counts the digits of keys [begin, end) in cnt (a column per work-item),
// then sums them: work-item d < BINS gets the count of digit d (the others
// 0). part: [RS_WG].
uint rs_count_digits(__global const uint* keys, uint begin, uint end, int shift, __local uint* cnt,
                     __local uint* part) {
  const uint lid = get_local_id(0);
  for (uint d = 0; d < BINS; ++d) cnt[PAD(d * RS_WG + lid)] = 0u;
  for (uint i = begin + lid; i < end; i += RS_WG) cnt[PAD(((keys[i] >> shift) & (BINS - 1)) * RS_WG + lid)]++;
  barrier(CLK_LOCAL_MEM_FENCE);
  // Row d holds RS_WG counters: each work-item sums a run of BINS of them,
  // then the first BINS work-items add their row's RS_WG / BINS runs.
  uint s = 0;
  for (uint j = 0; j < BINS; ++j) s += cnt[PAD(lid * BINS + j)];
  part[lid] = s;
  barrier(CLK_LOCAL_MEM_FENCE);
  uint t = 0;
  if (lid < BINS)
    for (uint j = 0; j < RS_WG / BINS; ++j) t += part[lid * (RS_WG / BINS) + j];
  return t;
}

__kernel __attribute__((reqd_work_group_size(RS_WG, 1, 1)))
void rs_count(uint n, int shift, uint tiles_per_group,
              __global const uint* keys,  // [n]
              __global uint* counts) {    // [BINS, groups] digit-major
  __local uint cnt[CNT_WORDS];
  __local uint part[RS_WG];
  const uint lid = get_local_id(0), g = get_group_id(0), groups = get_num_groups(0);
  uint begin, end;
  rs_range(n, tiles_per_group, g, &begin, &end);
  const uint t = rs_count_digits(keys, begin, end, shift, cnt, part);
  if (lid < BINS) counts[(size_t)lid * groups + g] = t;
}

// One work-group: counts [BINS * groups] -> exclusive prefix sums, in place.
__kernel __attribute__((reqd_work_group_size(RS_WG, 1, 1)))
void rs_scan(uint groups, __global uint* counts) {  // [BINS * groups]
  __local uint tmp[RS_WG];
  group_scan_in_place(counts, BINS * groups, tmp);
}

// Moves keys [begin, end) and their values to their places of this pass,
// tile by tile in order: base[d] (set by work-item d < BINS) is where the
// range's first key of digit d goes. Local arrays as in rs_scatter.
void rs_scatter_tiles(uint begin, uint end, int shift,
                      __global const uint* keys_in, __global const uint* vals_in,
                      __global uint* keys_out, __global uint* vals_out,
                      __local uint* cnt, __local uint* tmp, __local uint* lkeys, __local uint* lvals,
                      __local uint* base, __local uint* dest) {
  const uint lid = get_local_id(0);
  const uint ntiles = (end - begin + TILE_KEYS - 1) / TILE_KEYS;
  // This work-item's keys of a tile: a contiguous run of RS_IPT, so that
  // rank order (digit, work-item, run position) is index order within a
  // digit. Keys past the end take the last digit and rank after every real
  // key.
  uint k[RS_IPT], v[RS_IPT], r[RS_IPT];
  for (uint t = 0; t < ntiles; ++t) {
    const uint t0 = begin + t * TILE_KEYS;
    const uint nvalid = min((uint)TILE_KEYS, end - t0);
    for (uint d = 0; d < BINS; ++d) cnt[PAD(d * RS_WG + lid)] = 0u;
    for (uint j = 0; j < RS_IPT; ++j) {
      const uint idx = lid * RS_IPT + j;
      uint d = BINS - 1;
      if (idx < nvalid) {
        k[j] = keys_in[t0 + idx];
        v[j] = vals_in[t0 + idx];
        d = (k[j] >> shift) & (BINS - 1);
      }
      const uint c = PAD(d * RS_WG + lid);
      r[j] = cnt[c];
      cnt[c] = r[j] + 1u;
    }
    barrier(CLK_LOCAL_MEM_FENCE);
    // Exclusive scan of cnt in digit-major order: a run of BINS per work-item.
    uint s = 0;
    for (uint j = 0; j < BINS; ++j) s += cnt[PAD(lid * BINS + j)];
    uint all;
    uint acc = group_exclusive_scan(s, tmp, &all);
    for (uint j = 0; j < BINS; ++j) {
      const uint c = PAD(lid * BINS + j);
      const uint x = cnt[c];
      cnt[c] = acc;
      acc += x;
    }
    barrier(CLK_LOCAL_MEM_FENCE);
    if (lid < BINS) {
      // The tile's first rank of digit lid, and its keys of that digit (the
      // padding keys sit at the end of the last digit: ranks [nvalid, TILE_KEYS)).
      const uint first = cnt[PAD(lid * RS_WG)];
      const uint count = (lid + 1 < BINS ? cnt[PAD((lid + 1) * RS_WG)] : nvalid) - first;
      dest[lid] = base[lid] - first;  // modulo 2^32: dest + rank is in range
      base[lid] += count;
    }
    for (uint j = 0; j < RS_IPT; ++j) {
      if (lid * RS_IPT + j < nvalid) {
        const uint rank = cnt[PAD(((k[j] >> shift) & (BINS - 1)) * RS_WG + lid)] + r[j];
        lkeys[rank] = k[j];
        lvals[rank] = v[j];
      }
    }
    barrier(CLK_LOCAL_MEM_FENCE);
    // Write the tile in rank order: each digit's keys land in a run.
    for (uint i = lid; i < nvalid; i += RS_WG) {
      const uint key = lkeys[i];
      const uint pos = dest[(key >> shift) & (BINS - 1)] + i;
      keys_out[pos] = key;
      vals_out[pos] = lvals[i];
    }
    // No barrier needed here: the next tile writes lkeys, lvals and dest
    // only after two more barriers, and the counters read above (other
    // work-items' cells) were read before the last one.
  }
}

__kernel __attribute__((reqd_work_group_size(RS_WG, 1, 1)))
void rs_scatter(uint n, int shift, uint tiles_per_group,
                __global const uint* keys_in,   // [n]
                __global const uint* vals_in,   // [n]
                __global uint* keys_out,        // [n]
                __global uint* vals_out,        // [n]
                __global const uint* offsets) { // [BINS, groups] of rs_scan
  // (Letting the tile's keys share the counters' memory, with one more
  // barrier, is miscompiled by PoCL 3.1: wrong ranks, then writes out of
  // bounds. Oclgrind finds nothing wrong with it.)
  __local uint cnt[CNT_WORDS];
  __local uint tmp[RS_WG];
  __local uint lkeys[TILE_KEYS], lvals[TILE_KEYS];  // the tile in rank order
  __local uint base[BINS];  // where the group's next key of each digit goes
  __local uint dest[BINS];  // the tile's key of rank i and digit d goes to dest[d] + i
  const uint lid = get_local_id(0), g = get_group_id(0), groups = get_num_groups(0);
  if (lid < BINS) base[lid] = offsets[(size_t)lid * groups + g];
  uint begin, end;
  rs_range(n, tiles_per_group, g, &begin, &end);
  rs_scatter_tiles(begin, end, shift, keys_in, vals_in, keys_out, vals_out, cnt, tmp, lkeys, lvals, base, dest);
}

// A small sort whole: one work-group runs every pass over all its keys in
// one launch, for frames of a few tiles, where the three launches of each
// pass cost more than its work. Each pass counts the digits, scans the BINS
// totals and scatters as rs_scatter does, so the order is the same. Passes
// alternate between the pairs as the host's do: the sorted keys end in
// (keys_in, vals_in) after an even number of passes, in (keys_out, vals_out)
// after an odd one; a global barrier lets each pass read what the last one
// wrote. Work-group g sorts its own run, keys [g * run, (g + 1) * run) of n
// (run >= n: one group, the whole sort); rs_merge_runs joins two runs.
__kernel __attribute__((reqd_work_group_size(RS_WG, 1, 1)))
void rs_one_group(uint n, int bits, uint run,
                  __global uint* keys_in, __global uint* vals_in,     // [n] the keys to sort
                  __global uint* keys_out, __global uint* vals_out) { // [n] scratch
  {
    const uint begin = (uint)min((ulong)n, (ulong)get_group_id(0) * run);
    n = min(n - begin, run);
    keys_in += begin; vals_in += begin; keys_out += begin; vals_out += begin;
  }
  __local uint cnt[CNT_WORDS];
  __local uint part[RS_WG];
  __local uint tmp[RS_WG];
  __local uint lkeys[TILE_KEYS], lvals[TILE_KEYS];
  __local uint base[BINS];
  __local uint dest[BINS];
  const uint lid = get_local_id(0);
  // One loop of steps, each a pass's count (t 0) or one of its tiles: PoCL
  // 3.1 miscompiles the tile loop's barriers nested in a loop of passes
  // (wrong orders from the second tile on; Oclgrind finds nothing wrong).
  const uint ntiles = (n + TILE_KEYS - 1) / TILE_KEYS;
  const uint steps = (uint)((bits + RS_BITS - 1) / RS_BITS) * (ntiles + 1);
  for (uint step = 0; step < steps; ++step) {
    const uint pass = step / (ntiles + 1), t = step % (ntiles + 1);
    const int shift = (int)pass * RS_BITS;
    __global uint* const src_k = pass & 1 ? keys_out : keys_in;
    __global uint* const src_v = pass & 1 ? vals_out : vals_in;
    __global uint* const dst_k = pass & 1 ? keys_in : keys_out;
    __global uint* const dst_v = pass & 1 ? vals_in : vals_out;
    if (t == 0) {
      // The last pass's writes are done.
      barrier(CLK_GLOBAL_MEM_FENCE | CLK_LOCAL_MEM_FENCE);
      const uint c = rs_count_digits(src_k, 0u, n, shift, cnt, part);
      uint all;
      const uint first = group_exclusive_scan(c, tmp, &all);  // over the BINS totals; the rest add 0
      if (lid < BINS) base[lid] = first;
    } else {
      const uint t0 = (t - 1) * TILE_KEYS;
      rs_scatter_tiles(t0, min(n, t0 + TILE_KEYS), shift, src_k, src_v, dst_k, dst_v, cnt, tmp, lkeys, lvals, base,
                       dest);
    }
  }
}

// The stable merge of two sorted runs, [0, run) and [run, n) of the input
// pair, into the output pair: a key of the first run goes after the keys of
// the second that are smaller, a key of the second after those of the first
// that are smaller or equal, so equal keys keep index order. One work-item
// per key, a binary search in the other run; each output slot is written
// once.
__kernel void rs_merge_runs(uint n, uint run,
                            __global const uint* keys_in, __global const uint* vals_in,  // [n] two sorted runs
                            __global uint* keys_out, __global uint* vals_out) {          // [n] sorted
  const uint i = get_global_id(0);
  if (i >= n) return;
  const uint key = keys_in[i];
  const bool first = i < run;
  uint lo = first ? run : 0u, hi = first ? n : run;
  while (lo < hi) {
    const uint mid = lo + (hi - lo) / 2u, k = keys_in[mid];
    if (first ? k < key : k <= key)
      lo = mid + 1u;
    else
      hi = mid;
  }
  const uint pos = first ? i + (lo - run) : (i - run) + lo;
  keys_out[pos] = key;
  vals_out[pos] = vals_in[i];
}
#endif  // RS_BITS

// ---------------------------------------------------------------- block sort
#ifdef RADIX_BLOCK
// One LSD pass over 8 bits. Each work-item owns a contiguous block, so the
// scatter is stable; counts are digit-major: counts[digit * nblocks + block].
__kernel void radix_hist(int n, int shift, __global const uint* keys,
                         __global uint* counts, int nblocks) {  // [256 * nblocks]
  int b = get_global_id(0);
  if (b >= nblocks) return;
  uint h[256];
  for (int d = 0; d < 256; ++d) h[d] = 0;
  int end = min(n, (b + 1) * RADIX_BLOCK);
  for (int i = b * RADIX_BLOCK; i < end; ++i) h[(keys[i] >> shift) & 255u]++;
  for (int d = 0; d < 256; ++d) counts[d * nblocks + b] = h[d];
}

// One work-group of 256: exclusive scan of counts in digit-major order.
__kernel __attribute__((reqd_work_group_size(256, 1, 1)))
void radix_scan(int nblocks, __global uint* counts) {
  __local uint totals[256];
  int d = get_local_id(0);
  uint acc = 0;
  for (int b = 0; b < nblocks; ++b) {
    uint v = counts[d * nblocks + b];
    counts[d * nblocks + b] = acc;
    acc += v;
  }
  totals[d] = acc;
  barrier(CLK_LOCAL_MEM_FENCE);
  if (d == 0) {
    uint run = 0;
    for (int i = 0; i < 256; ++i) {
      uint v = totals[i];
      totals[i] = run;
      run += v;
    }
  }
  barrier(CLK_LOCAL_MEM_FENCE);
  uint base = totals[d];
  for (int b = 0; b < nblocks; ++b) counts[d * nblocks + b] += base;
}

__kernel void radix_scatter(int n, int shift,
                            __global const uint* keys_in, __global const uint* vals_in,
                            __global uint* keys_out, __global uint* vals_out,
                            __global const uint* counts, int nblocks) {
  int b = get_global_id(0);
  if (b >= nblocks) return;
  uint pos[256];
  for (int d = 0; d < 256; ++d) pos[d] = counts[d * nblocks + b];
  int end = min(n, (b + 1) * RADIX_BLOCK);
  for (int i = b * RADIX_BLOCK; i < end; ++i) {
    uint k = keys_in[i];
    uint p = pos[(k >> shift) & 255u]++;
    keys_out[p] = k;
    vals_out[p] = vals_in[i];
  }
}
#endif  // RADIX_BLOCK
