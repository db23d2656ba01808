// Shared device code: vector-width plumbing, small matrix helpers, and every
// differentiable helper beside its vector-Jacobian product (v_<name>).
// The host prepends "#define"s (VW, pixels per work-item, and the
// kernel-specific settings), then kernels/layout.h.

// Identical float operations in forward and backward kernels, so that the
// backward pass reproduces the forward pass's discrete decisions exactly.
#pragma OPENCL FP_CONTRACT OFF

#define TILE_PIXELS (TILE * TILE)

// For helpers that take or return structs of vectors (blend_vjp, load_totals,
// sky_colour): PoCL compiles a call that stays a call with those structs in
// memory, so the blend backward spent a third of its time passing them. Inlined,
// they stay in registers (the cup's blend_bwd 13.1 -> 10.2 ms a step on 2
// cores, same bits). The small helpers of the projection (3x3 matrices,
// ewa_project, one call a kernel) are inlined for Oclgrind's -Oz build,
// which otherwise keeps their structs in private memory. Helpers that PoCL
// inlines itself, or whose calls are cheaper than the code they would
// duplicate, keep plain inline.
#define ALWAYS_INLINE inline __attribute__((always_inline))

#define CAT_(a, b) a##b
#define CAT(a, b) CAT_(a, b)

// --------------------------------------------------------------- vectors
// vfloat holds VW horizontally adjacent pixels of one tile row. On CPUs
// (VW = 16) PoCL maps it to SIMD registers; on GPUs VW = 1 and it is a float.
#if VW == 1
typedef float vfloat;
typedef int vint;
#define LANE_OFFSETS 0.0f
#define ANY(m) ((m) != 0)
#define VLOAD(p) (*(p))
#define VSTORE(v, p) (*(p) = (v))
#define HSUM(v) (v)
#else
typedef CAT(float, VW) vfloat;
typedef CAT(int, VW) vint;
#define ANY(m) any(m)
#define VLOAD(p) CAT(vload, VW)(0, p)
#define VSTORE(v, p) CAT(vstore, VW)(v, 0, p)
#if VW == 2
#define LANE_OFFSETS ((vfloat)(0, 1))
#define HSUM(v) ((v).s0 + (v).s1)
#elif VW == 4
#define LANE_OFFSETS ((vfloat)(0, 1, 2, 3))
#define HSUM(v) hsum4(v)
#elif VW == 8
#define LANE_OFFSETS ((vfloat)(0, 1, 2, 3, 4, 5, 6, 7))
#define HSUM(v) hsum4((v).lo + (v).hi)
#elif VW == 16
#define LANE_OFFSETS ((vfloat)(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15))
#define HSUM(v) hsum4(((v).lo + (v).hi).lo + ((v).lo + (v).hi).hi)
#endif
#endif
#define WG_SIZE (TILE_PIXELS / VW)
// Lane masks (vint) come from comparisons (all bits set where true in
// vectors, 1 in scalars), are combined with & and |, and negated with NOT
// (~ on vectors). The spec gives vector !, && and || all-bits results too,
// but Oclgrind computes them as 1 (its interpreter's logic on vectors of
// comparison bits), which any() and select() read as false: the kernels use
// those operators on scalars only, so every device reads the masks alike.
#if VW == 1
#define NOT(m) (!(m))
#else
#define NOT(m) (~(m))
#endif

// A fixed summation order: deterministic and the same on every device.
inline float hsum4(float4 v) { return (v.s0 + v.s1) + (v.s2 + v.s3); }

// The activation of opacities and anchor scales (kernels/expander.cl,
// kernels/free_trainer.cl): s = sigmoid(x) = 1 / (1 + e^-x).
inline float sigmoid(float x) { return 1.f / (1.f + exp(-x)); }
// ds/dx = s (1 - s) = sigmoid(x) sigmoid(-x): no cancellation in 1 - s when s -> 1.
inline float sigmoid_vjp(float x, float v_s) { return v_s * (sigmoid(x) * sigmoid(-x)); }

// SH coefficients per channel above the DC term at degree 3: the trainers
// store a Gaussian's SH split, DC [N,3] and rest [N,SH_REST,3].
#define SH_REST 15

// What both trainers' activations (kernels/expander.cl, kernels/free_trainer.cl)
// write alike for Gaussian g: the quaternion as stored, the opacity's
// sigmoid, and the first sh_out SH coefficients (DC, then the rest).
ALWAYS_INLINE void store_quat_opacity_sh(int g, __global const float* quat, __global const float* opacity_logit,
                                         __global const float* sh_dc, __global const float* sh_rest, int sh_out,
                                         __global float* quats, __global float* opacities, __global float* sh) {
  vstore4(vload4(g, quat), g, quats);
  opacities[g] = sigmoid(opacity_logit[g]);
  vstore3(vload3(g, sh_dc), (size_t)g * sh_out, sh);
  for (int k = 1; k < sh_out; ++k) vstore3(vload3((size_t)g * SH_REST + k - 1, sh_rest), (size_t)g * sh_out + k, sh);
}

#ifndef EXPF
#define EXPF native_exp
#endif

// Record and camera layouts (REC_*, G2_*, CAM_*, TILE): kernels/layout.h,
// which the host puts in front of this file.

// --------------------------------------------------------------- 3x3 matrices
typedef struct { float m[9]; } mat3;  // row-major

