// The sky: a colour per ray direction behind every Gaussian (host:
// host/render/sky.h). The colour is a sum of real spherical harmonics of
// the world-space viewing direction, K = (degree + 1)^2 coefficients per
// channel, with no offset and no clamp (linear in the coefficients). A
// rendered pixel becomes
//
//   out = rgb + T * sky(d),   T = 1 - alpha
//
// where rgb is the renderer's blend over a black background. d is the unit
// direction of the ray through the pixel centre: camera ray ((x + 0.5 - cx)
// / fx, (y + 0.5 - cy) / fy, 1) rotated by R^T (rows r0, r1, r2 below).
// Images are planar [3, H, W]; alpha is [H, W]. SKY_K (the host defines
// it, K) is a compile-time constant so the basis loops unroll and
// sh_basis's switch folds away.
#ifndef SKY_K
#define SKY_K 16
#endif

// The kernels below that work per pixel use scalars, not float3
// arithmetic: PoCL runs a kernel's work-items 8 or 16 at a time in SIMD
// registers only when the kernel computes with scalars (vector-typed
// arithmetic keeps its work-item loop scalar), which made sky_compose
// twice as fast on a CPU. The operations and their order are those of the float3
// forms (normalize as the rotated ray times rsqrt of its squared length,
// each channel summed over k in order), and the cup's model keeps its
// bytes on PoCL.
inline float3 sky_direction(int x, int y, float4 r0, float4 r1, float4 r2, float4 intr) {
  const float cx = ((float)x + 0.5f - intr.z) / intr.x, cy = ((float)y + 0.5f - intr.w) / intr.y;
  const float dx = r0.x * cx + r0.y * cy + r0.z, dy = r1.x * cx + r1.y * cy + r1.z;
  const float dz = r2.x * cx + r2.y * cy + r2.z;
  const float il = rsqrt(dx * dx + dy * dy + dz * dz);
  return (float3)(dx * il, dy * il, dz * il);
}

// sky(d), each channel into its own float.
ALWAYS_INLINE void sky_colour(__global const float* coef, float3 d, float* r, float* g, float* b) {
  float cr = 0.f, cg = 0.f, cb = 0.f;
#define SKY_TERM(k)                             \
  {                                             \
    float3 unused;                              \
    const float y = sh_basis(k, d, &unused);    \
    cr += y * coef[3 * (k)];                    \
    cg += y * coef[3 * (k) + 1];                \
    cb += y * coef[3 * (k) + 2];                \
  }
  SH_EACH(SKY_K, SKY_TERM)
#undef SKY_TERM
  *r = cr;
  *g = cg;
  *b = cb;
}

// out = rgb + (1 - alpha) * sky(d), and sky(d) itself into sky_out for the
// backward pass. One work-item per pixel.
__kernel void sky_compose(int w, int h, float4 r0, float4 r1, float4 r2, float4 intr,
                          __global const float* coef,   // [K,3]
                          __global const float* rgb,    // [3,H,W]
                          __global const float* alpha,  // [H,W]
                          __global float* out,          // [3,H,W]
                          __global float* sky_out) {    // [3,H,W]
  const int p = get_global_id(0);
  const int npix = w * h;
  if (p >= npix) return;
  float sr, sg, sb;
  sky_colour(coef, sky_direction(p % w, p / w, r0, r1, r2, intr), &sr, &sg, &sb);
  const float t = 1.f - alpha[p];
  out[p] = rgb[p] + t * sr;
  out[npix + p] = rgb[npix + p] + t * sg;
  out[2 * npix + p] = rgb[2 * npix + p] + t * sb;
  sky_out[p] = sr;
  sky_out[npix + p] = sg;
  sky_out[2 * npix + p] = sb;
}

// sky(d) alone, [3,H,W] (a backward pass with no compose before it).
__kernel void sky_colours(int w, int h, float4 r0, float4 r1, float4 r2, float4 intr,
                          __global const float* coef,  // [K,3]
                          __global float* sky_out) {   // [3,H,W]
  const int p = get_global_id(0);
  const int npix = w * h;
  if (p >= npix) return;
  float sr, sg, sb;
  sky_colour(coef, sky_direction(p % w, p / w, r0, r1, r2, intr), &sr, &sg, &sb);
  sky_out[p] = sr;
  sky_out[npix + p] = sg;
  sky_out[2 * npix + p] = sb;
}

