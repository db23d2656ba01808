// Photometric loss of 3DGS between a rendered image x and a target y, 3
// channels (DESIGN.md section 3):
//
//   L_rgb = (1 - lambda) L1 + lambda (1 - SSIM)
//   L1    = sum_p w_p sum_c |x - y| / (3 sum_p w_p)      (w = 1: mean over H*W*3)
//   SSIM  = sum_p w_p sum_c S_c(p) / (3 sum_p w_p)
//
// S is the SSIM map of one channel with an 11x11 Gaussian window G = g g^T
// (sigma 1.5) applied as a "same" convolution with zero padding, as 3DGS's
// conv2d(padding = 5):
//   mx = G*x, my = G*y, sxx = G*(x^2) - mx^2, syy = G*(y^2) - my^2,
//   sxy = G*(xy) - mx my,
//   S = (2 mx my + C1)(2 sxy + C2) / ((mx^2 + my^2 + C1)(sxx + syy + C2)).
// G is separable and the zero-padded domain is a product of intervals, so
// G* = (vertical pass) o (horizontal pass) exactly.
//
// Backward. With a = dL/dS(p) = -lambda w_p / (3 sum w), S depends on x only
// through the raw moments mx, Exx = G*(x^2) and Exy = G*(xy), so
//   dL/dx(q) = [G^T*(a dS/dmx)](q) + 2 x_q [G^T*(a dS/dExx)](q)
//              + y_q [G^T*(a dS/dExy)](q) + (1 - lambda) w_q sign(x_q - y_q) / (3 sum w).
// G^T* is the adjoint of the zero-padded convolution: the same symmetric
// window, again with zero padding, i.e. the same two blur passes. The partials
// come from the central moments (see ssim_partials) and 1 / (3 sum w) is
// factored out of the blurs and applied last, so the pixel pass needs no
// reduction result.
//
// Buffers use one of two layouts, chosen per call by `planar`: interleaved
// [H,W,3] (RenderOutput.rgb on the host) or planar [3,H,W] (the renderer's
// device images). Reductions: per work-group partial sums in a fixed tree
// order, no floating-point atomics.
//
// Defines: WG (work-group size, a power of two), GW0..GW5 (the normalised 1D
// window at distances 0..5), SSIM_C1, SSIM_C2.

#define RADIUS 5
#define TAPS (2 * RADIUS + 1)

__constant float kWindow[TAPS] = {GW5, GW4, GW3, GW2, GW1, GW0, GW1, GW2, GW3, GW4, GW5};

inline size_t image_index(int planar, size_t npix, size_t p, int c) {
  return planar ? (size_t)c * npix + p : p * 3 + c;
}

// Partials of S with respect to the raw moments (mx, Exx, Exy) of x, from
// those with respect to the central moments (mx, sxx, sxy):
//   dS/dsxx = -S / D2,  dS/dsxy = 2 N1 / (D1 D2),
//   dS/dmx|central = 2 my N2 / (D1 D2) - 2 mx S / D1,
// and sxx = Exx - mx^2, sxy = Exy - mx my give
//   dS/dmx = dS/dmx|central - 2 mx dS/dsxx - my dS/dsxy,
//   dS/dExx = dS/dsxx, dS/dExy = dS/dsxy.
// Returns S; writes the three partials to d.
inline float ssim_partials(float mx, float my, float exx, float eyy, float exy, float3* d) {
  float sxx = exx - mx * mx, syy = eyy - my * my, sxy = exy - mx * my;
  float n1 = 2.f * mx * my + SSIM_C1, n2 = 2.f * sxy + SSIM_C2;
  float d1 = mx * mx + my * my + SSIM_C1, d2 = sxx + syy + SSIM_C2;
  float inv_d = 1.f / (d1 * d2);
  float s = n1 * n2 * inv_d;
  float ds_dsxx = -s / d2;
  float ds_dsxy = 2.f * n1 * inv_d;
  float ds_dmx_c = 2.f * my * n2 * inv_d - 2.f * mx * s / d1;
  *d = (float3)(ds_dmx_c - 2.f * mx * ds_dsxx - my * ds_dsxy, ds_dsxx, ds_dsxy);
  return s;
}