// The 3x3 helpers are written out entry by entry and always inlined: a
// compiler that neither unrolls loops nor inlines much (Oclgrind builds at
// -Oz) would otherwise pass the matrices through private memory and index
// them element by element.
ALWAYS_INLINE mat3 mat3_mul(mat3 a, mat3 b) {
  mat3 r;
#define MAT3_MUL_ENTRY(i, j) \
  r.m[3 * (i) + (j)] = a.m[3 * (i)] * b.m[j] + a.m[3 * (i) + 1] * b.m[3 + (j)] + a.m[3 * (i) + 2] * b.m[6 + (j)];
  MAT3_MUL_ENTRY(0, 0) MAT3_MUL_ENTRY(0, 1) MAT3_MUL_ENTRY(0, 2)
  MAT3_MUL_ENTRY(1, 0) MAT3_MUL_ENTRY(1, 1) MAT3_MUL_ENTRY(1, 2)
  MAT3_MUL_ENTRY(2, 0) MAT3_MUL_ENTRY(2, 1) MAT3_MUL_ENTRY(2, 2)
#undef MAT3_MUL_ENTRY
  return r;
}
ALWAYS_INLINE mat3 mat3_transpose(mat3 a) {
  mat3 r;
  r.m[0] = a.m[0]; r.m[1] = a.m[3]; r.m[2] = a.m[6];
  r.m[3] = a.m[1]; r.m[4] = a.m[4]; r.m[5] = a.m[7];
  r.m[6] = a.m[2]; r.m[7] = a.m[5]; r.m[8] = a.m[8];
  return r;
}
ALWAYS_INLINE float3 mat3_vec(mat3 a, float3 v) {
  return (float3)(a.m[0] * v.x + a.m[1] * v.y + a.m[2] * v.z, a.m[3] * v.x + a.m[4] * v.y + a.m[5] * v.z,
                  a.m[6] * v.x + a.m[7] * v.y + a.m[8] * v.z);
}
ALWAYS_INLINE mat3 mat3_load(__constant const float* p) {
  mat3 r;
  r.m[0] = p[0]; r.m[1] = p[1]; r.m[2] = p[2];
  r.m[3] = p[3]; r.m[4] = p[4]; r.m[5] = p[5];
  r.m[6] = p[6]; r.m[7] = p[7]; r.m[8] = p[8];
  return r;
}

// --------------------------------------------------------------- quaternion
// R(q) for a unit quaternion q = (w, x, y, z).
ALWAYS_INLINE mat3 quat_to_rotmat(float4 q) {
  float w = q.x, x = q.y, y = q.z, z = q.w;
  mat3 r;
  r.m[0] = 1.f - 2.f * (y * y + z * z); r.m[1] = 2.f * (x * y - w * z);       r.m[2] = 2.f * (x * z + w * y);
  r.m[3] = 2.f * (x * y + w * z);       r.m[4] = 1.f - 2.f * (x * x + z * z); r.m[5] = 2.f * (y * z - w * x);
  r.m[6] = 2.f * (x * z - w * y);       r.m[7] = 2.f * (y * z + w * x);       r.m[8] = 1.f - 2.f * (x * x + y * y);
  return r;
}
// v_q = sum_ij G_ij dR_ij/dq, each entry of R being quadratic in q.
inline float4 quat_to_rotmat_vjp(float4 q, mat3 G) {
  float w = q.x, x = q.y, y = q.z, z = q.w;
  const float* g = G.m;
  float vw = 2.f * (-z * g[1] + y * g[2] + z * g[3] - x * g[5] - y * g[6] + x * g[7]);
  float vx = 2.f * (y * g[1] + z * g[2] + y * g[3] - 2.f * x * g[4] - w * g[5] + z * g[6] + w * g[7] - 2.f * x * g[8]);
  float vy = 2.f * (-2.f * y * g[0] + x * g[1] + w * g[2] + x * g[3] + z * g[5] - w * g[6] + z * g[7] - 2.f * y * g[8]);
  float vz = 2.f * (-2.f * z * g[0] - w * g[1] + x * g[2] + w * g[3] - 2.f * z * g[4] + y * g[5] + x * g[6] + y * g[7]);
  return (float4)(vw, vx, vy, vz);
}
// q = raw / |raw|: v_raw = (v_q - q (q . v_q)) / |raw|.
inline float4 normalize_vjp(float4 q_unit, float inv_norm, float4 v_q) {
  return (v_q - q_unit * dot(q_unit, v_q)) * inv_norm;
}

