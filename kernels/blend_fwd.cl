// Blend forward, front to back in depth order (docs/rasterizer.md,
// "Blending"). Outputs are planar [C,H,W]. Two layouts share the per-record
// step (blend_step):
// - GPU (staging): one work-group per 16x16 tile, VW pixels per work-item,
//   records staged through local memory in batches.
// - CPU (NO_STAGING): one work-item per tile, records in the outer loop and
//   the tile's rows (VW pixels each) in the inner one, like the backward:
//   a record is read once per tile and its reach in rows computed once.
// Defines: BATCH (records staged per round); WITH_FEAT (0: the feature
// planes are not blended and come out zero).

// The running state of VW pixels.
typedef struct {
  vfloat T, r, g, b, f0, f1, f2, dsum, A, mu, M2;
  vint last, count, done;
} BlendState;

inline void blend_state_init(BlendState* s, vint inside) {
  s->T = 1.f;
  s->r = s->g = s->b = s->f0 = s->f1 = s->f2 = s->dsum = 0.f;
  s->A = s->mu = s->M2 = 0.f;
  s->last = s->count = 0;
  s->done = NOT(inside);
}

// Blends record `index` (0-based in the tile's list), of opacity o, colour
// c, feature f, depth z and distortion depth m, at sigma into the lanes not
// yet done. Lanes whose alpha fails add exact zeros, so a caller may skip a
// record that no lane blends without changing a bit.
ALWAYS_INLINE void blend_step(BlendState* s, vfloat sigma, float o, float3 c, float3 f, float z, float m,
                              int index) {
  vfloat alpha = fmin(o * blend_falloff(sigma), ALPHA_MAX);
  vint ok = NOT(s->done) & (sigma >= 0.f) & (alpha >= ALPHA_MIN);
  vfloat Tn = s->T * (1.f - alpha);
  vint stop = ok & (Tn < T_MIN);
  s->done = s->done | stop;
  ok = ok & NOT(stop);
  vfloat w = select((vfloat)0.f, alpha * s->T, ok);
  s->r += w * c.x;
  s->g += w * c.y;
  s->b += w * c.z;
#if WITH_FEAT
  s->f0 += w * f.x;
  s->f1 += w * f.y;
  s->f2 += w * f.z;
#endif
  s->dsum += w * z;
  // Weighted Welford update of the distortion depth m (stable variance).
  vfloat An = s->A + w;
  vfloat mun = select(s->mu, s->mu + (w / An) * (m - s->mu), ok);
  s->M2 += w * (m - s->mu) * (m - mun);
  s->A = An;
  s->mu = mun;
  s->T = select(s->T, Tn, ok);
  s->last = select(s->last, (vint)(index + 1), ok);
  s->count = select(s->count, s->count + (vint)1, ok);
}

inline void store_state(const BlendState* s, PixelRow pr, int width, size_t npix, __constant const float* cam,
                        __global float* out_rgb, __global float* out_feat, __global float* out_depth,
                        __global float* out_alpha, __global float* out_dist, __global float* out_aux,
                        __global int* out_last, __global int* out_count) {
  store_row(s->r + s->T * cam[CAM_BG], out_rgb, pr, width);
  store_row(s->g + s->T * cam[CAM_BG + 1], out_rgb + npix, pr, width);
  store_row(s->b + s->T * cam[CAM_BG + 2], out_rgb + 2 * npix, pr, width);
  store_row(s->f0, out_feat, pr, width);
  store_row(s->f1, out_feat + npix, pr, width);
  store_row(s->f2, out_feat + 2 * npix, pr, width);
  store_row(s->dsum, out_depth, pr, width);
  store_row(1.f - s->T, out_alpha, pr, width);
  store_row(s->A * s->M2, out_dist, pr, width);
  store_row(s->T, out_aux, pr, width);
  store_row(s->A, out_aux + npix, pr, width);
  store_row(s->mu, out_aux + 2 * npix, pr, width);
  store_row(s->M2, out_aux + 3 * npix, pr, width);
  store_row_int(s->last, out_last, pr, width);
  store_row_int(s->count, out_count, pr, width);
}