// Pass 1: horizontal blur of x, y, x^2, y^2 and xy for each channel.
__kernel void ssim_blur_h(int width, int height, int planar,
                          __global const float* x,  // [H,W,3] or [3,H,W] rendered
                          __global const float* y,  // same layout, target
                          __global float* h) {      // [5,3,H,W] (x, y, xx, yy, xy) x channel
  const size_t npix = (size_t)width * height;
  const size_t p = get_global_id(0);
  if (p >= npix) return;
  const int col = (int)(p % (size_t)width);
  const size_t row_start = p - col;
  const int t0 = max(-RADIUS, -col), t1 = min(RADIUS, width - 1 - col);
  for (int c = 0; c < 3; ++c) {
    float sx = 0.f, sy = 0.f, sxx = 0.f, syy = 0.f, sxy = 0.f;
    for (int t = t0; t <= t1; ++t) {
      const float g = kWindow[t + RADIUS];
      const size_t q = row_start + (size_t)(col + t);
      const float xv = x[image_index(planar, npix, q, c)], yv = y[image_index(planar, npix, q, c)];
      sx += g * xv;
      sy += g * yv;
      sxx += g * (xv * xv);
      syy += g * (yv * yv);
      sxy += g * (xv * yv);
    }
    h[(size_t)(0 + c) * npix + p] = sx;
    h[(size_t)(3 + c) * npix + p] = sy;
    h[(size_t)(6 + c) * npix + p] = sxx;
    h[(size_t)(9 + c) * npix + p] = syy;
    h[(size_t)(12 + c) * npix + p] = sxy;
  }
}

// Vertical blur of plane `k` of h at pixel p (rows t0..t1 around it).
inline float blur_v(__global const float* h, size_t npix, int k, size_t p, int width, int t0, int t1) {
  __global const float* plane = h + (size_t)k * npix;
  float s = 0.f;
  for (int t = t0; t <= t1; ++t) s += kWindow[t + RADIUS] * plane[(long)p + (long)t * width];
  return s;
}

// Fixed-order tree sum over the work-group; every work-item must call it.
inline float4 group_sum4(float4 v, __local float4* scratch) {
  const int lid = get_local_id(0);
  scratch[lid] = v;
  barrier(CLK_LOCAL_MEM_FENCE);
  for (int s = WG / 2; s > 0; s >>= 1) {
    if (lid < s) scratch[lid] += scratch[lid + s];
    barrier(CLK_LOCAL_MEM_FENCE);
  }
  return scratch[0];
}

// Pass 2: vertical blur, the SSIM map and the loss terms of each pixel; with
// want_grad, also the per-pixel coefficients of the backward blurs.
__kernel void ssim_map(int width, int height, int planar, float lambda, int want_grad, int has_weights,
                       __global const float* x,        // rendered, layout as in pass 1
                       __global const float* y,        // target
                       __global const float* h,        // [5,3,H,W] from pass 1
                       __global const float* weights,  // [H,W] when has_weights
                       __global float* coef,           // [3,3,H,W] -lambda w (dS/dmx, dS/dExx, dS/dExy) x channel
                       __global float4* partials) {    // [groups] sums of (w|x-y|, w S, w (x-y)^2, w)
  __local float4 scratch[WG];
  const size_t npix = (size_t)width * height;
  const size_t p = get_global_id(0);
  float4 sums = (float4)(0.f);
  if (p < npix) {
    const int col = (int)(p % (size_t)width), row = (int)(p / (size_t)width);
    const int t0 = max(-RADIUS, -row), t1 = min(RADIUS, height - 1 - row);
    const float w = has_weights ? weights[p] : 1.f;
    float l1 = 0.f, ssim = 0.f, sq = 0.f;
    for (int c = 0; c < 3; ++c) {
      const float mx = blur_v(h, npix, 0 + c, p, width, t0, t1);
      const float my = blur_v(h, npix, 3 + c, p, width, t0, t1);
      const float exx = blur_v(h, npix, 6 + c, p, width, t0, t1);
      const float eyy = blur_v(h, npix, 9 + c, p, width, t0, t1);
      const float exy = blur_v(h, npix, 12 + c, p, width, t0, t1);
      float3 d;
      ssim += ssim_partials(mx, my, exx, eyy, exy, &d);
      if (want_grad) {
        const float a = -lambda * w;
        coef[(size_t)(0 + c) * npix + p] = a * d.x;
        coef[(size_t)(3 + c) * npix + p] = a * d.y;
        coef[(size_t)(6 + c) * npix + p] = a * d.z;
      }
      const float diff = x[image_index(planar, npix, p, c)] - y[image_index(planar, npix, p, c)];
      l1 += fabs(diff);
      sq += diff * diff;
    }
    sums = (float4)(w * l1, w * ssim, w * sq, w);
  }
  const float4 total = group_sum4(sums, scratch);
  if (get_local_id(0) == 0) partials[get_group_id(0)] = total;
}