// --------------------------------------------------------------- spherical harmonics
#define SH_C0 0.28209479177387814f
#define SH_C1 0.4886025119029199f
// Basis function k (3DGS order) at unit direction d, and its gradient in d.
// Always inlined: with a constant k the switch and the unused gradient fold
// away.
ALWAYS_INLINE float sh_basis(int k, float3 d, float3* grad) {
  float x = d.x, y = d.y, z = d.z;
  float xx = x * x, yy = y * y, zz = z * z;
  switch (k) {
    case 0: *grad = (float3)(0.f); return SH_C0;
    case 1: *grad = (float3)(0.f, -SH_C1, 0.f); return -SH_C1 * y;
    case 2: *grad = (float3)(0.f, 0.f, SH_C1); return SH_C1 * z;
    case 3: *grad = (float3)(-SH_C1, 0.f, 0.f); return -SH_C1 * x;
    case 4: { const float c = 1.0925484305920792f; *grad = (float3)(c * y, c * x, 0.f); return c * x * y; }
    case 5: { const float c = -1.0925484305920792f; *grad = (float3)(0.f, c * z, c * y); return c * y * z; }
    case 6: { const float c = 0.31539156525252005f;
              *grad = (float3)(-2.f * c * x, -2.f * c * y, 4.f * c * z); return c * (2.f * zz - xx - yy); }
    case 7: { const float c = -1.0925484305920792f; *grad = (float3)(c * z, 0.f, c * x); return c * x * z; }
    case 8: { const float c = 0.5462742152960396f; *grad = (float3)(2.f * c * x, -2.f * c * y, 0.f); return c * (xx - yy); }
    case 9: { const float c = -0.5900435899266435f;
              *grad = (float3)(6.f * c * x * y, c * (3.f * xx - 3.f * yy), 0.f); return c * y * (3.f * xx - yy); }
    case 10: { const float c = 2.890611442640554f;
               *grad = (float3)(c * y * z, c * x * z, c * x * y); return c * x * y * z; }
    case 11: { const float c = -0.4570457994644658f;
               *grad = (float3)(-2.f * c * x * y, c * (4.f * zz - xx - 3.f * yy), 8.f * c * y * z);
               return c * y * (4.f * zz - xx - yy); }
    case 12: { const float c = 0.3731763325901154f;
               *grad = (float3)(-6.f * c * x * z, -6.f * c * y * z, c * (6.f * zz - 3.f * xx - 3.f * yy));
               return c * z * (2.f * zz - 3.f * xx - 3.f * yy); }
    case 13: { const float c = -0.4570457994644658f;
               *grad = (float3)(c * (4.f * zz - 3.f * xx - yy), -2.f * c * x * y, 8.f * c * x * z);
               return c * x * (4.f * zz - xx - yy); }
    case 14: { const float c = 1.445305721320277f;
               *grad = (float3)(2.f * c * x * z, -2.f * c * y * z, c * (xx - yy)); return c * z * (xx - yy); }
    default: { const float c = -0.5900435899266435f;
               *grad = (float3)(c * (3.f * xx - 3.f * yy), -6.f * c * x * y, 0.f); return c * x * (xx - 3.f * yy); }
  }
}

// F(k) for k = 0, 1, ... below n (1, 4, 9 or 16, a compile-time constant),
// written out: a loop over sh_basis unrolls into straight-line code where
// the compiler does not unroll loops on its own (Oclgrind builds at -Oz and
// would interpret a call, a switch and a counter per coefficient).
#define SH_EACH(n, F)                                              \
  {                                                                \
    F(0)                                                           \
    if ((n) > 1) { F(1) F(2) F(3) }                                \
    if ((n) > 4) { F(4) F(5) F(6) F(7) F(8) }                      \
    if ((n) > 9) { F(9) F(10) F(11) F(12) F(13) F(14) F(15) }      \
  }

// Unit view direction from the camera centre to a mean; zero when they meet.
ALWAYS_INLINE float3 view_dir(float3 mean, float3 campos, float* inv_norm) {
  float3 d = mean - campos;
  float n2 = dot(d, d);
  *inv_norm = n2 > 0.f ? rsqrt(n2) : 0.f;
  return d * *inv_norm;
}

// Depth mapped for the distortion loss (2DGS): m = f/(f-n) (1 - n/z).
inline float dist_depth(float z, float n, float f) { return f / (f - n) * (1.f - n / z); }
// dm/dz = f/(f-n) n / z^2
inline float dist_depth_vjp(float z, float n, float f) { return f / (f - n) * n / (z * z); }

// --------------------------------------------------------------- EWA projection
// Quantities of one Gaussian's projection kept for the backward pass.
typedef struct {
  float3 p;        // camera-space mean
  float4 q;        // unit quaternion
  float inv_qnorm; // 1 / |raw quaternion|
  mat3 Rq;         // rotation of the Gaussian
  mat3 Sigma_c;    // camera-space covariance
  float J[6];      // 2x3 Jacobian of the perspective map (clamped, 3DGS style)
  int clamp_x, clamp_y;  // which side the clamp hit: -1, 0, +1
  float lim_x, lim_y;    // the limit used when clamped (signed)
  float a, b, c;   // 2D covariance incl. low-pass
} Proj;

