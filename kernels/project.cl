// Projection forward: 3D Gaussians -> screen-space records, tile rectangles
// and the depth keys that order them (docs/rasterizer.md, "Projection").
// Defines: SH_K (coefficients per channel stored), SH_ACTIVE (active degree).

__kernel void project_fwd(
    int n,
    __constant const float* cam,      // [CAM_SIZE]
    __global const float* means,      // [N,3]
    __global const float* scales,     // [N,3]
    __global const float* quats,      // [N,4]
    __global const float* opacities,  // [N]
    __global const float* sh,         // [N,SH_K,3]
    __global const float* features,   // [N,3]
    int tiles_x, int tiles_y,
    __global float* records,          // [N,REC_SIZE]
    __global int4* rects,             // [N] tile rectangle x0,y0,x1,y1 (inclusive)
    __global uint* tile_counts,       // [N] tiles touched, 0 = culled
    __global uint* depth_keys,        // [N] float bits of z, 0xffffffff when culled
    __global int* radii) {            // [N]
  int g = get_global_id(0);
  if (g >= n) return;
  tile_counts[g] = 0;
  depth_keys[g] = 0xffffffffu;
  radii[g] = 0;
  rects[g] = (int4)(0, 0, -1, -1);

  float3 mean = vload3(g, means), scale = vload3(g, scales), feat = vload3(g, features);
  float4 qraw = vload4(g, quats);
  float opacity = opacities[g];
  // Non-finite inputs are culled, never propagated.
  float check = mean.x + mean.y + mean.z + scale.x + scale.y + scale.z + qraw.x + qraw.y + qraw.z + qraw.w + opacity;
  // x * 0 is NaN exactly when x is not finite, else +-0: the SH terms only
  // decide whether check stays finite, in any order, so four at a time.
  {
    __global const float* c = sh + (size_t)g * SH_K * 3;
    float4 c4 = 0.f;
    int k = 0;
    for (; k + 4 <= SH_K * 3; k += 4) c4 += vload4(0, c + k) * 0.f;
    for (; k < SH_K * 3; ++k) check += c[k] * 0.f;
    check += (c4.x + c4.y) + (c4.z + c4.w);
  }
  check += (feat.x + feat.y + feat.z) * 0.f;
  if (!isfinite(check)) return;
  if (!(opacity >= ALPHA_MIN)) return;

  Proj pr;
  if (!ewa_project(cam, mean, scale, qraw, &pr)) return;
  float det = pr.a * pr.c - pr.b * pr.b;
  if (!(det > 0.f) || !isfinite(det)) return;
  float idet = 1.f / det;
  float cA = pr.c * idet, cB = -pr.b * idet, cC = pr.a * idet;
  float z = pr.p.z;
  float u = cam[CAM_FX] * pr.p.x / z + cam[CAM_CX];
  float v = cam[CAM_FY] * pr.p.y / z + cam[CAM_CY];
  if (!isfinite(u + v + cA + cB + cC)) return;

  // Opacity-aware extent: alpha >= 1/255 inside sigma <= k/2, k = 2 ln(255 o);
  // the ellipse's bounding box has half-widths sqrt(k a), sqrt(k c).
  float thr = log(255.f * opacity);
  float k = fmax(2.f * thr, 0.f);
  float ex = sqrt(k * pr.a) * 1.001f + 0.01f;
  float ey = sqrt(k * pr.c) * 1.001f + 0.01f;
  // Pixel i's centre is i + 0.5: tiles whose centres may lie in [u - ex, u + ex].
  float fx0 = floor((u - ex - 0.5f) / TILE), fx1 = floor((u + ex - 0.5f) / TILE);
  float fy0 = floor((v - ey - 0.5f) / TILE), fy1 = floor((v + ey - 0.5f) / TILE);
  fx0 = fmax(fx0, 0.f); fy0 = fmax(fy0, 0.f);
  fx1 = fmin(fx1, (float)(tiles_x - 1)); fy1 = fmin(fy1, (float)(tiles_y - 1));
  if (!(fx0 <= fx1 && fy0 <= fy1)) return;  // off-screen
  int4 rect = (int4)((int)fx0, (int)fy0, (int)fx1, (int)fy1);

  // Colour from SH at the view direction, + 0.5, clamped at 0 (3DGS).
  float inv_norm;
  float3 d = view_dir(mean, vload3(0, cam + CAM_POS), &inv_norm);
  float3 rgb = (float3)(0.f);
#define SH_TERM(k)                       \
  {                                      \
    float3 grad;                         \
    float b = sh_basis(k, d, &grad);     \
    rgb += b * vload3(g * SH_K + k, sh); \
  }
  SH_EACH((SH_ACTIVE + 1) * (SH_ACTIVE + 1), SH_TERM)
#undef SH_TERM
  rgb = fmax(rgb + 0.5f, 0.f);

  __global float* r = records + (size_t)g * REC_SIZE;
  r[REC_U] = u; r[REC_V] = v;
  r[REC_CA] = cA; r[REC_CB] = cB; r[REC_CC] = cC;
  r[REC_OPACITY] = opacity;
  r[REC_Z] = z;
  r[REC_M] = dist_depth(z, cam[CAM_DNEAR], cam[CAM_DFAR]);
  vstore3(rgb, 0, r + REC_RGB);
  vstore3(feat, 0, r + REC_FEAT);
  r[REC_THR] = thr;
  r[REC_CM] = cC - cB * cB / cA;
  rects[g] = rect;
  // The tiles of the box that the ellipse reaches (tile_touched).
  uint touched = 0;
  for (int ty = rect.y; ty <= rect.w; ++ty)
    for (int tx = rect.x; tx <= rect.z; ++tx) touched += tile_touched(u, v, cA, cB, cC, k, tx, ty) ? 1u : 0u;
  tile_counts[g] = touched;
  depth_keys[g] = as_uint(z);  // z > 0: float bits order like the values
  radii[g] = (int)ceil(fmax(ex, ey));
}
