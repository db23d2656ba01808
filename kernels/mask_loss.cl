// SAM mask losses of one view (docs/design.md section 4) on the rendered feature
// map F (3 channels) and their gradient with respect to F (and alpha):
//
//   G(p)    = F(p) / alpha(p)  where alpha(p) >= MASK_ALPHA_MIN, else the pixel
//             is excluded from every mask       (with alpha; without: G = F)
//   N_j     = |M_j| (valid pixels with label j in any layer, counted once)
//   Gbar_j  = sum_{p in M_j} G(p) / N_j          (mask j is present when N_j > 0)
//   T       = sum_j N_j,  m = number of present masks
//   L_is    = (1 / T) sum_j sum_{p in M_j} |G(p) - Gbar_j|_1
//   L_ic    = 1 / (m (m - 1)) sum_{j != k} 1 / (|Gbar_j - Gbar_k|_1 + 1)   (0 when m < 2)
//
// Backward, with s = sign (sign(0) = 0), per channel c:
//   dL_is/dG_c(q) = (1 / T) sum_{j : q in M_j} (s(G_c(q) - Gbar_jc) - A_jc / N_j),
//       A_jc = sum_{p in M_j} s(G_c(p) - Gbar_jc)      (the chain through Gbar_j)
//   dL_ic/dGbar_jc = -2 / (m (m - 1)) sum_{k != j} s(Gbar_jc - Gbar_kc) / (d_jk + 1)^2
//   dL_ic/dG_c(q) = sum_{j : q in M_j} dL_ic/dGbar_jc / N_j
// so dL/dG_c(q) = sum_{j : q in M_j} (w_is / T s(G_c(q) - Gbar_jc) + K_jc) with
//   K_jc = (-w_is A_jc / T + w_ic dL_ic/dGbar_jc) / N_j   (one per mask, mask_coef).
// Through G = F / alpha: dL/dF_c = v_c / alpha, dL/dalpha = -sum_c v_c G_c / alpha
// (v = dL/dG); excluded pixels get zero gradients.
//
// Work split. The host lists, once per view, the pixels of each mask in
// ascending order (a pixel appears once per mask it belongs to) and cuts each
// mask's list into chunks of at most CHUNK entries. One work-group per chunk
// gathers and sums its entries (fixed per-work-item order, then a fixed tree),
// one work-item per mask sums its chunks in order: deterministic, no atomics,
// and the cost is the number of mask pixels whatever the number of masks.
// The per-pixel gradient reads the label maps (a gather, no scatter).
//
// Defines: WG (work-group size, a power of two), LANES (entries or pixels per
// work-item: 16 on CPUs, 1 on GPUs), MASK_ALPHA_MIN (0.1f).

#define CHUNK (WG * LANES)

inline size_t feature_index(int planar, size_t npix, size_t p, int c) {
  return planar ? (size_t)c * npix + p : p * 3 + c;
}

// G at pixel p; returns 0 (and G = 0) when the pixel is excluded. NaN alpha
// fails the comparison and is excluded too. The same operations everywhere,
// so every kernel sees the same bits of G.
inline int load_g(__global const float* feature, __global const float* alpha, int has_alpha, int planar, size_t npix,
                  size_t p, float3* g) {
  float3 v = (float3)(feature[feature_index(planar, npix, p, 0)], feature[feature_index(planar, npix, p, 1)],
                      feature[feature_index(planar, npix, p, 2)]);
  if (has_alpha) {
    const float a = alpha[p];
    if (!(a >= MASK_ALPHA_MIN)) {
      *g = (float3)(0.f);
      return 0;
    }
    v = v / a;
  }
  *g = v;
  return 1;
}

inline float l1_norm3(float3 v) {
  return (fabs(v.x) + fabs(v.y)) + fabs(v.z);
}