// Camera-space mean, covariance and its 2D EWA image (docs/rasterizer.md 2-6).
// Returns 0 when the Gaussian is culled by the near plane or a bad quaternion.
ALWAYS_INLINE int ewa_project(__constant const float* cam, float3 mean, float3 scale, float4 qraw, Proj* o) {
  mat3 R = mat3_load(cam + CAM_R);
  float3 t = (float3)(cam[CAM_T], cam[CAM_T + 1], cam[CAM_T + 2]);
  o->p = mat3_vec(R, mean) + t;
  if (!(o->p.z > cam[CAM_NEAR])) return 0;
  float qn2 = dot(qraw, qraw);
  if (!(qn2 >= 1e-20f)) return 0;
  o->inv_qnorm = rsqrt(qn2);
  o->q = qraw * o->inv_qnorm;
  o->Rq = quat_to_rotmat(o->q);
  // Sigma = M M^T with M = Rq diag(scale); Sigma_c = R Sigma R^T = (R M)(R M)^T.
  mat3 M = o->Rq;
  M.m[0] *= scale.x; M.m[1] *= scale.y; M.m[2] *= scale.z;
  M.m[3] *= scale.x; M.m[4] *= scale.y; M.m[5] *= scale.z;
  M.m[6] *= scale.x; M.m[7] *= scale.y; M.m[8] *= scale.z;
  mat3 RM = mat3_mul(R, M);
  o->Sigma_c = mat3_mul(RM, mat3_transpose(RM));

  float fx = cam[CAM_FX], fy = cam[CAM_FY], cx = cam[CAM_CX], cy = cam[CAM_CY];
  float W = cam[CAM_W], H = cam[CAM_H];
  float z = o->p.z, iz = 1.f / z;
  float tan_x = 0.5f * W / fx, tan_y = 0.5f * H / fy;
  float lim_xp = (W - cx) / fx + 0.3f * tan_x, lim_xn = cx / fx + 0.3f * tan_x;
  float lim_yp = (H - cy) / fy + 0.3f * tan_y, lim_yn = cy / fy + 0.3f * tan_y;
  float rx = o->p.x * iz, ry = o->p.y * iz;
  o->clamp_x = rx > lim_xp ? 1 : (rx < -lim_xn ? -1 : 0);
  o->clamp_y = ry > lim_yp ? 1 : (ry < -lim_yn ? -1 : 0);
  o->lim_x = o->clamp_x > 0 ? lim_xp : -lim_xn;
  o->lim_y = o->clamp_y > 0 ? lim_yp : -lim_yn;
  // tx = clamp(x/z) z; J02 = -fx tx / z^2.
  float tx_over_z2 = o->clamp_x ? o->lim_x * iz : o->p.x * iz * iz;
  float ty_over_z2 = o->clamp_y ? o->lim_y * iz : o->p.y * iz * iz;
  o->J[0] = fx * iz; o->J[1] = 0.f; o->J[2] = -fx * tx_over_z2;
  o->J[3] = 0.f; o->J[4] = fy * iz; o->J[5] = -fy * ty_over_z2;
  // cov2d = J Sigma_c J^T + 0.3 I (low-pass: every splat covers ~1 pixel).
  const float* S = o->Sigma_c.m;
  float JS0[3], JS1[3];
#define JS_ENTRY(k)                                                        \
  JS0[k] = o->J[0] * S[k] + o->J[1] * S[3 + (k)] + o->J[2] * S[6 + (k)]; \
  JS1[k] = o->J[3] * S[k] + o->J[4] * S[3 + (k)] + o->J[5] * S[6 + (k)];
  JS_ENTRY(0) JS_ENTRY(1) JS_ENTRY(2)
#undef JS_ENTRY
  o->a = JS0[0] * o->J[0] + JS0[1] * o->J[1] + JS0[2] * o->J[2] + cam[CAM_LOWPASS];
  o->b = JS0[0] * o->J[3] + JS0[1] * o->J[4] + JS0[2] * o->J[5];
  o->c = JS1[0] * o->J[3] + JS1[1] * o->J[4] + JS1[2] * o->J[5] + cam[CAM_LOWPASS];
  return 1;
}

// --------------------------------------------------------------- blending
// The Gaussian's exponent at pixel offsets (dx, dy) from its centre; shared by
// the forward and backward kernels so both see identical bits.
ALWAYS_INLINE vfloat blend_sigma(float cA, float cB, float cC, vfloat dx, float dy) {
  return 0.5f * (cA * dx * dx + cC * dy * dy) + cB * dx * dy;
}

// exp(-sigma), with sigma capped at 40: beyond it alpha < 1/255 for any
// opacity <= 1, so the Gaussian is skipped either way, and the cap keeps every
// product downstream (alpha T, ...) out of denormals, which cost x86 CPUs
// dearly.
ALWAYS_INLINE vfloat blend_falloff(vfloat sigma) { return EXPF(-fmin(sigma, 40.f)); }

// Whether the alpha test fails at every lane of sigma (blend_sigma's bits)
// for a record whose REC_THR is thr: sigma above ln(255 o) by row_beyond's
// margin gives alpha < 1/255 whatever the rounding of the exponential, and
// a NaN lane fails sigma >= 0. Tested before the exponential, which it
// spares the pixels of a tile that a Gaussian misses (most of them in the
// GPU layout, which has no row test); the outcome is the alpha test's, so
// no bit changes.
ALWAYS_INLINE int out_of_reach(vfloat sigma, float thr) { return !ANY(sigma <= thr + 0.01f); }

// Tile geometry of one work-item: VW adjacent pixels of a tile row.
typedef struct {
  int tile, x0, y;   // first pixel's column, the row
  vfloat px;         // pixel centres (x + 0.5)
  float py;
  vint inside;       // lanes inside the image
} PixelRow;

// Work-item `lid`'s pixels of tile `tile` (CPU kernels walk the rows themselves).
inline PixelRow pixel_row_of(int tile, int lid, int tiles_x, int width, int height) {
  PixelRow r;
  r.tile = tile;
  int p0 = lid * VW;
  r.x0 = (r.tile % tiles_x) * TILE + p0 % TILE;
  r.y = (r.tile / tiles_x) * TILE + p0 / TILE;
  r.px = (float)r.x0 + 0.5f + LANE_OFFSETS;
  r.py = (float)r.y + 0.5f;
  r.inside = r.px < (float)width;
  if (r.y >= height) r.inside = (vint)0;
  return r;
}
inline PixelRow pixel_row(int tiles_x, int width, int height) {
  return pixel_row_of(get_group_id(0), get_local_id(0), tiles_x, width, height);
}

// Conservative test that no pixel of a row can blend record q: 1 only when
// sigma > ln(255 o) (so alpha < 1/255) at every pixel centre of the row, with a
// margin far above the rounding of the kernels' own sigma and exp (relative
// 1e-5 of sigma's terms, absolute 0.01 for the exponential). The true minimum
// of sigma over a row at offset dy is 0.5 dy^2 (cC - cB^2/cA). Skipping such a
// row changes nothing: every lane would have been skipped by the alpha test.
// dx0, dx1: u minus the first and last pixel centre of the row.
ALWAYS_INLINE int row_beyond(float cA, float cB, float cC, float cm, float thr, float dy, float dx0, float dx1) {
  float dxm = fmax(fabs(dx0), fabs(dx1));
  float dy2 = dy * dy;
  float terms = 0.5f * (cA * dxm * dxm + cC * dy2) + fabs(cB) * dxm * fabs(dy);
  return 0.5f * dy2 * cm > thr + 0.01f + 1e-5f * terms;
}

