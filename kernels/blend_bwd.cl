// Blend backward: per tile, front to back, recomputing transmittance exactly
// as the forward pass did (never recovering it by division). For every
// (Gaussian, tile) intersection the tile's pixel contributions are summed in
// a fixed order (lanes, then work-items) and written to that intersection's
// own slot: no atomics, so the result is bit-identical run to run.
//
// Per blended Gaussian j of a pixel, with forward totals O, A_T, mu_T, M2_T,
// T_final and prefix sums that include j (docs/rasterizer.md, "Backward"):
//   dO/dalpha_j = T_j c_j - (O - P_j)/(1 - alpha_j) for every linear channel;
//   folded over channels with the upstream gradients g: gc = g . c_j,
//   G_O = g . O, G_P = sum_{k<=j} w_k gc_k.
//   alpha output: T_final/(1 - alpha_j).
//   distortion D = A M2: e_j = M2_T + A_T (m_j - mu_T)^2,
//     dD/dalpha_j = T_j e_j - (M2_T (A_T - A_j) + A_T (M2_T - Q_j))/(1 - alpha_j),
//     dD/dm_j = 2 w_j A_T (m_j - mu_T).
// Defines: BATCH, NO_STAGING (CPU layout below).

// Forward totals and upstream gradients of one work-item's pixels.
typedef struct {
  vfloat gr, gg, gb, gf0, gf1, gf2, gd, ga, gD;
  vfloat G_O, T_final, A_T, mu_T, M2_T;
  vint last;
} RowTotals;

inline RowTotals load_totals(PixelRow pr, int width, size_t npix,
                             __global const float* out_rgb, __global const float* out_feat,
                             __global const float* out_depth, __global const float* out_aux,
                             __global const int* out_last, __global const float* v_rgb,
                             __global const float* v_feat, __global const float* v_depth,
                             __global const float* v_alpha, __global const float* v_dist) {
  RowTotals t;
  t.gr = load_row(v_rgb, pr, width); t.gg = load_row(v_rgb + npix, pr, width);
  t.gb = load_row(v_rgb + 2 * npix, pr, width);
  t.gf0 = load_row(v_feat, pr, width); t.gf1 = load_row(v_feat + npix, pr, width);
  t.gf2 = load_row(v_feat + 2 * npix, pr, width);
  t.gd = load_row(v_depth, pr, width); t.ga = load_row(v_alpha, pr, width); t.gD = load_row(v_dist, pr, width);
  t.G_O = t.gr * load_row(out_rgb, pr, width) + t.gg * load_row(out_rgb + npix, pr, width) +
          t.gb * load_row(out_rgb + 2 * npix, pr, width) + t.gf0 * load_row(out_feat, pr, width) +
          t.gf1 * load_row(out_feat + npix, pr, width) + t.gf2 * load_row(out_feat + 2 * npix, pr, width) +
          t.gd * load_row(out_depth, pr, width);
  t.T_final = load_row(out_aux, pr, width); t.A_T = load_row(out_aux + npix, pr, width);
  t.mu_T = load_row(out_aux + 2 * npix, pr, width); t.M2_T = load_row(out_aux + 3 * npix, pr, width);
  t.last = load_row_int(out_last, pr, width);
  return t;
}

