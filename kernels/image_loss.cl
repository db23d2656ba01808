// Photometric loss of 3DGS between a rendered image x and a target y, 3
// channels (docs/design.md section 4):
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
// factored out of the blurs and applied last, so the pixel passes need no
// reduction result.
//
// Work split: a work-item handles LANES horizontally adjacent pixels of one
// row (a segment) as one vector, LANES = 16 on CPUs (explicit SIMD), 1 on
// GPUs. Every pixel's arithmetic is the same whatever LANES and the
// work-group size, so gradients are bit-identical across them; only the
// partial sums of the loss are grouped differently.
//
// Buffers use one of two layouts, chosen per call by `planar`: interleaved
// [H,W,3] (RenderOutput.rgb on the host) or planar [3,H,W] (the renderer's
// device images). Scratch planes are [plane,H,W]. Reductions: per work-group
// partial sums in a fixed tree order, no floating-point atomics.
//
// Defines: WG (work-group size, a power of two), LANES (1, 2, 4, 8 or 16),
// GW0..GW5 (the normalised 1D window at distances 0..5), SSIM_C1, SSIM_C2.

#define RADIUS 5
#define TAPS (2 * RADIUS + 1)
#define SPAN (LANES + 2 * RADIUS)  // pixels one segment's horizontal blur reads

__constant float kWindow[TAPS] = {GW5, GW4, GW3, GW2, GW1, GW0, GW1, GW2, GW3, GW4, GW5};
__constant float kLaneIds[16] = {0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15};

// --------------------------------------------------------------- lanes
#if LANES == 1
typedef float lfloat;
#define LLOAD(p) (*(p))
#define LSTORE(v, p) (*(p) = (v))
#define LANE_IDS 0.f
#else
typedef CAT(float, LANES) lfloat;
#define LLOAD(p) CAT(vload, LANES)(0, p)
#define LSTORE(v, p) CAT(vstore, LANES)(v, 0, p)
#define LANE_IDS CAT(vload, LANES)(0, kLaneIds)
#endif

// The sum of the lanes in index order.
inline float lane_sum(lfloat v) {
  float a[LANES];
  LSTORE(v, a);
  float s = a[0];
  for (int l = 1; l < LANES; ++l) s += a[l];
  return s;
}

// One segment: pixels (x0 .. x0 + LANES - 1, row); lanes past the right edge
// are computed on zeros and masked out of every store and sum.
typedef struct {
  int row, x0;
  lfloat inside;  // 1 for lanes inside the image, else 0
} Segment;

// Returns 0 for work-items past the last row.
inline int segment(int width, int height, Segment* s) {
  const int per_row = (width + LANES - 1) / LANES;
  const size_t i = get_global_id(0);
  if (i >= (size_t)per_row * height) return 0;
  s->row = (int)(i / per_row);
  s->x0 = (int)(i % per_row) * LANES;
  s->inside = ((float)s->x0 + LANE_IDS < (float)width) ? (lfloat)1.f : (lfloat)0.f;
  return 1;
}

// LANES values of a row from x0; zero past the right edge (never read there).
inline lfloat load_seg(__global const float* row, int x0, int width) {
  if (x0 + LANES <= width) return LLOAD(row + x0);
  float tmp[LANES];
  for (int l = 0; l < LANES; ++l) tmp[l] = x0 + l < width ? row[x0 + l] : 0.f;
  return LLOAD(tmp);
}
inline void store_seg(lfloat v, __global float* row, int x0, int width) {
  if (x0 + LANES <= width) {
    LSTORE(v, row + x0);
    return;
  }
  float tmp[LANES];
  LSTORE(v, tmp);
  for (int l = 0; l < LANES && x0 + l < width; ++l) row[x0 + l] = tmp[l];
}

// Channel c of an image pixel (row, col) in either layout.
inline size_t image_index(int planar, size_t npix, int width, int row, int col, int c) {
  const size_t p = (size_t)row * width + col;
  return planar ? (size_t)c * npix + p : p * 3 + c;
}
inline lfloat load_image_seg(__global const float* img, int planar, size_t npix, int width, Segment s, int c) {
  if (planar) return load_seg(img + (size_t)c * npix + (size_t)s.row * width, s.x0, width);
  float tmp[LANES];
  for (int l = 0; l < LANES; ++l)
    tmp[l] = s.x0 + l < width ? img[image_index(0, npix, width, s.row, s.x0 + l, c)] : 0.f;
  return LLOAD(tmp);
}
inline void store_image_seg(lfloat v, __global float* img, int planar, size_t npix, int width, Segment s, int c) {
  if (planar) {
    store_seg(v, img + (size_t)c * npix + (size_t)s.row * width, s.x0, width);
    return;
  }
  float tmp[LANES];
  LSTORE(v, tmp);
  for (int l = 0; l < LANES && s.x0 + l < width; ++l) img[image_index(0, npix, width, s.row, s.x0 + l, c)] = tmp[l];
}