// A bound on |dy| past which row_beyond holds for every row of pixel
// centres whose offsets from u are at most dxm: row_beyond's test with its
// terms written out, 0.5 cm dy^2 - 1e-5 (0.5 (cA dxm^2 + cC dy^2) + |cB| dxm
// |dy|) > thr + 0.01, is a quadratic in |dy| that holds beyond its larger
// root; the root is widened by 1e-4 relative and 1e-3 absolute against its
// own rounding. INFINITY where the quadratic does not grow (a conic so
// elongated that cm is within 1e-5 of cC's scale). The CPU layout's
// backward walks compute it once per Gaussian and tile and skip the rows
// past it with one compare instead of a row test each.
inline float row_reach(float cA, float cB, float cC, float cm, float thr, float dxm) {
  const float a = 0.5f * (cm - 1e-5f * cC);
  if (!(a > 0.f)) return INFINITY;
  const float b = 1e-5f * fabs(cB) * dxm;
  const float c = fmax(thr + 0.01f + 0.5e-5f * cA * dxm * dxm, 0.f);
  const float root = (b + sqrt(b * b + 4.f * a * c)) / (2.f * a);
  return isfinite(root) ? root * 1.0001f + 1e-3f : INFINITY;
}

// row_reach of record q for the rows of a tile whose first pixel centre
// across is x0 (its last x0 + TILE - 1): the CPU layouts' walks, once per
// record and tile.
inline float tile_first_centre(int tile, int tiles_x) { return (float)((tile % tiles_x) * TILE) + 0.5f; }
inline float tile_row_reach(__global const float* q, float x0) {
  const float u = q[REC_U];
  return row_reach(q[REC_CA], q[REC_CB], q[REC_CC], q[REC_CM], q[REC_THR],
                   fmax(fabs(u - x0), fabs(u - (x0 + (float)(TILE - 1)))));
}

// The GPU layout's row test: bit r set when row r of tile `tile` may blend
// the record q. The work-item that stages a record computes its mask once
// for the tile; then each pixel of a row the record cannot reach skips it
// with one bit test instead of its exponent, which changes no bit of the
// result. The rows are those within row_reach of the record's centre, the
// CPU layouts' row test (|dy| <= reach, dy computed as they compute it): one
// square root per record and tile instead of a row_beyond per row.
ALWAYS_INLINE uint reach_mask(float w, float first, float reach) {
  uint mask = 0u;
  for (int r = 0; r < TILE; ++r) mask |= (fabs(w - (first + (float)r)) <= reach ? 1u : 0u) << r;
  return mask;
}
inline uint tile_rows_reached(__local const float* q, int tile, int tiles_x) {
  const float u = q[REC_U];
  const float x0 = (float)((tile % tiles_x) * TILE) + 0.5f, y0 = (float)((tile / tiles_x) * TILE) + 0.5f;
  const float dxm = fmax(fabs(u - x0), fabs(u - (x0 + (float)(TILE - 1))));
  return reach_mask(q[REC_V], y0, row_reach(q[REC_CA], q[REC_CB], q[REC_CC], q[REC_CM], q[REC_THR], dxm));
}

// The column counterpart of tile_rows_reached: bit c set when column c of
// tile `tile` may blend the record q. It is row_reach with x and y swapped:
// over a column at offset dx the least sigma is 0.5 dx^2 (cA - cB^2 / cC).
inline uint tile_cols_reached(__local const float* q, int tile, int tiles_x) {
  const float v = q[REC_V];
  const float x0 = (float)((tile % tiles_x) * TILE) + 0.5f, y0 = (float)((tile / tiles_x) * TILE) + 0.5f;
  const float dym = fmax(fabs(v - y0), fabs(v - (y0 + (float)(TILE - 1))));
  const float cm = q[REC_CA] - q[REC_CB] * q[REC_CB] / q[REC_CC];
  return reach_mask(q[REC_U], x0, row_reach(q[REC_CC], q[REC_CB], q[REC_CA], cm, q[REC_THR], dym));
}

// Copies record gid into slot i of a staged batch: one 16-float vector
// load and store (REC_SIZE is 16) rather than 16 of each.
ALWAYS_INLINE void stage_record(__local float* s_rec, int i, __global const float* records, uint gid) {
#if REC_SIZE == 16
  vstore16(vload16((size_t)gid, records), (size_t)i, s_rec);
#else
  for (int c = 0; c < REC_SIZE; ++c) s_rec[i * REC_SIZE + c] = records[(size_t)gid * REC_SIZE + c];
#endif
}

// Both: the rows in the low TILE bits, the columns in the next TILE.
inline uint tile_reached(__local const float* q, int tile, int tiles_x) {
  return tile_rows_reached(q, tile, tiles_x) | (tile_cols_reached(q, tile, tiles_x) << TILE);
}