#if NO_STAGING
// CPU layout: one work-item per tile walks its rows (VW pixels each) in order,
// so there are no barriers and the running state stays in SIMD registers
// (PoCL keeps values that live across a barrier in memory). The tile's slots
// are zeroed first; each row then adds its lane-summed partials in row order,
// the same order of additions as the work-group sum of the staged layout.
// A row adds nothing for a Gaussian that none of its pixels blended.
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
  int n = range.y - range.x;
  __global const uint* vals = isect_vals + range.x;
  for (int k = 0; k < n; ++k) {
    __global float* o = isect_grads + (size_t)vals[k] * G2_SIZE;
    for (int c = 0; c < G2_SIZE; ++c) o[c] = 0.f;
  }
  for (int row = 0; row < WG_SIZE; ++row) {
    PixelRow pr = pixel_row_of(tile, row, tiles_x, width, height);
    if (!ANY(pr.inside)) continue;
    RowTotals t = load_totals(pr, width, npix, out_rgb, out_feat, out_depth, out_aux, out_last, v_rgb, v_feat,
                              v_depth, v_alpha, v_dist);
    int bound = 0;
#if VW == 1
    bound = t.last;
#else
    {
      int tmp[VW];
      VSTORE(t.last, tmp);
      for (int l = 0; l < VW; ++l) bound = max(bound, tmp[l]);
    }
#endif
    bound = min(bound, n);
    const float dx0 = -(pr.x0 + 0.5f), dx1 = -(pr.x0 + (VW - 0.5f));
    vfloat T = 1.f, G_P = 0.f, A = 0.f, Q = 0.f;
    for (int j = 0; j < bound; ++j) {
      uint slot = vals[j];
      __global const float* q = records + (size_t)isect_gid[slot] * REC_SIZE;
      const float u = q[REC_U];
      float dy = q[REC_V] - pr.py;
      if (row_culled(q, dy, u + dx0, u + dx1)) continue;
      const float cA = q[REC_CA], cB = q[REC_CB], cC = q[REC_CC], o = q[REC_OPACITY];
      vfloat dx = u - pr.px;
      vfloat sigma = blend_sigma(cA, cB, cC, dx, dy);
      vfloat G = blend_falloff(sigma);
      vfloat oG = o * G;
      vfloat alpha = fmin(ALPHA_MAX, oG);
      vint ok = (vint)j < t.last && sigma >= 0.f && alpha >= ALPHA_MIN;
      if (!ANY(ok)) continue;
      vfloat w = select((vfloat)0.f, alpha * T, ok);

      const float cr = q[REC_RGB], cg = q[REC_RGB + 1], cb = q[REC_RGB + 2];
      const float c0 = q[REC_FEAT], c1 = q[REC_FEAT + 1], c2 = q[REC_FEAT + 2], z = q[REC_Z], m = q[REC_M];
      vfloat gc = t.gr * cr + t.gg * cg + t.gb * cb + t.gf0 * c0 + t.gf1 * c1 + t.gf2 * c2 + t.gd * z;
      G_P += w * gc;
      vfloat dm = m - t.mu_T;
      A += w;
      Q += w * dm * dm;
      vfloat e = t.M2_T + t.A_T * dm * dm;
      vfloat S = t.M2_T * (t.A_T - A) + t.A_T * (t.M2_T - Q);
      vfloat inv = 1.f / (1.f - alpha);
      vfloat v_a = gc * T - (t.G_O - G_P) * inv + t.ga * t.T_final * inv + t.gD * (T * e - S * inv);
      vfloat v_oG = select((vfloat)0.f, v_a, ok && oG <= ALPHA_MAX);
      vfloat v_sigma = -v_oG * oG;
      vfloat v_z = t.gd * w + t.gD * 2.f * w * t.A_T * dm * dist_depth_vjp(z, dnear, dfar);

      __global float* o2 = isect_grads + (size_t)slot * G2_SIZE;
      o2[G2_U] += HSUM(v_sigma * (cA * dx + cB * dy));
      o2[G2_V] += HSUM(v_sigma * (cB * dx + cC * dy));
      o2[G2_CA] += HSUM(0.5f * v_sigma * dx * dx);
      o2[G2_CB] += HSUM(v_sigma * dx * dy);
      o2[G2_CC] += HSUM(0.5f * v_sigma * dy * dy);
      o2[G2_OPACITY] += HSUM(v_oG * G);
      o2[G2_RGB] += HSUM(t.gr * w);
      o2[G2_RGB + 1] += HSUM(t.gg * w);
      o2[G2_RGB + 2] += HSUM(t.gb * w);
      o2[G2_FEAT] += HSUM(t.gf0 * w);
      o2[G2_FEAT + 1] += HSUM(t.gf1 * w);
      o2[G2_FEAT + 2] += HSUM(t.gf2 * w);
      o2[G2_Z] += HSUM(v_z);
      T = select(T, T * (1.f - alpha), ok);
    }
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
  __local float s_part[BATCH * WG_SIZE * G2_SIZE];
  __local int s_bound;
  const int lid = get_local_id(0);
  PixelRow pr = pixel_row(tiles_x, width, height);
  const size_t npix = (size_t)width * height;

  // Upstream gradients and forward totals of this row's pixels.
  vfloat gr = load_row(v_rgb, pr, width), gg = load_row(v_rgb + npix, pr, width),
         gb = load_row(v_rgb + 2 * npix, pr, width);
  vfloat gf0 = load_row(v_feat, pr, width), gf1 = load_row(v_feat + npix, pr, width),
         gf2 = load_row(v_feat + 2 * npix, pr, width);
  vfloat gd = load_row(v_depth, pr, width), ga = load_row(v_alpha, pr, width), gD = load_row(v_dist, pr, width);
  vfloat G_O = gr * load_row(out_rgb, pr, width) + gg * load_row(out_rgb + npix, pr, width) +
               gb * load_row(out_rgb + 2 * npix, pr, width) + gf0 * load_row(out_feat, pr, width) +
               gf1 * load_row(out_feat + npix, pr, width) + gf2 * load_row(out_feat + 2 * npix, pr, width) +
               gd * load_row(out_depth, pr, width);
  vfloat T_final = load_row(out_aux, pr, width), A_T = load_row(out_aux + npix, pr, width),
         mu_T = load_row(out_aux + 2 * npix, pr, width), M2_T = load_row(out_aux + 3 * npix, pr, width);
  vint last = load_row_int(out_last, pr, width);
  const float dnear = cam[CAM_DNEAR], dfar = cam[CAM_DFAR];

  int2 range = ranges[pr.tile];
  int n = range.y - range.x;
  if (lid == 0) s_bound = 0;
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

  vfloat T = 1.f, G_P = 0.f, A = 0.f, Q = 0.f;
  for (int b0 = 0; b0 < bound; b0 += BATCH) {
    int nb = min(BATCH, bound - b0);
    barrier(CLK_LOCAL_MEM_FENCE);
    for (int i = lid; i < nb; i += WG_SIZE) {
      uint slot = isect_vals[range.x + b0 + i];
      uint gid = isect_gid[slot];
      s_slot[i] = slot;
      for (int c = 0; c < REC_SIZE; ++c) s_rec[i * REC_SIZE + c] = records[(size_t)gid * REC_SIZE + c];
    }
    barrier(CLK_LOCAL_MEM_FENCE);
    for (int j = 0; j < nb; ++j) {
      __local float* part = s_part + (j * WG_SIZE + lid) * G2_SIZE;
      vint active = (vint)(b0 + j) < last;
      if (!ANY(active)) {
        for (int c = 0; c < G2_SIZE; ++c) part[c] = 0.f;
        continue;
      }
      __local const float* q = s_rec + j * REC_SIZE;
      const float cA = q[REC_CA], cB = q[REC_CB], cC = q[REC_CC], o = q[REC_OPACITY];
      vfloat dx = q[REC_U] - pr.px;
      float dy = q[REC_V] - pr.py;
      vfloat sigma = blend_sigma(cA, cB, cC, dx, dy);
      vfloat G = blend_falloff(sigma);
      vfloat oG = o * G;
      vfloat alpha = fmin(ALPHA_MAX, oG);
      vint ok = active && sigma >= 0.f && alpha >= ALPHA_MIN;
      vfloat w = select((vfloat)0.f, alpha * T, ok);

      const float cr = q[REC_RGB], cg = q[REC_RGB + 1], cb = q[REC_RGB + 2];
      const float c0 = q[REC_FEAT], c1 = q[REC_FEAT + 1], c2 = q[REC_FEAT + 2], z = q[REC_Z], m = q[REC_M];
      vfloat gc = gr * cr + gg * cg + gb * cb + gf0 * c0 + gf1 * c1 + gf2 * c2 + gd * z;
      G_P += w * gc;
      vfloat dm = m - mu_T;
      A += w;
      Q += w * dm * dm;
      vfloat e = M2_T + A_T * dm * dm;
      vfloat S = M2_T * (A_T - A) + A_T * (M2_T - Q);
      vfloat inv = 1.f / (1.f - alpha);
      vfloat v_a = gc * T - (G_O - G_P) * inv + ga * T_final * inv + gD * (T * e - S * inv);
      // alpha = min(0.99, o G): no gradient through the clamp.
      vfloat v_oG = select((vfloat)0.f, v_a, ok && oG <= ALPHA_MAX);
      vfloat v_sigma = -v_oG * oG;
      vfloat v_z = gd * w + gD * 2.f * w * A_T * dm * dist_depth_vjp(z, dnear, dfar);

      part[G2_U] = HSUM(v_sigma * (cA * dx + cB * dy));
      part[G2_V] = HSUM(v_sigma * (cB * dx + cC * dy));
      part[G2_CA] = HSUM(0.5f * v_sigma * dx * dx);
      part[G2_CB] = HSUM(v_sigma * dx * dy);
      part[G2_CC] = HSUM(0.5f * v_sigma * dy * dy);
      part[G2_OPACITY] = HSUM(v_oG * G);
      part[G2_RGB] = HSUM(gr * w);
      part[G2_RGB + 1] = HSUM(gg * w);
      part[G2_RGB + 2] = HSUM(gb * w);
      part[G2_FEAT] = HSUM(gf0 * w);
      part[G2_FEAT + 1] = HSUM(gf1 * w);
      part[G2_FEAT + 2] = HSUM(gf2 * w);
      part[G2_Z] = HSUM(v_z);
      T = select(T, T * (1.f - alpha), ok);
    }
    barrier(CLK_LOCAL_MEM_FENCE);
    // Sum the work-items' partials in index order into each intersection's slot.
    for (int idx = lid; idx < nb * G2_SIZE; idx += WG_SIZE) {
      int j = idx / G2_SIZE, c = idx % G2_SIZE;
      float s = 0.f;
      for (int l = 0; l < WG_SIZE; ++l) s += s_part[(j * WG_SIZE + l) * G2_SIZE + c];
      isect_grads[(size_t)s_slot[j] * G2_SIZE + c] = s;
    }
  }
  // Intersections behind every pixel's last blended Gaussian get zeros.
  for (int k = bound + lid; k < n; k += WG_SIZE) {
    uint slot = isect_vals[range.x + k];
    for (int c = 0; c < G2_SIZE; ++c) isect_grads[(size_t)slot * G2_SIZE + c] = 0.f;
  }
}
#endif
