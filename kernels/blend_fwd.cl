// Blend forward: one work-group per 16x16 tile, VW pixels per work-item,
// Gaussians staged through local memory in depth order (docs/rasterizer.md,
// "Blending"). Outputs are planar [C,H,W].
// Defines: BATCH (records staged per round); WITH_FEAT (0: the feature
// planes are not blended and come out zero).

__kernel __attribute__((reqd_work_group_size(WG_SIZE, 1, 1)))
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
#if !NO_STAGING
  __local float s_rec[BATCH * REC_SIZE];
  __local uint s_rows[BATCH];  // tile_rows_reached
  __local int s_alive;
  const int lid = get_local_id(0);
#endif
  PixelRow pr = pixel_row(tiles_x, width, height);
#if !NO_STAGING
  const uint row_bit = 1u << (pr.y % TILE);
#endif
  const size_t npix = (size_t)width * height;

  vfloat T = 1.f, r = 0.f, g = 0.f, b = 0.f, f0 = 0.f, f1 = 0.f, f2 = 0.f, dsum = 0.f;
  vfloat A = 0.f, mu = 0.f, M2 = 0.f;
  vint last = 0, count = 0;
  vint done = NOT(pr.inside);

  int2 range = ranges[pr.tile];
  int n = range.y - range.x;
#if NO_STAGING
  // CPU layout: one tile row per work-item. No staging and no barriers, so
  // the pixel state stays in SIMD registers (PoCL keeps values that live
  // across a barrier in memory); records come from cache instead.
  {
    const int b0 = 0;
    for (int j = 0; j < n; ++j) {
      __global const float* q = records + (size_t)isect_gid[isect_vals[range.x + j]] * REC_SIZE;
      // Most Gaussians of a tile touch only some of its rows: a scalar test
      // skips the rest before any vector work.
      if (row_culled(q, q[REC_V] - pr.py, q[REC_U] - (pr.x0 + 0.5f), q[REC_U] - (pr.x0 + (VW - 0.5f)))) continue;
#else
  for (int b0 = 0; b0 < n; b0 += BATCH) {
    int nb = min(BATCH, n - b0);
    barrier(CLK_LOCAL_MEM_FENCE);
    if (lid == 0) s_alive = 0;
    for (int i = lid; i < nb; i += WG_SIZE) {
      uint gid = isect_gid[isect_vals[range.x + b0 + i]];
      for (int c = 0; c < REC_SIZE; ++c) s_rec[i * REC_SIZE + c] = records[(size_t)gid * REC_SIZE + c];
      s_rows[i] = tile_rows_reached(s_rec + i * REC_SIZE, pr.tile, tiles_x);
    }
    barrier(CLK_LOCAL_MEM_FENCE);
    if (ANY(NOT(done))) atomic_or(&s_alive, 1);
    barrier(CLK_LOCAL_MEM_FENCE);
    if (!s_alive) break;
    if (!ANY(NOT(done))) continue;
    for (int j = 0; j < nb; ++j) {
      if (!(s_rows[j] & row_bit)) continue;  // the record cannot reach this work-item's row
      __local const float* q = s_rec + j * REC_SIZE;
#endif
      vfloat dx = q[REC_U] - pr.px;
      float dy = q[REC_V] - pr.py;
      vfloat sigma = blend_sigma(q[REC_CA], q[REC_CB], q[REC_CC], dx, dy);
#if !NO_STAGING
      if (out_of_reach(sigma, q[REC_THR])) continue;  // (the CPU layout's row test came first)
#endif
      vfloat alpha = fmin(q[REC_OPACITY] * blend_falloff(sigma), ALPHA_MAX);
      vint ok = NOT(done) & (sigma >= 0.f) & (alpha >= ALPHA_MIN);
      vfloat Tn = T * (1.f - alpha);
      vint stop = ok & (Tn < T_MIN);
      done = done | stop;
      ok = ok & NOT(stop);
      vfloat w = select((vfloat)0.f, alpha * T, ok);
      r += w * q[REC_RGB]; g += w * q[REC_RGB + 1]; b += w * q[REC_RGB + 2];
#if WITH_FEAT
      f0 += w * q[REC_FEAT]; f1 += w * q[REC_FEAT + 1]; f2 += w * q[REC_FEAT + 2];
#endif
      dsum += w * q[REC_Z];
      // Weighted Welford update of the distortion depth m (stable variance).
      float m = q[REC_M];
      vfloat An = A + w;
      vfloat mun = select(mu, mu + (w / An) * (m - mu), ok);
      M2 += w * (m - mu) * (m - mun);
      A = An;
      mu = mun;
      T = select(T, Tn, ok);
      last = select(last, (vint)(b0 + j + 1), ok);
      count = select(count, count + (vint)1, ok);
      if (!ANY(NOT(done))) break;
    }
  }
  store_row(r + T * cam[CAM_BG], out_rgb, pr, width);
  store_row(g + T * cam[CAM_BG + 1], out_rgb + npix, pr, width);
  store_row(b + T * cam[CAM_BG + 2], out_rgb + 2 * npix, pr, width);
  store_row(f0, out_feat, pr, width);
  store_row(f1, out_feat + npix, pr, width);
  store_row(f2, out_feat + 2 * npix, pr, width);
  store_row(dsum, out_depth, pr, width);
  store_row(1.f - T, out_alpha, pr, width);
  store_row(A * M2, out_dist, pr, width);
  store_row(T, out_aux, pr, width);
  store_row(A, out_aux + npix, pr, width);
  store_row(mu, out_aux + 2 * npix, pr, width);
  store_row(M2, out_aux + 3 * npix, pr, width);
  store_row_int(last, out_last, pr, width);
  store_row_int(count, out_count, pr, width);
}