// Pass 1: per chunk, the sum of G and the number of valid pixels.
__kernel void mask_chunk_sums(int planar, int has_alpha, int npix,
                              __global const float* feature,  // [3,H,W] or [H,W,3]
                              __global const float* alpha,    // [H,W] when has_alpha
                              __global const int* pixels,     // [entries] pixel index, grouped by mask
                              __global const int4* chunks,    // [chunks] (mask, begin, end, 0) into pixels
                              __global float4* partials) {    // [chunks] (sum G, count)
  __local float4 scratch[WG];
  const int4 ch = chunks[get_group_id(0)];
  float4 s = (float4)(0.f);
  for (int e = ch.y + (int)get_local_id(0); e < ch.z; e += WG) {
    float3 g;
    if (load_g(feature, alpha, has_alpha, planar, (size_t)npix, (size_t)pixels[e], &g)) s += (float4)(g, 1.f);
  }
  const float4 total = group_sum4(s, scratch);
  if (get_local_id(0) == 0) partials[get_group_id(0)] = total;
}

// Pass 2 (one work-group): per mask, the chunks summed in order -> mean and
// count; m and T over all masks (integers: exact in any order).
__kernel void mask_means(int masks,
                         __global const int* mask_chunks,  // [masks + 1] first chunk of each mask
                         __global const float4* partials,  // [chunks] from pass 1
                         __global float4* means,           // [masks] (Gbar, N), 0 for absent masks
                         __global int* stats) {            // [2] (m, T)
  __local int2 scratch[WG];
  const int lid = get_local_id(0);
  int2 acc = (int2)(0);
  for (int j = lid; j < masks; j += WG) {
    float3 s = (float3)(0.f);
    int n = 0;
    for (int k = mask_chunks[j]; k < mask_chunks[j + 1]; ++k) {
      const float4 part = partials[k];
      s += part.xyz;
      n += (int)part.w;
    }
    means[j] = n > 0 ? (float4)(s / (float)n, (float)n) : (float4)(0.f);
    acc += (int2)(n > 0 ? 1 : 0, n);
  }
  scratch[lid] = acc;
  barrier(CLK_LOCAL_MEM_FENCE);
  for (int s = WG / 2; s > 0; s >>= 1) {
    if (lid < s) scratch[lid] += scratch[lid + s];
    barrier(CLK_LOCAL_MEM_FENCE);
  }
  if (lid == 0) {
    stats[0] = scratch[0].x;
    stats[1] = scratch[0].y;
  }
}

// Pass 3: per chunk, the sign sums A (per channel) and sum |G - Gbar|_1.
__kernel void mask_chunk_abs(int planar, int has_alpha, int npix,
                             __global const float* feature,  // as in pass 1
                             __global const float* alpha,    // [H,W] when has_alpha
                             __global const int* pixels,     // [entries]
                             __global const int4* chunks,    // [chunks]
                             __global const float4* means,   // [masks] from pass 2
                             __global float4* partials) {    // [chunks] (A, sum |G - Gbar|_1)
  __local float4 scratch[WG];
  const int4 ch = chunks[get_group_id(0)];
  const float3 mean = means[ch.x].xyz;
  float4 s = (float4)(0.f);
  for (int e = ch.y + (int)get_local_id(0); e < ch.z; e += WG) {
    float3 g;
    if (load_g(feature, alpha, has_alpha, planar, (size_t)npix, (size_t)pixels[e], &g)) {
      const float3 d = g - mean;
      s += (float4)(sign(d), l1_norm3(d));
    }
  }
  const float4 total = group_sum4(s, scratch);
  if (get_local_id(0) == 0) partials[get_group_id(0)] = total;
}