// The GPU layout's walk of a staged batch by rows and columns: the batch's
// tile_reached masks become one list per tile row and one per work-item
// column (its VW columns), LIST_WORDS words of bits each (bit b of word w:
// record 32 w + b), and a work-item visits the records in both its row's
// and its columns' lists, in order (pop_record of the two words anded),
// instead of testing every record: it skips only records that cannot blend
// at any of its pixels, so no bit of a result changes. (TILE <= 16: both
// masks fit a uint.)
#ifdef BATCH
#define LIST_WORDS ((BATCH + 31) / 32)
#define REACH_LISTS (TILE + TILE / VW)
// This work-item's two lists: its row's and its columns'.
#define ROW_LIST(pr) (s_list + ((pr).y % TILE) * LIST_WORDS)
#define COL_LIST(pr) (s_list + (TILE + ((pr).x0 % TILE) / VW) * LIST_WORDS)
// The lowest set bit of *m, taken out of it.
ALWAYS_INLINE int pop_record(uint* m) {
  const uint low = *m & (0u - *m);
  *m ^= low;
  return 31 - (int)clz(low);
}
// The next record of list word m (index w) whose exponent at this
// work-item's pixels, *sigma (blend_sigma's bits), passes out_of_reach: its
// index in the batch, or -1 once the word is empty. Every record it passes
// over is one whose alpha test would fail at each pixel: a walk that blends
// only what it returns has the same bits. Keeping the skips in this small
// loop spares the walks' running state a merge after each of them, which an
// interpreter (Oclgrind) pays per state variable.
ALWAYS_INLINE int next_in_reach(uint* m, int w, __local const float* s_rec, PixelRow pr, vfloat* sigma) {
  while (*m != 0u) {
    const int j = w * 32 + pop_record(m);
    __local const float* q = s_rec + j * REC_SIZE;
    *sigma = blend_sigma(q[REC_CA], q[REC_CB], q[REC_CC], q[REC_U] - pr.px, q[REC_V] - pr.py);
    if (!out_of_reach(*sigma, q[REC_THR])) return j;
  }
  return -1;
}
// The lists from the batch's masks s_reach[0, nb): every work-item calls
// reach_lists after the barrier that follows the staging; the lists are
// read after the next barrier.
inline void reach_lists(__local const uint* s_reach, int nb, __local uint* s_list, int lid) {
  for (int k = lid; k < REACH_LISTS * LIST_WORDS; k += WG_SIZE) {
    const int list = k / LIST_WORDS, j0 = (k % LIST_WORDS) * 32;
    // Row `list`, or the column group list - TILE (VW columns).
    const int shift = list < TILE ? list : TILE + (list - TILE) * VW;
    const uint bits = list < TILE ? 1u : (1u << VW) - 1u;
    uint m = 0u;
    int b = 0;
    // Sixteen records at a time as vectors (an interpreter such as Oclgrind
    // runs a vector operation as one step), then one by one to nb.
    for (; b < 32 && j0 + b + 16 <= nb; b += 16) {
      const uint16 hit = as_uint16(((vload16(0, s_reach + j0 + b) >> (uint)shift) & bits) != (uint16)0u) &
                         (uint16)(0x1u, 0x2u, 0x4u, 0x8u, 0x10u, 0x20u, 0x40u, 0x80u, 0x100u, 0x200u, 0x400u, 0x800u,
                                  0x1000u, 0x2000u, 0x4000u, 0x8000u);
      const uint8 h8 = hit.lo | hit.hi;
      const uint4 h4 = h8.lo | h8.hi;
      const uint2 h2 = h4.lo | h4.hi;
      m |= (h2.x | h2.y) << b;
    }
    for (; b < 32 && j0 + b < nb; ++b) m |= (((s_reach[j0 + b] >> shift) & bits) != 0u ? 1u : 0u) << b;
    s_list[k] = m;
  }
}
// The same lists built while staging, for a kernel with no barrier to spare
// between the staging and the walk (blend_bwd: with reach_lists between two
// barriers of its own, PoCL read the lists back wrong where Oclgrind ran it
// clean and bit-exact): reach_lists_clear empties them (every work-item,
// between barriers, after the last walk of them), and the work-item that
// stages record i adds it to its lists with atomic_or on local memory (the
// same bits in any order).
inline void reach_lists_clear(__local uint* s_list, int lid) {
  for (int k = lid; k < REACH_LISTS * LIST_WORDS; k += WG_SIZE) s_list[k] = 0u;
}
inline void reach_lists_add(__local uint* s_list, int i, uint reach) {
  const uint bit = 1u << (i % 32);
  const int w = i / 32;
  for (uint r = reach & ((1u << TILE) - 1u); r != 0u;) atomic_or(&s_list[pop_record(&r) * LIST_WORDS + w], bit);
  for (int c = 0; c < TILE / VW; ++c)
    if (((reach >> (TILE + c * VW)) & ((1u << VW) - 1u)) != 0u) atomic_or(&s_list[(TILE + c) * LIST_WORDS + w], bit);
}
#endif

// Whether the ellipse q(d) = cA dx^2 + 2 cB dx dy + cC dy^2 <= k around
// (u, v) reaches a pixel centre of tile (tx, ty). q is convex, so its
// minimum over the rectangle of the tile's pixel centres is 0 when (u, v)
// lies inside and otherwise on an edge, where it is the edge line's own
// minimum clamped to the edge. Blending skips a Gaussian at every pixel
// with q > k (alpha < 1/255, k = 2 ln(255 o)), so binning leaves out the
// tiles of its bounding box that this test rejects and every picture and
// gradient keeps its bits; the margin (as row_beyond's) covers rounding in
// blending's evaluation. project_fwd counts with it and emit_isects emits
// with it, from the same floats (records) and with FP_CONTRACT OFF, so the
// two agree exactly.
inline float edge_min_q(float cA, float cB, float cC, float e, float lo, float hi, int e_is_x) {
  // The edge at x = e (e_is_x) or y = e; the free coordinate in [lo, hi].
  float a = e_is_x ? cA : cC, c = e_is_x ? cC : cA;
  float f = clamp(-cB * e / c, lo, hi);
  float q = a * e * e + 2.f * cB * e * f + c * f * f;
  float terms = a * e * e + 2.f * fabs(cB * e * f) + c * f * f;
  return q - 2e-5f * terms;
}