#if NO_STAGING
// CPU layout: no barriers, so PoCL keeps the work-item's values in registers
// and cache. Each row's state lives in a private array; a record's rows are
// those within row_reach of its centre (the backward's bound), and every row
// outside it is one whose pixels the alpha test would all have skipped.
__kernel __attribute__((reqd_work_group_size(1, 1, 1)))
#else
__kernel __attribute__((reqd_work_group_size(WG_SIZE, 1, 1)))
#endif
void blend_fwd(int width, int height, int tiles_x,
               __constant const float* cam,        // [CAM_SIZE]
               __global const int2* ranges,        // [tiles] [start, end) into the sorted lists
               __global const uint* isect_vals,    // [M] sorted: intersection slot
               __global const uint* isect_gid,     // [M] by slot: Gaussian id
               __global const float* records,      // [N,REC_SIZE]
               __global float* out_rgb,            // [3,H,W] incl. T * background
               __global float* out_feat,           // [3,H,W]
               __global float* out_depth,          // [H,W] sum w z
               __global float* out_alpha,          // [H,W] 1 - T
               __global float* out_dist,           // [H,W] A M2
               __global float* out_aux,            // [4,H,W] T, A, mu, M2 (for backward)
               __global int* out_last,             // [H,W] 1 + list index of the last blended
               __global int* out_count) {          // [H,W] Gaussians blended
  const size_t npix = (size_t)width * height;
#if NO_STAGING
  const int tile = get_group_id(0);
  const int2 range = ranges[tile];
  const int n = range.y - range.x;
  BlendState st[WG_SIZE];
  PixelRow rows[WG_SIZE];
  int open = 0;  // rows with a lane not done
  for (int row = 0; row < WG_SIZE; ++row) {
    rows[row] = pixel_row_of(tile, row, tiles_x, width, height);
    blend_state_init(&st[row], rows[row].inside);
    open += ANY(NOT(st[row].done)) ? 1 : 0;
  }
  // The tile's first pixel centre across.
  const float tile_x0 = tile_first_centre(tile, tiles_x);
  for (int j = 0; j < n && open > 0; ++j) {
    __global const float* q = records + (size_t)isect_gid[isect_vals[range.x + j]] * REC_SIZE;
    const float u = q[REC_U], v = q[REC_V], cA = q[REC_CA], cB = q[REC_CB], cC = q[REC_CC];
    const float reach = tile_row_reach(q, tile_x0);
    const float3 c = vload3(0, q + REC_RGB), f = vload3(0, q + REC_FEAT);
    for (int row = 0; row < WG_SIZE; ++row) {
      const float dy = v - rows[row].py;
      if (!(fabs(dy) <= reach) || !ANY(NOT(st[row].done))) continue;
      blend_step(&st[row], blend_sigma(cA, cB, cC, u - rows[row].px, dy), q[REC_OPACITY], c, f, q[REC_Z], q[REC_M],
                 j);
      if (!ANY(NOT(st[row].done))) --open;
    }
  }
  for (int row = 0; row < WG_SIZE; ++row)
    store_state(&st[row], rows[row], width, npix, cam, out_rgb, out_feat, out_depth, out_alpha, out_dist, out_aux,
                out_last, out_count);
#else
  __local float s_rec[BATCH * REC_SIZE];
  __local uint s_reach[BATCH];                     // tile_reached
  __local uint s_list[REACH_LISTS * LIST_WORDS];  // reach_lists
  __local int s_alive;
  const int lid = get_local_id(0);
  PixelRow pr = pixel_row(tiles_x, width, height);
  __local const uint *rows = ROW_LIST(pr), *cols = COL_LIST(pr);
  BlendState s;
  blend_state_init(&s, pr.inside);
  const int2 range = ranges[pr.tile];
  const int n = range.y - range.x;
  for (int b0 = 0; b0 < n; b0 += BATCH) {
    int nb = min(BATCH, n - b0);
    barrier(CLK_LOCAL_MEM_FENCE);
    if (lid == 0) s_alive = 0;
    for (int i = lid; i < nb; i += WG_SIZE) {
      uint gid = isect_gid[isect_vals[range.x + b0 + i]];
      stage_record(s_rec, i, records, gid);
      s_reach[i] = tile_reached(s_rec + i * REC_SIZE, pr.tile, tiles_x);
    }
    barrier(CLK_LOCAL_MEM_FENCE);
    reach_lists(s_reach, nb, s_list, lid);
    if (ANY(NOT(s.done))) atomic_or(&s_alive, 1);
    barrier(CLK_LOCAL_MEM_FENCE);
    if (!s_alive) break;
    // The records that may reach this work-item's pixels, in list order.
    for (int w = 0; w < LIST_WORDS && ANY(NOT(s.done)); ++w) {
      for (uint m = rows[w] & cols[w];;) {
        vfloat sigma;
        const int j = next_in_reach(&m, w, s_rec, pr, &sigma);
        if (j < 0) break;
        __local const float* q = s_rec + j * REC_SIZE;
        blend_step(&s, sigma, q[REC_OPACITY], vload3(0, q + REC_RGB), vload3(0, q + REC_FEAT), q[REC_Z], q[REC_M],
                   b0 + j);
        if (!ANY(NOT(s.done))) break;
      }
    }
  }
  store_state(&s, pr, width, npix, cam, out_rgb, out_feat, out_depth, out_alpha, out_dist, out_aux, out_last,
              out_count);
#endif
}