// 1 / (3 sum w) from the partial sums, in a fixed order: one work-group.
__kernel void loss_norm(int groups,
                        __global const float4* partials,  // [groups]
                        __global float* norm) {           // [1]
  __local float4 scratch[WG];
  const int lid = get_local_id(0);
  float s = 0.f;
  for (int i = lid; i < groups; i += WG) s += partials[i].w;
  const float total = group_sum4((float4)(s, 0.f, 0.f, 0.f), scratch).x;
  if (lid == 0) norm[0] = total > 0.f ? 1.f / (3.f * total) : 0.f;
}

// Pass 3: horizontal blur of the 9 coefficient planes (the adjoint of pass 2).
__kernel void coef_blur_h(int width, int height,
                          __global const float* coef,  // [9,H,W]
                          __global float* out) {       // [9,H,W]
  const size_t npix = (size_t)width * height;
  const size_t p = get_global_id(0);
  if (p >= npix) return;
  const int col = (int)(p % (size_t)width);
  const int t0 = max(-RADIUS, -col), t1 = min(RADIUS, width - 1 - col);
  for (int k = 0; k < 9; ++k) {
    __global const float* plane = coef + (size_t)k * npix;
    float s = 0.f;
    for (int t = t0; t <= t1; ++t) s += kWindow[t + RADIUS] * plane[(long)p + t];
    out[(size_t)k * npix + p] = s;
  }
}

// Pass 4: vertical blur of the coefficients (the adjoint of pass 1) and the
// gradient with respect to the rendered image.
__kernel void image_loss_grad(int width, int height, int planar, float lambda, int has_weights,
                              __global const float* x,        // rendered
                              __global const float* y,        // target
                              __global const float* weights,  // [H,W] when has_weights
                              __global const float* hc,       // [9,H,W] from pass 3
                              __global const float* norm,     // [1] 1 / (3 sum w)
                              __global float* grad) {         // layout of x: dL/dx
  const size_t npix = (size_t)width * height;
  const size_t p = get_global_id(0);
  if (p >= npix) return;
  const int row = (int)(p / (size_t)width);
  const int t0 = max(-RADIUS, -row), t1 = min(RADIUS, height - 1 - row);
  const float w = has_weights ? weights[p] : 1.f;
  const float scale = norm[0];
  for (int c = 0; c < 3; ++c) {
    const size_t i = image_index(planar, npix, p, c);
    const float xv = x[i], yv = y[i];
    const float b_mx = blur_v(hc, npix, 0 + c, p, width, t0, t1);
    const float b_exx = blur_v(hc, npix, 3 + c, p, width, t0, t1);
    const float b_exy = blur_v(hc, npix, 6 + c, p, width, t0, t1);
    const float diff = xv - yv;
    const float sgn = diff > 0.f ? 1.f : (diff < 0.f ? -1.f : 0.f);  // torch: sign(0) = 0
    grad[i] = scale * (b_mx + 2.f * xv * b_exx + yv * b_exy + (1.f - lambda) * w * sgn);
  }
}