inline int tile_touched(float u, float v, float cA, float cB, float cC, float k, int tx, int ty) {
  float x0 = (float)(tx * TILE) + 0.5f - u, x1 = (float)(tx * TILE) + ((float)TILE - 0.5f) - u;
  float y0 = (float)(ty * TILE) + 0.5f - v, y1 = (float)(ty * TILE) + ((float)TILE - 0.5f) - v;
  if (x0 <= 0.f && 0.f <= x1 && y0 <= 0.f && 0.f <= y1) return 1;
  float lim = k + 0.02f;
  return edge_min_q(cA, cB, cC, x0, y0, y1, 1) <= lim || edge_min_q(cA, cB, cC, x1, y0, y1, 1) <= lim ||
         edge_min_q(cA, cB, cC, y0, x0, x1, 0) <= lim || edge_min_q(cA, cB, cC, y1, x0, x1, 0) <= lim;
}

// Load one plane's VW pixels of this row (0 outside the image).
inline vfloat load_row(__global const float* plane, PixelRow r, int width) {
  if (!ANY(r.inside)) return (vfloat)0.f;
  __global const float* p = plane + (size_t)r.y * width + r.x0;
  if (r.x0 + VW <= width) return VLOAD(p);
  float tmp[VW];
  for (int l = 0; l < VW; ++l) tmp[l] = r.x0 + l < width ? p[l] : 0.f;
  return VLOAD(tmp);
}
inline vint load_row_int(__global const int* plane, PixelRow r, int width) {
  if (!ANY(r.inside)) return (vint)0;
  __global const int* p = plane + (size_t)r.y * width + r.x0;
  if (r.x0 + VW <= width) return VLOAD(p);
  int tmp[VW];
  for (int l = 0; l < VW; ++l) tmp[l] = r.x0 + l < width ? p[l] : 0;
  return VLOAD(tmp);
}
inline void store_row(vfloat v, __global float* plane, PixelRow r, int width) {
  if (!ANY(r.inside)) return;
  __global float* p = plane + (size_t)r.y * width + r.x0;
  if (r.x0 + VW <= width) { VSTORE(v, p); return; }
  float tmp[VW];
  VSTORE(v, tmp);
  for (int l = 0; l < VW && r.x0 + l < width; ++l) p[l] = tmp[l];
}
inline void store_row_int(vint v, __global int* plane, PixelRow r, int width) {
  if (!ANY(r.inside)) return;
  __global int* p = plane + (size_t)r.y * width + r.x0;
  if (r.x0 + VW <= width) { VSTORE(v, p); return; }
  int tmp[VW];
  VSTORE(v, tmp);
  for (int l = 0; l < VW && r.x0 + l < width; ++l) p[l] = tmp[l];
}

// --------------------------------------------------------------- blend backward
// Which upstream gradients a blend backward program is given (the host says
// 0 for those that are zero everywhere, and their terms are left out).
#ifndef GRAD_RGB
#define GRAD_RGB 1
#endif
#ifndef GRAD_FEAT
#define GRAD_FEAT 1
#endif
#ifndef GRAD_DEPTH
#define GRAD_DEPTH 1
#endif
#ifndef GRAD_ALPHA
#define GRAD_ALPHA 1
#endif
#ifndef GRAD_DIST
#define GRAD_DIST 1
#endif

// Forward totals and upstream gradients of one row's pixels.
typedef struct {
  vfloat gr, gg, gb, gf0, gf1, gf2, gd, ga, gD;
  vfloat G_O, T_final, A_T, mu_T, M2_T;
  vint last;
} RowTotals;