// Horizontal blur of a span of values: out = sum_t g_t span[t .. t + LANES).
// span[k] is the pixel at column x0 - RADIUS + k, zero outside the image.
inline lfloat blur_span(const float* span) {
  lfloat s = (lfloat)0.f;
  for (int t = 0; t < TAPS; ++t) s += kWindow[t] * LLOAD(span + t);
  return s;
}

// Whether a segment's horizontal window lies inside the image: then vectors
// are loaded straight from the row; else through a zero-padded span. Both
// sum the same nonzero terms in the same order.
inline int interior(int x0, int width) {
  return x0 >= RADIUS && x0 + LANES + RADIUS <= width;
}

// Horizontal blur of one row of an [H,W] plane at a segment.
inline lfloat blur_h(__global const float* row, int x0, int width) {
  if (interior(x0, width)) {
    __global const float* r = row + x0 - RADIUS;
    lfloat s = (lfloat)0.f;
    for (int t = 0; t < TAPS; ++t) s += kWindow[t] * LLOAD(r + t);
    return s;
  }
  float span[SPAN];
  for (int k = 0; k < SPAN; ++k) {
    const int col = x0 - RADIUS + k;
    span[k] = col >= 0 && col < width ? row[col] : 0.f;
  }
  return blur_span(span);
}

// Vertical blur at a segment of one [H,W] plane; rows outside the image are
// zero (skipped: the same for all lanes).
inline lfloat blur_v(__global const float* plane, Segment s, int width, int height) {
  lfloat acc = (lfloat)0.f;
  for (int t = -RADIUS; t <= RADIUS; ++t) {
    const int r = s.row + t;
    if (r < 0 || r >= height) continue;
    acc += kWindow[t + RADIUS] * load_seg(plane + (size_t)r * width, s.x0, width);
  }
  return acc;
}

// --------------------------------------------------------------- SSIM
// S and its partials with respect to the raw moments (mx, Exx, Exy) of x,
// from those with respect to the central moments (mx, sxx, sxy):
//   dS/dsxx = -S / D2,  dS/dsxy = 2 N1 / (D1 D2),
//   dS/dmx|central = 2 my N2 / (D1 D2) - 2 mx S / D1,
// and sxx = Exx - mx^2, sxy = Exy - mx my give
//   dS/dmx = dS/dmx|central - 2 mx dS/dsxx - my dS/dsxy,
//   dS/dExx = dS/dsxx, dS/dExy = dS/dsxy.
inline lfloat ssim_partials(lfloat mx, lfloat my, lfloat exx, lfloat eyy, lfloat exy, lfloat* ds_dmx,
                            lfloat* ds_dexx, lfloat* ds_dexy) {
  const lfloat sxx = exx - mx * mx, syy = eyy - my * my, sxy = exy - mx * my;
  const lfloat n1 = 2.f * mx * my + SSIM_C1, n2 = 2.f * sxy + SSIM_C2;
  const lfloat d1 = mx * mx + my * my + SSIM_C1, d2 = sxx + syy + SSIM_C2;
  const lfloat inv_d = 1.f / (d1 * d2);
  const lfloat s = n1 * n2 * inv_d;
  *ds_dexx = -s / d2;
  *ds_dexy = 2.f * n1 * inv_d;
  const lfloat ds_dmx_central = 2.f * my * n2 * inv_d - 2.f * mx * s / d1;
  *ds_dmx = ds_dmx_central - 2.f * mx * *ds_dexx - my * *ds_dexy;
  return s;
}

// Window sums of x, y, x^2, y^2, xy.
typedef struct {
  lfloat x, y, xx, yy, xy;
} Moments;

inline void add_tap(Moments* m, float g, lfloat xv, lfloat yv) {
  m->x += g * xv;
  m->y += g * yv;
  m->xx += g * (xv * xv);
  m->yy += g * (yv * yv);
  m->xy += g * (xv * yv);
}

