// Blend backward: per tile, front to back, recomputing transmittance exactly
// as the forward pass did (never recovering it by division). For every
// (Gaussian, tile) intersection the tile's pixel contributions are summed in
// a fixed order (GPU layout: lanes, then work-items; CPU layout: rows per
// lane, then lanes) and written to that intersection's own slot: no atomics,
// so the result is bit-identical run to run on a device.
//
// The per-Gaussian gradient itself is blend_vjp in common.cl, which both
// layouts below call.
// Defines: BATCH, SEG, NO_STAGING (CPU layout below); GRAD_RGB, GRAD_FEAT,
// GRAD_DEPTH, GRAD_ALPHA, GRAD_DIST: 0 when that upstream gradient is zero
// everywhere (not given), so blend_vjp leaves their terms out (a zero term
// adds nothing; float rules forbid the compiler to drop x * 0 itself).

// GPU layout: SEG (a power of two dividing WG_SIZE) work-items sum each
// value's partials; PSTRIDE pads s_part's rows against bank conflicts.
#ifndef SEG
#define SEG 1
#endif
#define PSTRIDE (WG_SIZE + SEG)
// The segment sums' local array, or (SEG 1, none declared) s_part, unread.
#if SEG > 1
#define S_SEG s_seg
#else
#define S_SEG s_part
#endif

#if !NO_STAGING
// p[0, n) = 0 by the work-group, 16 floats per store where it can.
inline void zero_local(__local float* p, int n, int lid) {
  for (int i = lid * 16; i + 16 <= n; i += WG_SIZE * 16) vstore16((float16)0.f, 0, p + i);
  for (int t = n / 16 * 16 + lid; t < n; t += WG_SIZE) p[t] = 0.f;
}

// The GPU layout's fixed-order sum of each of `rows` values over the
// work-items' partials (row r of s_part, PSTRIDE apart; `per` rows per
// record, whose tile_reached mask is s_reach[r / per]), shared by blend_bwd
// and blend_weights. Only the work-items whose pixels the record may reach
// (the record is in both their lists) have a partial; every other
// work-item's would be +0, which leaves a sum unchanged (a sum that starts
// at +0 is never -0), so they are left out and the sums keep their bits.
// SEG 1: one work-item per value sums the partials in work-item order.
// SEG > 1: segment_sums (every work-item calls it) first has segment g of
// each row sum work-items g, g + SEG, ... into s_seg; then one work-item sums
// the SEG segment sums in order. PSTRIDE = WG_SIZE + SEG puts a warp's
// 32 / SEG rows x SEG segments in distinct banks.
//
// reached_sum: p[L] summed over the reached work-items L = g (mod step), in
// increasing L (work-item L has row L / (TILE / VW), column group
// L % (TILE / VW)).
ALWAYS_INLINE float reached_sum(__local const float* p, uint reach, int g, int step) {
  const int per_row = TILE / VW;  // work-items per tile row
  float s = 0.f;
  if (per_row % step == 0) {
    // L % step is the column group's own: the segment's groups of each
    // reached row, per_row / step of them, in a loop of fixed length that
    // the compiler unrolls. Bit VW c of `any` is set when column group c
    // has a reached column.
    uint any = reach >> TILE;
    for (int b = 1; b < VW; b <<= 1) any |= any >> b;
    for (uint rows = reach & ((1u << TILE) - 1u); rows != 0u;) {
      __local const float* row = p + pop_record(&rows) * per_row;
#pragma unroll
      for (int t = 0; t < per_row / step; ++t)
        if ((any >> (VW * (g + t * step))) & 1u) s += row[g + t * step];
    }
    return s;
  }
  uint groups = 0u;
  for (int c = 0; c < per_row; ++c)
    groups |= (((reach >> (TILE + c * VW)) & ((1u << VW) - 1u)) != 0u ? 1u : 0u) << c;
  for (uint rows = reach & ((1u << TILE) - 1u); rows != 0u;) {
    const int base = pop_record(&rows) * per_row;
    for (uint m = groups; m != 0u;) {
      const int L = base + pop_record(&m);
      if (L % step == g) s += p[L];
    }
  }
  return s;
}
inline void segment_sums(__local const float* s_part, __local float* s_seg, __local const uint* s_reach, int per,
                         int rows, int lid) {
  for (int k = lid; k < rows * SEG; k += WG_SIZE)
    s_seg[k] = reached_sum(s_part + (k / SEG) * PSTRIDE, s_reach[k / SEG / per], k % SEG, SEG);
  barrier(CLK_LOCAL_MEM_FENCE);
}
// Row r's total (after segment_sums when SEG > 1; s_seg unread when SEG is 1).
inline float row_total(__local const float* s_part, __local const float* s_seg, __local const uint* s_reach, int per,
                       int r) {
#if SEG == 1
  return reached_sum(s_part + r * PSTRIDE, s_reach[r / per], 0, 1);
#else
  float s = 0.f;
  for (int g = 0; g < SEG; ++g) s += s_seg[r * SEG + g];
  return s;
#endif
}
#endif