// Pass 4: one work-item per mask j: its chunks' sums in order, the m x m
// contrastive term against every other present mask (in index order), the
// per-mask gradient coefficient K_j and the mask's loss terms.
__kernel void mask_coef(int masks, float w_is, float w_ic,
                        __global const int* mask_chunks,  // [masks + 1]
                        __global const float4* partials,  // [chunks] from pass 3
                        __global const float4* means,     // [masks] (Gbar, N)
                        __global const int* stats,        // [2] (m, T)
                        __global float4* coef,            // [masks] (K_j, 0)
                        __global float2* terms) {         // [masks] (sum |G - Gbar_j|_1, sum_k 1 / (d_jk + 1))
  const int j = get_global_id(0);
  if (j >= masks) return;
  const float4 mj = means[j];
  if (!(mj.w > 0.f)) {
    coef[j] = (float4)(0.f);
    terms[j] = (float2)(0.f);
    return;
  }
  const int m = stats[0], total = stats[1];
  float4 a = (float4)(0.f);
  for (int k = mask_chunks[j]; k < mask_chunks[j + 1]; ++k) a += partials[k];
  float ic = 0.f;
  float3 b = (float3)(0.f);
  if (m >= 2) {
    for (int k = 0; k < masks; ++k) {
      const float4 mk = means[k];
      if (k == j || !(mk.w > 0.f)) continue;
      const float3 d = mj.xyz - mk.xyz;
      const float inv = 1.f / (l1_norm3(d) + 1.f);
      ic += inv;
      b += sign(d) * (inv * inv);
    }
  }
  // dL_ic/dGbar_j = -2 / (m (m - 1)) b: each pair appears as (j, k) and (k, j).
  const float ic_norm = m >= 2 ? 1.f / ((float)m * (float)(m - 1)) : 0.f;
  const float3 v_mean = w_ic * (-2.f * ic_norm) * b - (w_is / (float)total) * a.xyz;
  coef[j] = (float4)(v_mean / mj.w, 0.f);
  terms[j] = (float2)(a.w, ic);
}

// Pass 5: the gradient of every pixel (zero outside the masks and at excluded
// pixels), LANES consecutive pixels per work-item.
__kernel void mask_grad(int layers, int npix, int planar, int has_alpha, int want_alpha_grad, float w_is,
                        __global const float* feature,  // [3,H,W] or [H,W,3]
                        __global const float* alpha,    // [H,W] when has_alpha
                        __global const int* labels,     // [layers,H,W] mask index, -1 none
                        __global const float4* means,   // [masks] (Gbar, N)
                        __global const float4* coef,    // [masks] (K, 0)
                        __global const int* stats,      // [2] (m, T)
                        __global float* grad_feature,   // layout of feature: dL/dF
                        __global float* grad_alpha) {   // [H,W] dL/dalpha when want_alpha_grad
  const int total = stats[1];
  const float unit = total > 0 ? w_is / (float)total : 0.f;
  const size_t first = get_global_id(0) * LANES;
  for (int l = 0; l < LANES; ++l) {
    const size_t p = first + l;
    if (p >= (size_t)npix) return;
    float3 g;
    const int valid = load_g(feature, alpha, has_alpha, planar, (size_t)npix, p, &g);
    float3 v = (float3)(0.f);
    if (valid) {
      for (int a = 0; a < layers; ++a) {
        const int j = labels[(size_t)a * npix + p];
        if (j < 0) continue;
        int seen = 0;  // the same mask in an earlier layer: counted once
        for (int b = 0; b < a; ++b) seen |= labels[(size_t)b * npix + p] == j;
        if (seen) continue;
        const float4 mj = means[j];
        if (!(mj.w > 0.f)) continue;
        v += unit * sign(g - mj.xyz) + coef[j].xyz;
      }
    }
    float3 df = v;
    float da = 0.f;
    if (has_alpha && valid) {
      const float a = alpha[p];
      df = v / a;
      da = -((v.x * g.x + v.y * g.y) + v.z * g.z) / a;
    }
    grad_feature[feature_index(planar, (size_t)npix, p, 0)] = df.x;
    grad_feature[feature_index(planar, (size_t)npix, p, 1)] = df.y;
    grad_feature[feature_index(planar, (size_t)npix, p, 2)] = df.z;
    if (want_alpha_grad) grad_alpha[p] = da;
  }
}