// Pass 1: horizontal blur of x, y, x^2, y^2 and xy for each channel.
__kernel void ssim_blur_h(int width, int height, int planar,
                          __global const float* x,  // [H,W,3] or [3,H,W] rendered
                          __global const float* y,  // same layout, target
                          __global float* h) {      // [5,3,H,W] (x, y, xx, yy, xy) x channel
  Segment s;
  if (!segment(width, height, &s)) return;
  const size_t npix = (size_t)width * height, row_off = (size_t)s.row * width;
  for (int c = 0; c < 3; ++c) {
    Moments m = {(lfloat)0.f, (lfloat)0.f, (lfloat)0.f, (lfloat)0.f, (lfloat)0.f};
    if (planar && interior(s.x0, width)) {
      __global const float* xr = x + (size_t)c * npix + row_off + s.x0 - RADIUS;
      __global const float* yr = y + (size_t)c * npix + row_off + s.x0 - RADIUS;
      for (int t = 0; t < TAPS; ++t) add_tap(&m, kWindow[t], LLOAD(xr + t), LLOAD(yr + t));
    } else {
      float xs[SPAN], ys[SPAN];
      for (int k = 0; k < SPAN; ++k) {
        const int col = s.x0 - RADIUS + k;
        const int in = col >= 0 && col < width;
        const size_t i = image_index(planar, npix, width, s.row, in ? col : 0, c);
        xs[k] = in ? x[i] : 0.f;
        ys[k] = in ? y[i] : 0.f;
      }
      for (int t = 0; t < TAPS; ++t) add_tap(&m, kWindow[t], LLOAD(xs + t), LLOAD(ys + t));
    }
    store_seg(m.x, h + (size_t)(0 + c) * npix + row_off, s.x0, width);
    store_seg(m.y, h + (size_t)(3 + c) * npix + row_off, s.x0, width);
    store_seg(m.xx, h + (size_t)(6 + c) * npix + row_off, s.x0, width);
    store_seg(m.yy, h + (size_t)(9 + c) * npix + row_off, s.x0, width);
    store_seg(m.xy, h + (size_t)(12 + c) * npix + row_off, s.x0, width);
  }
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
  float4 sums = (float4)(0.f);
  Segment s;
  if (segment(width, height, &s)) {
    const size_t npix = (size_t)width * height, row_off = (size_t)s.row * width;
    const lfloat w = s.inside * (has_weights ? load_seg(weights + row_off, s.x0, width) : (lfloat)1.f);
    lfloat l1 = (lfloat)0.f, ssim = (lfloat)0.f, sq = (lfloat)0.f;
    for (int c = 0; c < 3; ++c) {
      const lfloat mx = blur_v(h + (size_t)(0 + c) * npix, s, width, height);
      const lfloat my = blur_v(h + (size_t)(3 + c) * npix, s, width, height);
      const lfloat exx = blur_v(h + (size_t)(6 + c) * npix, s, width, height);
      const lfloat eyy = blur_v(h + (size_t)(9 + c) * npix, s, width, height);
      const lfloat exy = blur_v(h + (size_t)(12 + c) * npix, s, width, height);
      lfloat d_mx, d_exx, d_exy;
      ssim += ssim_partials(mx, my, exx, eyy, exy, &d_mx, &d_exx, &d_exy);
      if (want_grad) {
        const lfloat a = -lambda * w;
        store_seg(a * d_mx, coef + (size_t)(0 + c) * npix + row_off, s.x0, width);
        store_seg(a * d_exx, coef + (size_t)(3 + c) * npix + row_off, s.x0, width);
        store_seg(a * d_exy, coef + (size_t)(6 + c) * npix + row_off, s.x0, width);
      }
      const lfloat diff = load_image_seg(x, planar, npix, width, s, c) - load_image_seg(y, planar, npix, width, s, c);
      l1 += fabs(diff);
      sq += diff * diff;
    }
    // w is 0 in lanes past the edge; select keeps NaN/Inf there out of the sums.
    const lfloat zero = (lfloat)0.f;
    sums = (float4)(lane_sum(s.inside > 0.f ? w * l1 : zero), lane_sum(s.inside > 0.f ? w * ssim : zero),
                    lane_sum(s.inside > 0.f ? w * sq : zero), lane_sum(w));
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
  Segment s;
  if (!segment(width, height, &s)) return;
  const size_t npix = (size_t)width * height, row_off = (size_t)s.row * width;
  for (int k = 0; k < 9; ++k)
    store_seg(blur_h(coef + (size_t)k * npix + row_off, s.x0, width), out + (size_t)k * npix + row_off, s.x0, width);
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
  Segment s;
  if (!segment(width, height, &s)) return;
  const size_t npix = (size_t)width * height;
  const lfloat w = has_weights ? load_seg(weights + (size_t)s.row * width, s.x0, width) : (lfloat)1.f;
  const float scale = norm[0];
  for (int c = 0; c < 3; ++c) {
    const lfloat xv = load_image_seg(x, planar, npix, width, s, c);
    const lfloat yv = load_image_seg(y, planar, npix, width, s, c);
    const lfloat b_mx = blur_v(hc + (size_t)(0 + c) * npix, s, width, height);
    const lfloat b_exx = blur_v(hc + (size_t)(3 + c) * npix, s, width, height);
    const lfloat b_exy = blur_v(hc + (size_t)(6 + c) * npix, s, width, height);
    // sign(0) = 0, as torch's abs backward.
    const lfloat g = scale * (b_mx + 2.f * xv * b_exx + yv * b_exy + (1.f - lambda) * w * sign(xv - yv));
    store_image_seg(g, grad, planar, npix, width, s, c);
  }
}