#if NO_STAGING
// CPU layout: one work-item per tile. The Gaussians are the outer loop and the
// tile's rows (VW pixels each) the inner one, with each row's running state
// in private arrays: a record is read once per tile, and the intersection's
// 13 partials are summed over rows as vectors (rows in order, per lane) and
// reduced across lanes once, not once per row. No barriers, so PoCL keeps
// the vectors in registers and cache. A row adds nothing for a Gaussian that
// none of its pixels blended.
__kernel __attribute__((reqd_work_group_size(1, 1, 1)))
void blend_bwd(int width, int height, int tiles_x,
               __constant const float* cam,          // [CAM_SIZE]
               __global const int2* ranges,          // [tiles]
               __global const uint* isect_vals,      // [M] sorted: intersection slot
               __global const uint* isect_gid,       // [M] by slot: Gaussian id
               __global const float* records,        // [N,REC_SIZE]
               __global const float* out_rgb,        // [3,H,W] forward outputs
               __global const float* out_feat,       // [3,H,W]
               __global const float* out_depth,      // [H,W]
               __global const float* out_aux,        // [4,H,W] T, A, mu, M2
               __global const int* out_last,         // [H,W]
               __global const float* v_rgb,          // [3,H,W] upstream gradients
               __global const float* v_feat,         // [3,H,W]
               __global const float* v_depth,        // [H,W]
               __global const float* v_alpha,        // [H,W]
               __global const float* v_dist,         // [H,W]
               __global float* isect_grads) {        // [M,G2_SIZE] by slot
  const int tile = get_group_id(0);
  const size_t npix = (size_t)width * height;
  const float dnear = cam[CAM_DNEAR], dfar = cam[CAM_DFAR];
  int2 range = ranges[tile];
  const int n = range.y - range.x;
  __global const uint* vals = isect_vals + range.x;

  RowTotals tot[WG_SIZE];
  BlendRun runs[WG_SIZE];
  vfloat pxs[WG_SIZE];
  float pys[WG_SIZE];
  // The tile's first pixel centre across.
  const float tile_x0 = tile_first_centre(tile, tiles_x);
  int bounds[WG_SIZE];
  int bound = 0;
  for (int row = 0; row < WG_SIZE; ++row) {
    PixelRow pr = pixel_row_of(tile, row, tiles_x, width, height);
    bounds[row] = 0;
    pxs[row] = pr.px;
    pys[row] = pr.py;
    runs[row].T = 1.f;
    runs[row].G_P = runs[row].A = runs[row].Q = 0.f;
    if (!ANY(pr.inside)) continue;
    tot[row] = load_totals(pr, width, npix, out_rgb, out_feat, out_depth, out_aux, out_last, v_rgb, v_feat, v_depth,
                           v_alpha, v_dist);
#if VW == 1
    int b = tot[row].last;
#else
    int b = 0;
    {
      int tmp[VW];
      VSTORE(tot[row].last, tmp);
      for (int l = 0; l < VW; ++l) b = max(b, tmp[l]);
    }
#endif
    bounds[row] = min(b, n);
    bound = max(bound, bounds[row]);
  }

  for (int j = 0; j < n; ++j) {
    const uint slot = vals[j];
    __global float* o2 = isect_grads + (size_t)slot * G2_SIZE;
    vfloat s_u = 0.f, s_v = 0.f, s_ca = 0.f, s_cb = 0.f, s_cc = 0.f, s_op = 0.f;
    vfloat s_r = 0.f, s_g = 0.f, s_b = 0.f, s_f0 = 0.f, s_f1 = 0.f, s_f2 = 0.f, s_z = 0.f;
    int touched = 0;
    if (j < bound) {
      __global const float* q = records + (size_t)isect_gid[slot] * REC_SIZE;
      const BlendRec rec = BLEND_REC_LOAD(q);
      const float zj = dist_depth_vjp(rec.z, dnear, dfar);
      const float reach = tile_row_reach(q, tile_x0);
      for (int row = 0; row < WG_SIZE; ++row) {
        if (j >= bounds[row]) continue;
        const float dy = rec.v - pys[row];
        if (!(fabs(dy) <= reach)) continue;  // no pixel of the row can blend it
        BlendVjp d;
        if (!blend_vjp(rec, rec.u - pxs[row], dy, (vint)j < tot[row].last, zj, &tot[row], &runs[row], &d)) continue;
        touched = 1;
        s_u += d.u;
        s_v += d.v;
        s_ca += d.ca;
        s_cb += d.cb;
        s_cc += d.cc;
        s_op += d.op;
#if GRAD_RGB
        s_r += d.r;
        s_g += d.g;
        s_b += d.b;
#endif
#if GRAD_FEAT
        s_f0 += d.f0;
        s_f1 += d.f1;
        s_f2 += d.f2;
#endif
#if GRAD_DEPTH
        s_z += d.z_depth;
#endif
#if GRAD_DIST
        s_z += d.z_dist;
#endif
      }
    }
    if (!touched) {
      for (int c = 0; c < G2_SIZE; ++c) o2[c] = 0.f;
      continue;
    }
    o2[G2_U] = HSUM(s_u);
    o2[G2_V] = HSUM(s_v);
    o2[G2_CA] = HSUM(s_ca);
    o2[G2_CB] = HSUM(s_cb);
    o2[G2_CC] = HSUM(s_cc);
    o2[G2_OPACITY] = HSUM(s_op);
    o2[G2_RGB] = HSUM(s_r);
    o2[G2_RGB + 1] = HSUM(s_g);
    o2[G2_RGB + 2] = HSUM(s_b);
    o2[G2_FEAT] = HSUM(s_f0);
    o2[G2_FEAT + 1] = HSUM(s_f1);
    o2[G2_FEAT + 2] = HSUM(s_f2);
    o2[G2_Z] = HSUM(s_z);
  }
}
#else
__kernel __attribute__((reqd_work_group_size(WG_SIZE, 1, 1)))
void blend_bwd(int width, int height, int tiles_x,
               __constant const float* cam,          // [CAM_SIZE]
               __global const int2* ranges,          // [tiles]
               __global const uint* isect_vals,      // [M] sorted: intersection slot
               __global const uint* isect_gid,       // [M] by slot: Gaussian id
               __global const float* records,        // [N,REC_SIZE]
               __global const float* out_rgb,        // [3,H,W] forward outputs
               __global const float* out_feat,       // [3,H,W]
               __global const float* out_depth,      // [H,W]
               __global const float* out_aux,        // [4,H,W] T, A, mu, M2
               __global const int* out_last,         // [H,W]
               __global const float* v_rgb,          // [3,H,W] upstream gradients
               __global const float* v_feat,         // [3,H,W]
               __global const float* v_depth,        // [H,W]
               __global const float* v_alpha,        // [H,W]
               __global const float* v_dist,         // [H,W]
               __global float* isect_grads) {        // [M,G2_SIZE] by slot
  __local float s_rec[BATCH * REC_SIZE];
  __local uint s_slot[BATCH];
  __local uint s_reach[BATCH];                     // tile_reached
  __local uint s_list[REACH_LISTS * LIST_WORDS];  // reach_lists
  __local float s_part[BATCH * G2_SIZE * PSTRIDE];
#if SEG > 1
  __local float s_seg[BATCH * G2_SIZE * SEG];
#endif
  __local int s_bound;
  const int lid = get_local_id(0);
  PixelRow pr = pixel_row(tiles_x, width, height);
  __local const uint *rows = ROW_LIST(pr), *cols = COL_LIST(pr);
  const size_t npix = (size_t)width * height;

  // Upstream gradients and forward totals of this row's pixels.
  const RowTotals tot = load_totals(pr, width, npix, out_rgb, out_feat, out_depth, out_aux, out_last, v_rgb, v_feat,
                                    v_depth, v_alpha, v_dist);
  const vint last = tot.last;
  const float dnear = cam[CAM_DNEAR], dfar = cam[CAM_DFAR];

  int2 range = ranges[pr.tile];
  int n = range.y - range.x;
  if (lid == 0) s_bound = 0;
  reach_lists_clear(s_list, lid);
  barrier(CLK_LOCAL_MEM_FENCE);
  {
    int mx = 0;
#if VW == 1
    mx = last;
#else
    int tmp[VW];
    VSTORE(last, tmp);
    for (int l = 0; l < VW; ++l) mx = max(mx, tmp[l]);
#endif
    atomic_max(&s_bound, mx);
  }
  barrier(CLK_LOCAL_MEM_FENCE);
  const int bound = min(s_bound, n);

  BlendRun run;
  run.T = 1.f;
  run.G_P = run.A = run.Q = 0.f;
  for (int b0 = 0; b0 < bound; b0 += BATCH) {
    int nb = min(BATCH, bound - b0);
    barrier(CLK_LOCAL_MEM_FENCE);
    for (int i = lid; i < nb; i += WG_SIZE) {
      uint slot = isect_vals[range.x + b0 + i];
      uint gid = isect_gid[slot];
      s_slot[i] = slot;
      stage_record(s_rec, i, records, gid);
      s_reach[i] = tile_reached(s_rec + i * REC_SIZE, pr.tile, tiles_x);
      reach_lists_add(s_list, i, s_reach[i]);
    }
    barrier(CLK_LOCAL_MEM_FENCE);
    // The records that may reach this work-item's pixels, in list order;
    // each gets its partials here, the sums below read no other.
    for (int w = 0; w < LIST_WORDS; ++w)
      for (uint m = rows[w] & cols[w]; m != 0u;) {
        const int j = w * 32 + pop_record(&m);
        __local float* part = s_part + j * G2_SIZE * PSTRIDE + lid;
        __local const float* q = s_rec + j * REC_SIZE;
        const BlendRec rec = BLEND_REC_LOAD(q);
        BlendVjp d;
        if (!blend_vjp(rec, rec.u - pr.px, rec.v - pr.py, (vint)(b0 + j) < last, dist_depth_vjp(rec.z, dnear, dfar),
                       &tot, &run, &d)) {
          for (int c = 0; c < G2_SIZE; ++c) part[c * PSTRIDE] = 0.f;
          continue;
        }
        part[G2_U * PSTRIDE] = HSUM(d.u);
        part[G2_V * PSTRIDE] = HSUM(d.v);
        part[G2_CA * PSTRIDE] = HSUM(d.ca);
        part[G2_CB * PSTRIDE] = HSUM(d.cb);
        part[G2_CC * PSTRIDE] = HSUM(d.cc);
        part[G2_OPACITY * PSTRIDE] = HSUM(d.op);
        part[G2_RGB * PSTRIDE] = HSUM(d.r);
        part[(G2_RGB + 1) * PSTRIDE] = HSUM(d.g);
        part[(G2_RGB + 2) * PSTRIDE] = HSUM(d.b);
        part[G2_FEAT * PSTRIDE] = HSUM(d.f0);
        part[(G2_FEAT + 1) * PSTRIDE] = HSUM(d.f1);
        part[(G2_FEAT + 2) * PSTRIDE] = HSUM(d.f2);
        part[G2_Z * PSTRIDE] = HSUM(d.z_depth + d.z_dist);
      }
    barrier(CLK_LOCAL_MEM_FENCE);
    // Sum the work-items' partials of each value (row r = j * G2_SIZE + c of
    // s_part) into the intersection's slot, in a fixed order.
    reach_lists_clear(s_list, lid);  // (the walk is done with them)
    const int values = nb * G2_SIZE;
#if SEG > 1
    segment_sums(s_part, s_seg, s_reach, G2_SIZE, values, lid);
#endif
    for (int r = lid; r < values; r += WG_SIZE)
      isect_grads[(size_t)s_slot[r / G2_SIZE] * G2_SIZE + r % G2_SIZE] = row_total(s_part, S_SEG, s_reach, G2_SIZE, r);
  }
  // Intersections behind every pixel's last blended Gaussian get zeros.
  for (int k = bound + lid; k < n; k += WG_SIZE) {
    uint slot = isect_vals[range.x + k];
    for (int c = 0; c < G2_SIZE; ++c) isect_grads[(size_t)slot * G2_SIZE + c] = 0.f;
  }
}
#endif

