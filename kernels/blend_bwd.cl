// Blend backward: per tile, front to back, recomputing transmittance exactly
// as the forward pass did (never recovering it by division). For every
// (Gaussian, tile) intersection the tile's pixel contributions are summed in
// a fixed order (GPU layout: lanes, then work-items; CPU layout: rows per
// lane, then lanes) and written to that intersection's own slot: no atomics,
// so the result is bit-identical run to run on a device.
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
// Defines: BATCH, NO_STAGING (CPU layout below); GRAD_RGB, GRAD_FEAT,
// GRAD_DEPTH, GRAD_ALPHA, GRAD_DIST: 0 when that upstream gradient is zero
// everywhere (not given), so the CPU layout leaves its terms out (a zero
// term adds nothing; float rules forbid the compiler to drop x * 0 itself).

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
  t.gr = GRAD_RGB ? load_row(v_rgb, pr, width) : 0.f;
  t.gg = GRAD_RGB ? load_row(v_rgb + npix, pr, width) : 0.f;
  t.gb = GRAD_RGB ? load_row(v_rgb + 2 * npix, pr, width) : 0.f;
  t.gf0 = GRAD_FEAT ? load_row(v_feat, pr, width) : 0.f;
  t.gf1 = GRAD_FEAT ? load_row(v_feat + npix, pr, width) : 0.f;
  t.gf2 = GRAD_FEAT ? load_row(v_feat + 2 * npix, pr, width) : 0.f;
  t.gd = GRAD_DEPTH ? load_row(v_depth, pr, width) : 0.f;
  t.ga = GRAD_ALPHA ? load_row(v_alpha, pr, width) : 0.f;
  t.gD = GRAD_DIST ? load_row(v_dist, pr, width) : 0.f;
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
  vfloat Ts[WG_SIZE], GPs[WG_SIZE], As[WG_SIZE], Qs[WG_SIZE];
  vfloat pxs[WG_SIZE];
  float pys[WG_SIZE], dx0s[WG_SIZE], dx1s[WG_SIZE];
  int bounds[WG_SIZE];
  int bound = 0;
  for (int row = 0; row < WG_SIZE; ++row) {
    PixelRow pr = pixel_row_of(tile, row, tiles_x, width, height);
    bounds[row] = 0;
    pxs[row] = pr.px;
    pys[row] = pr.py;
    dx0s[row] = -(pr.x0 + 0.5f);
    dx1s[row] = -(pr.x0 + (VW - 0.5f));
    Ts[row] = 1.f;
    GPs[row] = As[row] = Qs[row] = 0.f;
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
      const float u = q[REC_U], v = q[REC_V];
      const float cA = q[REC_CA], cB = q[REC_CB], cC = q[REC_CC], o = q[REC_OPACITY];
      const float cr = q[REC_RGB], cg = q[REC_RGB + 1], cb = q[REC_RGB + 2];
      const float c0 = q[REC_FEAT], c1 = q[REC_FEAT + 1], c2 = q[REC_FEAT + 2], z = q[REC_Z], m = q[REC_M];
      const float zj = dist_depth_vjp(z, dnear, dfar);
      for (int row = 0; row < WG_SIZE; ++row) {
        if (j >= bounds[row]) continue;
        const float dy = v - pys[row];
        if (row_culled(q, dy, u + dx0s[row], u + dx1s[row])) continue;
        const vfloat dx = u - pxs[row];
        const vfloat sigma = blend_sigma(cA, cB, cC, dx, dy);
        const vfloat G = blend_falloff(sigma);
        const vfloat oG = o * G;
        const vfloat alpha = fmin(ALPHA_MAX, oG);
        const RowTotals t = tot[row];
        const vint ok = (vint)j < t.last && sigma >= 0.f && alpha >= ALPHA_MIN;
        if (!ANY(ok)) continue;
        touched = 1;
        const vfloat T = Ts[row];
        const vfloat w = select((vfloat)0.f, alpha * T, ok);
        vfloat gc = 0.f;
#if GRAD_RGB
        gc = t.gr * cr + t.gg * cg + t.gb * cb;
#endif
#if GRAD_FEAT
        gc += t.gf0 * c0 + t.gf1 * c1 + t.gf2 * c2;
#endif
#if GRAD_DEPTH
        gc += t.gd * z;
#endif
        const vfloat G_P = GPs[row] + w * gc;
        const vfloat inv = 1.f / (1.f - alpha);
        vfloat v_a = gc * T - (t.G_O - G_P) * inv;
#if GRAD_ALPHA
        v_a += t.ga * t.T_final * inv;
#endif
#if GRAD_DIST
        const vfloat dm = m - t.mu_T;
        const vfloat A = As[row] + w;
        const vfloat Q = Qs[row] + w * dm * dm;
        const vfloat e = t.M2_T + t.A_T * dm * dm;
        const vfloat S = t.M2_T * (t.A_T - A) + t.A_T * (t.M2_T - Q);
        v_a += t.gD * (T * e - S * inv);
#endif
        const vfloat v_oG = select((vfloat)0.f, v_a, ok && oG <= ALPHA_MAX);
        const vfloat v_sigma = -v_oG * oG;
        s_u += v_sigma * (cA * dx + cB * dy);
        s_v += v_sigma * (cB * dx + cC * dy);
        s_ca += 0.5f * v_sigma * dx * dx;
        s_cb += v_sigma * dx * dy;
        s_cc += 0.5f * v_sigma * dy * dy;
        s_op += v_oG * G;
#if GRAD_RGB
        s_r += t.gr * w;
        s_g += t.gg * w;
        s_b += t.gb * w;
#endif
#if GRAD_FEAT
        s_f0 += t.gf0 * w;
        s_f1 += t.gf1 * w;
        s_f2 += t.gf2 * w;
#endif
#if GRAD_DEPTH
        s_z += t.gd * w;
#endif
#if GRAD_DIST
        s_z += t.gD * 2.f * w * t.A_T * dm * zj;
        As[row] = A;
        Qs[row] = Q;
#endif
        GPs[row] = G_P;
        Ts[row] = select(T, T * (1.f - alpha), ok);
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