// Backward of sky_compose for an upstream gradient g = dL/d out [3,H,W]
// (which is also dL/d rgb, left to the caller):
//   dL/d alpha[p] = base[p] - <g(p), sky(d)>   (base: the caller's alpha
//                   gradient, or 0 when add_base is 0)
//   dL/d coef[k,c] = sum over pixels of W(p) T(p) Y_k(d) g_c(p)
// W(p) is the pixel's weight (1 without one): the trainer gives 0 where
// an SfM point shows that a surface is there, so only open pixels teach
// the sky (host/render/sky.h, open_sky_pixels).
// The coefficient sums run in two deterministic passes, no atomics: work-item
// i sums the pixels [i * chunk, (i + 1) * chunk) in order into partial[i] (K*3
// floats), then sky_grad_reduce adds the partial rows in order. sky(d) comes
// from the compose pass; the basis is evaluated only for pixels of nonzero
// weight (a zero weight adds exact zeros to the sums).
__kernel void sky_grad_partial(int w, int h, int chunk, float4 r0, float4 r1, float4 r2, float4 intr,
                               __global const float* sky,         // [3,H,W] sky(d) per pixel
                               __global const float* grad_out,    // [3,H,W]
                               __global const float* alpha,       // [H,W]
                               int use_weight,                    // 0: every pixel weighs 1
                               __global const float* weight,      // [H,W] the pixel's share in the coefficient sums
                               int add_base,                      // grad_alpha holds a gradient to add to
                               __global float* grad_alpha,        // [H,W]
                               int rows,                          // work-items that write a partial row
                               __global float* partial) {         // [rows, K*3]
  const int i = get_global_id(0);
  if (i >= rows) return;
  const int npix = w * h;
  float acc[SKY_K * 3];
#pragma unroll
  for (int j = 0; j < SKY_K * 3; ++j) acc[j] = 0.f;
  const int end = min(npix, (i + 1) * chunk);
  for (int p = i * chunk; p < end; ++p) {
    const float3 g = (float3)(grad_out[p], grad_out[npix + p], grad_out[2 * npix + p]);
    const float3 s = (float3)(sky[p], sky[npix + p], sky[2 * npix + p]);
    grad_alpha[p] = (add_base ? grad_alpha[p] : 0.f) - dot(g, s);
    const float wp = use_weight ? weight[p] : 1.f;
    if (wp == 0.f) continue;
    const float3 d = sky_direction(p % w, p / w, r0, r1, r2, intr);
    const float t = 1.f - alpha[p];
    const float3 tg = (use_weight ? t * wp : t) * g;
#pragma unroll
    for (int k = 0; k < SKY_K; ++k) {
      float3 unused;
      const float b = sh_basis(k, d, &unused);
      acc[3 * k] += b * tg.x;
      acc[3 * k + 1] += b * tg.y;
      acc[3 * k + 2] += b * tg.z;
    }
  }
  for (int j = 0; j < SKY_K * 3; ++j) partial[i * SKY_K * 3 + j] = acc[j];
}

// grad[j] = sum over rows r (in order) of partial[r, j], j < K*3.
__kernel void sky_grad_reduce(int rows, int values,
                              __global const float* partial,  // [rows, values]
                              __global float* grad) {         // [values]
  const int j = get_global_id(0);
  if (j >= values) return;
  float s = 0.f;
  for (int r = 0; r < rows; ++r) s += partial[r * values + j];
  grad[j] = s;
}

// The normal equations of fitting the sky alone to an image [3,H,W]
// (every pixel as if no Gaussian covered it), each pixel weighted by W(p)
// (1 without weights): per partial row, the Gram matrix sum W Y_k Y_l (K*K,
// row-major), then sum W Y_k I_c (K*3), then sum W I_c^2 (3). Summed over rows by
// sky_grad_reduce, over views in double on the host.
__kernel void sky_fit_partial(int w, int h, int chunk, float4 r0, float4 r1, float4 r2, float4 intr,
                              __global const float* image,  // [3,H,W]
                              int use_weight,
                              __global const float* weight,  // [H,W]
                              int rows,
                              __global float* partial) {    // [rows, K*K + K*3 + 3]
  const int i = get_global_id(0);
  if (i >= rows) return;
  const int npix = w * h;
  const int values = SKY_K * SKY_K + 3 * SKY_K + 3;
  __global float* out = partial + i * values;
  for (int j = 0; j < values; ++j) out[j] = 0.f;
  const int end = min(npix, (i + 1) * chunk);
  for (int p = i * chunk; p < end; ++p) {
    const float3 d = sky_direction(p % w, p / w, r0, r1, r2, intr);
    const float wp = use_weight ? weight[p] : 1.f;
    if (wp == 0.f) continue;
    const float3 c = wp * (float3)(image[p], image[npix + p], image[2 * npix + p]);
    float b[SKY_K];
#pragma unroll
    for (int k = 0; k < SKY_K; ++k) {
      float3 unused;
      b[k] = sh_basis(k, d, &unused);
    }
    for (int k = 0; k < SKY_K; ++k) {
      for (int l = 0; l < SKY_K; ++l) out[k * SKY_K + l] += wp * b[k] * b[l];
      out[SKY_K * SKY_K + 3 * k] += b[k] * c.x;
      out[SKY_K * SKY_K + 3 * k + 1] += b[k] * c.y;
      out[SKY_K * SKY_K + 3 * k + 2] += b[k] * c.z;
    }
    // sum of W I^2 per channel: the fit's residual without a second pass.
    out[SKY_K * SKY_K + 3 * SKY_K] += c.x * image[p];
    out[SKY_K * SKY_K + 3 * SKY_K + 1] += c.y * image[npix + p];
    out[SKY_K * SKY_K + 3 * SKY_K + 2] += c.z * image[2 * npix + p];
  }
}
