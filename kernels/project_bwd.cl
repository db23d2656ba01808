// Projection backward: per Gaussian, sum its intersection slots in order (the
// deterministic segmented reduction), then chain the screen-space gradients
// back to means, scales, quaternions, opacities, SH and features.
// Defines: SH_K, SH_ACTIVE.

__kernel void project_bwd(
    int n,
    __constant const float* cam,      // [CAM_SIZE]
    __global const float* means,      // [N,3]
    __global const float* scales,     // [N,3]
    __global const float* quats,      // [N,4]
    __global const float* sh,         // [N,SH_K,3]
    __global const float* records,    // [N,REC_SIZE] from project_fwd
    __global const uint* tile_counts, // [N]
    __global const uint* isect_start, // [N]
    __global const float* isect_grads,// [M,G2_SIZE]
    __global float* v_means,          // [N,3]
    __global float* v_scales,         // [N,3]
    __global float* v_quats,          // [N,4]
    __global float* v_opacities,      // [N]
    __global float* v_sh,             // [N,SH_K,3]
    __global float* v_features,       // [N,3]
    __global float* v_means2d) {      // [N,2]
  int g = get_global_id(0);
  if (g >= n) return;
  float v2[G2_SIZE];
  for (int c = 0; c < G2_SIZE; ++c) v2[c] = 0.f;
  uint cnt = tile_counts[g];
  if (cnt > 0) {
    __global const float* p = isect_grads + (size_t)isect_start[g] * G2_SIZE;
    for (uint i = 0; i < cnt; ++i)
      for (int c = 0; c < G2_SIZE; ++c) v2[c] += p[(size_t)i * G2_SIZE + c];
  }
  const int K_ACTIVE = (SH_ACTIVE + 1) * (SH_ACTIVE + 1);
  // Inactive SH bands get zero gradients; the active ones are written once below.
  for (int k = cnt == 0 ? 0 : K_ACTIVE; k < SH_K; ++k) vstore3((float3)(0.f), g * SH_K + k, v_sh);
  vstore2((float2)(v2[G2_U], v2[G2_V]), g, v_means2d);
  v_opacities[g] = v2[G2_OPACITY];
  vstore3((float3)(v2[G2_FEAT], v2[G2_FEAT + 1], v2[G2_FEAT + 2]), g, v_features);
  if (cnt == 0) {
    vstore3((float3)(0.f), g, v_means);
    vstore3((float3)(0.f), g, v_scales);
    vstore4((float4)(0.f), g, v_quats);
    return;
  }

  float3 mean = vload3(g, means), scale = vload3(g, scales);
  Proj pr;
  ewa_project(cam, mean, scale, vload4(g, quats), &pr);  // visible, so it succeeds
  const float fx = cam[CAM_FX], fy = cam[CAM_FY];
  const float z = pr.p.z, iz = 1.f / z, iz2 = iz * iz;
  __global const float* rec = records + (size_t)g * REC_SIZE;
  const float cA = rec[REC_CA], cB = rec[REC_CB], cC = rec[REC_CC];

  // conic K = cov^-1: v_cov = -K v_K K, v_K symmetric with the off-diagonal
  // parameter B counted once in sigma = ... + B dx dy.
  float gA = v2[G2_CA], gB = 0.5f * v2[G2_CB], gC = v2[G2_CC];
  float t00 = cA * gA + cB * gB, t01 = cA * gB + cB * gC;  // K v_K
  float t10 = cB * gA + cC * gB, t11 = cB * gB + cC * gC;
  float G00 = -(t00 * cA + t01 * cB), G01 = -(t00 * cB + t01 * cC);
  float G11 = -(t10 * cB + t11 * cC);
  float Gc[4] = {G00, G01, G01, G11};  // symmetric 2x2

  // cov2d = J Sigma_c J^T + 0.3 I: v_Sigma_c = J^T Gc J, v_J = 2 Gc J Sigma_c.
  const float* J = pr.J;
  const float* S = pr.Sigma_c.m;
  mat3 vS;
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) {
      float s = 0.f;
      for (int a = 0; a < 2; ++a)
        for (int b = 0; b < 2; ++b) s += J[3 * a + i] * Gc[2 * a + b] * J[3 * b + j];
      vS.m[3 * i + j] = s;
    }
  float vJ[6];
  for (int a = 0; a < 2; ++a)
    for (int j = 0; j < 3; ++j) {
      float s = 0.f;
      for (int b = 0; b < 2; ++b)
        for (int k = 0; k < 3; ++k) s += Gc[2 * a + b] * J[3 * b + k] * S[3 * k + j];
      vJ[3 * a + j] = 2.f * s;
    }

  // Camera-space mean p: through (u, v), depth, and the Jacobian entries
  // J00 = fx/z, J11 = fy/z, J02 = -fx x/z^2 (or -fx L/z when clamped).
  float3 vp = (float3)(0.f);
  float vu = v2[G2_U], vv = v2[G2_V];
  vp.x += vu * fx * iz;
  vp.y += vv * fy * iz;
  vp.z += -(vu * fx * pr.p.x + vv * fy * pr.p.y) * iz2 + v2[G2_Z];
  vp.z += -vJ[0] * fx * iz2 - vJ[4] * fy * iz2;
  if (pr.clamp_x) {
    vp.z += vJ[2] * fx * pr.lim_x * iz2;
  } else {
    vp.x += -vJ[2] * fx * iz2;
    vp.z += vJ[2] * 2.f * fx * pr.p.x * iz2 * iz;
  }
  if (pr.clamp_y) {
    vp.z += vJ[5] * fy * pr.lim_y * iz2;
  } else {
    vp.y += -vJ[5] * fy * iz2;
    vp.z += vJ[5] * 2.f * fy * pr.p.y * iz2 * iz;
  }
  mat3 R = mat3_load(cam + CAM_R), Rt = mat3_transpose(R);
  float3 v_mean = mat3_vec(Rt, vp);

  // Sigma_c = R Sigma R^T -> v_Sigma = R^T v_Sigma_c R; Sigma = M M^T, M = Rq diag(s)
  // -> v_M = 2 v_Sigma M; v_Rq[:,i] = s_i v_M[:,i]; v_s_i = <v_M[:,i], Rq[:,i]>.
  mat3 vSig = mat3_mul(mat3_mul(Rt, vS), R);
  float sc[3] = {scale.x, scale.y, scale.z};
  mat3 M = pr.Rq;
  for (int r = 0; r < 3; ++r)
    for (int i = 0; i < 3; ++i) M.m[3 * r + i] *= sc[i];
  mat3 vM = mat3_mul(vSig, M);
  float vs[3] = {0.f, 0.f, 0.f};
  mat3 vRq;
  for (int r = 0; r < 3; ++r)
    for (int i = 0; i < 3; ++i) {
      float vm = 2.f * vM.m[3 * r + i];
      vRq.m[3 * r + i] = vm * sc[i];
      vs[i] += vm * pr.Rq.m[3 * r + i];
    }
  float4 vq = normalize_vjp(pr.q, pr.inv_qnorm, quat_to_rotmat_vjp(pr.q, vRq));

  // Colour = max(SH(d) + 0.5, 0), d = normalize(mean - campos).
  float inv_norm;
  float3 d = view_dir(mean, vload3(0, cam + CAM_POS), &inv_norm);
  float3 raw = (float3)(0.5f);
  // Fully unrolled: the constant k folds sh_basis's switch away.
  #pragma unroll
  for (int k = 0; k < K_ACTIVE; ++k) {
    float3 gr;
    raw += sh_basis(k, d, &gr) * vload3(g * SH_K + k, sh);
  }
  float3 vrgb = (float3)(v2[G2_RGB], v2[G2_RGB + 1], v2[G2_RGB + 2]);
  vrgb = select((float3)(0.f), vrgb, raw > 0.f);
  float3 vd = (float3)(0.f);
  // Fully unrolled: the constant k folds sh_basis's switch away.
  #pragma unroll
  for (int k = 0; k < K_ACTIVE; ++k) {
    float3 gr;
    float bk = sh_basis(k, d, &gr);
    vstore3(bk * vrgb, g * SH_K + k, v_sh);
    vd += gr * dot(vrgb, vload3(g * SH_K + k, sh));
  }
  v_mean += (vd - d * dot(d, vd)) * inv_norm;

  vstore3(v_mean, g, v_means);
  vstore3((float3)(vs[0], vs[1], vs[2]), g, v_scales);
  vstore4(vq, g, v_quats);
}

// Renderer::blend_weights()'s per-Gaussian step: the sum of a Gaussian's
// intersection slots' values (each slot one tile's blending weights,
// kernels/blend_bwd.cl blend_weights), in slot order from 0, the very sum
// project_bwd makes of the slots' G2_FEAT values, without project_bwd's
// chain rule, which the weights do not need.
__kernel void weight_sums(int n,
                          __global const uint* tile_counts,  // [N]
                          __global const uint* isect_start,  // [N]
                          __global const float* isect_weights, // [M] blend_weights' sum per slot
                          __global float* sums) {              // [N]
  int g = get_global_id(0);
  if (g >= n) return;
  float s = 0.f;
  const uint cnt = tile_counts[g];
  if (cnt > 0) {
    __global const float* p = isect_weights + isect_start[g];
    for (uint i = 0; i < cnt; ++i) s += p[i];
  }
  sums[g] = s;
}