ALWAYS_INLINE RowTotals load_totals(PixelRow pr, int width, size_t npix,
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

// A blended Gaussian's record fields, read by the caller from global
// (CPU layout) or local (GPU layout) memory.
typedef struct {
  float u, v, cA, cB, cC, o, cr, cg, cb, c0, c1, c2, z, m, thr;
} BlendRec;

#define BLEND_REC_LOAD(q) \
  {(q)[REC_U], (q)[REC_V], (q)[REC_CA], (q)[REC_CB], (q)[REC_CC], (q)[REC_OPACITY], (q)[REC_RGB], \
   (q)[REC_RGB + 1], (q)[REC_RGB + 2], (q)[REC_FEAT], (q)[REC_FEAT + 1], (q)[REC_FEAT + 2], (q)[REC_Z], (q)[REC_M], \
   (q)[REC_THR]}

// A row's running sums, front to back: transmittance, the weighted colour
// prefix G_P = sum_{k<=j} w_k gc_k, and the distortion prefixes A and Q.
typedef struct {
  vfloat T, G_P, A, Q;
} BlendRun;

// One Gaussian's contribution to a row's gradients (summed over the row's
// pixels by the caller): screen mean, conic, opacity, colour, feature, depth.
typedef struct {
  vfloat u, v, ca, cb, cc, op, r, g, b, f0, f1, f2, z_depth, z_dist;
} BlendVjp;

// The vector-Jacobian product of the blend for Gaussian j at one row, the one
// copy both blend_bwd layouts call (the forward is blend_fwd's loop body, with
// blend_sigma and blend_falloff above). active: lanes with j before their last
// blended Gaussian; dx = u - pixel centres, dy = v - row centre; zj: dm/dz at
// the Gaussian's depth. Returns 0, touching nothing, when no lane blended j;
// else fills *d and advances *run. Derivation: docs/rasterizer.md, "Backward".
// With forward totals O, A_T, mu_T, M2_T,
// T_final, and prefix sums that include j:
//   dO/dalpha_j = T_j c_j - (O - P_j)/(1 - alpha_j) for every linear channel;
//   folded over channels with the upstream gradients g: gc = g . c_j,
//   G_O = g . O, G_P = sum_{k<=j} w_k gc_k.
//   alpha output: T_final/(1 - alpha_j).
//   distortion D = A M2: e_j = M2_T + A_T (m_j - mu_T)^2,
//     dD/dalpha_j = T_j e_j - (M2_T (A_T - A_j) + A_T (M2_T - Q_j))/(1 - alpha_j),
//     dD/dm_j = 2 w_j A_T (m_j - mu_T).
// alpha = min(ALPHA_MAX, o G) passes no gradient through the clamp.
ALWAYS_INLINE int blend_vjp(BlendRec q, vfloat dx, float dy, vint active, float zj, const RowTotals* t, BlendRun* run,
                     BlendVjp* d) {
  const vfloat sigma = blend_sigma(q.cA, q.cB, q.cC, dx, dy);
  // The GPU layout has no row test. The CPU layout's (row_reach) bounds
  // whole tile rows, so its work-items of fewer than TILE pixels (8 on AVX2
  // CPUs: half a row) still meet records that reach none of their pixels;
  // the test spares them the exponential and changes no bit.
#if !NO_STAGING || VW < TILE
  if (out_of_reach(sigma, q.thr)) return 0;
#endif
  const vfloat G = blend_falloff(sigma);
  const vfloat oG = q.o * G;
  const vfloat alpha = fmin(oG, ALPHA_MAX);
  const vint ok = active & (sigma >= 0.f) & (alpha >= ALPHA_MIN);
  if (!ANY(ok)) return 0;
  const vfloat T = run->T;
  const vfloat w = select((vfloat)0.f, alpha * T, ok);
  vfloat gc = 0.f;
#if GRAD_RGB
  gc = t->gr * q.cr + t->gg * q.cg + t->gb * q.cb;
#endif
#if GRAD_FEAT
  gc += t->gf0 * q.c0 + t->gf1 * q.c1 + t->gf2 * q.c2;
#endif
#if GRAD_DEPTH
  gc += t->gd * q.z;
#endif
  const vfloat G_P = run->G_P + w * gc;
  const vfloat inv = 1.f / (1.f - alpha);
  vfloat v_a = gc * T - (t->G_O - G_P) * inv;
#if GRAD_ALPHA
  v_a += t->ga * t->T_final * inv;
#endif
#if GRAD_DIST
  const vfloat dm = q.m - t->mu_T;
  const vfloat A = run->A + w;
  const vfloat Q = run->Q + w * dm * dm;
  const vfloat e = t->M2_T + t->A_T * dm * dm;
  const vfloat S = t->M2_T * (t->A_T - A) + t->A_T * (t->M2_T - Q);
  v_a += t->gD * (T * e - S * inv);
  run->A = A;
  run->Q = Q;
  d->z_dist = t->gD * 2.f * w * t->A_T * dm * zj;
#else
  d->z_dist = 0.f;
#endif
  const vfloat v_oG = select((vfloat)0.f, v_a, ok & (oG <= ALPHA_MAX));
  const vfloat v_sigma = -v_oG * oG;
  d->u = v_sigma * (q.cA * dx + q.cB * dy);
  d->v = v_sigma * (q.cB * dx + q.cC * dy);
  d->ca = 0.5f * v_sigma * dx * dx;
  d->cb = v_sigma * dx * dy;
  d->cc = 0.5f * v_sigma * dy * dy;
  d->op = v_oG * G;
  d->r = GRAD_RGB ? t->gr * w : 0.f;
  d->g = GRAD_RGB ? t->gg * w : 0.f;
  d->b = GRAD_RGB ? t->gb * w : 0.f;
  d->f0 = GRAD_FEAT ? t->gf0 * w : 0.f;
  d->f1 = GRAD_FEAT ? t->gf1 * w : 0.f;
  d->f2 = GRAD_FEAT ? t->gf2 * w : 0.f;
  d->z_depth = GRAD_DEPTH ? t->gd * w : 0.f;
  run->G_P = G_P;
  run->T = select(T, T * (1.f - alpha), ok);
  return 1;
}

#ifdef WG
// Fixed-order tree sum over a work-group of WG items (a power of two), for the
// kernels that define WG; every work-item must call it. Deterministic: the
// same additions in the same order whatever the device's scheduling.
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
#endif

// --------------------------------------------------------------- group scan
// Exclusive prefix sum over the work-group of one uint per work-item
// (Hillis-Steele in local memory); *total gets the sum of all. Every
// work-item of the group must call it. tmp: [local size].
uint group_exclusive_scan(uint v, __local uint* tmp, uint* total) {
  const uint lid = get_local_id(0), wg = get_local_size(0);
  tmp[lid] = v;
  barrier(CLK_LOCAL_MEM_FENCE);
  for (uint off = 1; off < wg; off <<= 1) {
    uint a = lid >= off ? tmp[lid - off] : 0u;
    barrier(CLK_LOCAL_MEM_FENCE);
    tmp[lid] += a;
    barrier(CLK_LOCAL_MEM_FENCE);
  }
  const uint incl = tmp[lid];
  *total = tmp[wg - 1];
  barrier(CLK_LOCAL_MEM_FENCE);  // tmp is free again
  return incl - v;
}

// Exclusive prefix sum of a[0, n) in place by one work-group: each
// work-item sums a contiguous run, the runs' sums are scanned, then each
// run is rewritten. Returns the total to every work-item. tmp: [local size].
uint group_scan_in_place(__global uint* a, uint n, __local uint* tmp) {
  const uint wg = get_local_size(0);
  const uint per = (n + wg - 1) / wg;
  const uint b = min(n, (uint)get_local_id(0) * per), e = min(n, b + per);
  uint s = 0;
  for (uint i = b; i < e; ++i) s += a[i];
  uint total;
  uint acc = group_exclusive_scan(s, tmp, &total);
  for (uint i = b; i < e; ++i) {
    const uint v = a[i];
    a[i] = acc;
    acc += v;
  }
  return total;
}