// Blend weights: for every (Gaussian, tile) intersection, the sum over the
// tile's pixels of the Gaussian's blending weight w = alpha T, written to the
// slot's G2_FEAT value (every other value 0), so project_bwd's feature
// gradient is each Gaussian's summed weight. It is blend_bwd of an upstream
// gradient of 1 on feature channel 0 and nothing else, without the forward
// pass and the rest of the vector-Jacobian product: each pixel keeps its
// transmittance and stop as blend_fwd does (a Gaussian that would take T
// below T_MIN stops the pixel and is not blended), so the weights are
// blend_fwd's, and they are summed in blend_bwd's order (CPU layout: rows in
// order per lane, then lanes; GPU layout: the plan's VW, work-items and SEG),
// which makes the sums equal blend_bwd's bit for bit. For the importance
// prune (host/render/importance.h), which needs nothing else. With UPSTREAM
// 1 each pixel's weight is multiplied by its factor in `upstream` as
// blend_bwd multiplies it by the feature's upstream gradient (the removal's
// view checks, apps/removal/fill.cpp, count only some pixels); with
// UPSTREAM 0 `upstream` is not read.
#ifndef UPSTREAM
#define UPSTREAM 0
#endif
#if UPSTREAM
#define UPSTREAM_TIMES(up, w) ((up) * (w))
#else
#define UPSTREAM_TIMES(up, w) (w)
#endif
#if NO_STAGING
__kernel __attribute__((reqd_work_group_size(1, 1, 1)))
void blend_weights(int width, int height, int tiles_x,
                   __global const int2* ranges,       // [tiles]
                   __global const uint* isect_vals,   // [M] sorted: intersection slot
                   __global const uint* isect_gid,    // [M] by slot: Gaussian id
                   __global const float* records,     // [N,REC_SIZE]
                   __global const float* upstream,    // [H,W] with UPSTREAM: each pixel's factor
                   __global float* isect_weights) {   // [M] by slot: the weights' sum
  const int tile = get_group_id(0);
  int2 range = ranges[tile];
  const int n = range.y - range.x;
  __global const uint* vals = isect_vals + range.x;

  vfloat Ts[WG_SIZE], pxs[WG_SIZE];
#if UPSTREAM
  vfloat ups[WG_SIZE];
#endif
  vint dones[WG_SIZE];
  float pys[WG_SIZE];
  const float tile_x0 = tile_first_centre(tile, tiles_x);
  int live = 0;  // rows with a pixel still blending
  for (int row = 0; row < WG_SIZE; ++row) {
    PixelRow pr = pixel_row_of(tile, row, tiles_x, width, height);
#if UPSTREAM
    ups[row] = load_row(upstream, pr, width);
#endif
    pxs[row] = pr.px;
    pys[row] = pr.py;
    Ts[row] = 1.f;
    dones[row] = NOT(pr.inside);
    if (ANY(NOT(dones[row]))) ++live;
  }

  for (int j = 0; j < n; ++j) {
    vfloat s_w = 0.f;
    if (live > 0) {
      __global const float* q = records + (size_t)isect_gid[vals[j]] * REC_SIZE;
      const float u = q[REC_U], v = q[REC_V];
      const float reach = tile_row_reach(q, tile_x0);
      for (int row = 0; row < WG_SIZE; ++row) {
        if (!ANY(NOT(dones[row]))) continue;
        const float dy = v - pys[row];
        if (!(fabs(dy) <= reach)) continue;  // no pixel of the row can blend it
        const vfloat sigma = blend_sigma(q[REC_CA], q[REC_CB], q[REC_CC], u - pxs[row], dy);
        const vfloat alpha = fmin(q[REC_OPACITY] * blend_falloff(sigma), ALPHA_MAX);
        vint ok = NOT(dones[row]) & (sigma >= 0.f) & (alpha >= ALPHA_MIN);
        if (!ANY(ok)) continue;
        const vfloat T = Ts[row];
        const vfloat Tn = T * (1.f - alpha);
        const vint stop = ok & (Tn < T_MIN);
        dones[row] = dones[row] | stop;
        ok = ok & NOT(stop);
        s_w += UPSTREAM_TIMES(ups[row], select((vfloat)0.f, alpha * T, ok));
        Ts[row] = select(T, Tn, ok);
        if (!ANY(NOT(dones[row]))) --live;
      }
    }
    isect_weights[vals[j]] = HSUM(s_w);
  }
}
#else
__kernel __attribute__((reqd_work_group_size(WG_SIZE, 1, 1)))
void blend_weights(int width, int height, int tiles_x,
                   __global const int2* ranges,       // [tiles]
                   __global const uint* isect_vals,   // [M] sorted: intersection slot
                   __global const uint* isect_gid,    // [M] by slot: Gaussian id
                   __global const float* records,     // [N,REC_SIZE]
                   __global const float* upstream,    // [H,W] with UPSTREAM: each pixel's factor
                   __global float* isect_weights) {   // [M] by slot: the weights' sum
  __local float s_rec[BATCH * REC_SIZE];
  __local uint s_slot[BATCH];
  __local uint s_reach[BATCH];                     // tile_reached
  __local uint s_list[REACH_LISTS * LIST_WORDS];  // reach_lists
  __local float s_part[BATCH * PSTRIDE];
#if SEG > 1
  __local float s_seg[BATCH * SEG];
#endif
  __local int s_alive;
  const int lid = get_local_id(0);
  PixelRow pr = pixel_row(tiles_x, width, height);
  __local const uint *rows = ROW_LIST(pr), *cols = COL_LIST(pr);
  int2 range = ranges[pr.tile];
  const int n = range.y - range.x;

  vfloat T = 1.f;
  vint done = NOT(pr.inside);
#if UPSTREAM
  const vfloat up = load_row(upstream, pr, width);
#endif
  int b0 = 0;
  for (; b0 < n; b0 += BATCH) {
    const int nb = min(BATCH, n - b0);
    barrier(CLK_LOCAL_MEM_FENCE);
    if (lid == 0) s_alive = 0;
    for (int i = lid; i < nb; i += WG_SIZE) {
      uint slot = isect_vals[range.x + b0 + i];
      s_slot[i] = slot;
      uint gid = isect_gid[slot];
      stage_record(s_rec, i, records, gid);
      s_reach[i] = tile_reached(s_rec + i * REC_SIZE, pr.tile, tiles_x);
    }
    // Zeros for the records that blend at none of a work-item's pixels (not
    // in its lists, out of reach, or after its pixels stopped); the walk of
    // the lists writes the others. The whole block at once, in vectors.
    zero_local(s_part, nb * PSTRIDE, lid);
    barrier(CLK_LOCAL_MEM_FENCE);
    reach_lists(s_reach, nb, s_list, lid);
    if (ANY(NOT(done))) atomic_or(&s_alive, 1);
    barrier(CLK_LOCAL_MEM_FENCE);
    if (!s_alive) break;  // every pixel of the tile stopped: the rest get zeros below
    for (int w = 0; w < LIST_WORDS && ANY(NOT(done)); ++w)
      for (uint m = rows[w] & cols[w];;) {
        vfloat sigma;
        const int j = next_in_reach(&m, w, s_rec, pr, &sigma);
        if (j < 0) break;
        __local const float* q = s_rec + j * REC_SIZE;
        const vfloat alpha = fmin(q[REC_OPACITY] * blend_falloff(sigma), ALPHA_MAX);
        vint ok = NOT(done) & (sigma >= 0.f) & (alpha >= ALPHA_MIN);
        const vfloat Tn = T * (1.f - alpha);
        const vint stop = ok & (Tn < T_MIN);
        done = done | stop;
        ok = ok & NOT(stop);
        s_part[j * PSTRIDE + lid] = HSUM(UPSTREAM_TIMES(up, select((vfloat)0.f, alpha * T, ok)));
        T = select(T, Tn, ok);
      }
    barrier(CLK_LOCAL_MEM_FENCE);
    // One value per Gaussian, summed over the work-items as blend_bwd sums.
#if SEG > 1
    segment_sums(s_part, s_seg, s_reach, 1, nb, lid);
#endif
    for (int r = lid; r < nb; r += WG_SIZE) {
      isect_weights[s_slot[r]] = row_total(s_part, S_SEG, s_reach, 1, r);
    }
  }
  for (int k = b0 + lid; k < n; k += WG_SIZE) isect_weights[isect_vals[range.x + k]] = 0.f;
}
#endif
