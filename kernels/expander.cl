// Anchor -> Gaussian expansion (docs/design.md section 2) and its backward pass.
// Gaussian g = a * CHILDREN + i is child i of anchor a.
// Defines: CHILDREN (K), SCALE_CAP (M, default 1: a child's scale is at most
// M voxel edges; AnchorConfig::scale_cap). The cap holds for anchors whose
// voxel edge l is at least the argument cap_edge (the capped coarse layers,
// AnchorConfig::scale_cap_layers); finer anchors keep M = 1. The SH
// coefficient counts are arguments, so one program serves every degree.
// The SH of a child are stored split, DC [N,3] and rest [N,15,3], so the
// optimiser can step them with different learning rates.

#ifndef SCALE_CAP
#define SCALE_CAP 1.0f
#endif

// M for voxel edge l: SCALE_CAP on the capped layers, 1 below them.
inline float cap_of(float l, float cap_edge) { return l >= cap_edge ? SCALE_CAP : 1.f; }

// mean = pos + offset * l, scale = sigmoid(scale_logit) * M * l, quat as stored,
// opacity = sigmoid(opacity_logit), sh = (dc, rest[0 .. sh_out-2]),
// feature = the anchor's feature.
__kernel void expand_fwd(
    int n,                                  // N = A * CHILDREN Gaussians
    __global const float* pos,              // [A,3] voxel centres
    __global const float* voxel,            // [A]   voxel edge l
    __global const float* feature,          // [A,3]
    __global const float* offset,           // [N,3] voxel units
    __global const float* scale_logit,      // [N,3]
    __global const float* quat,             // [N,4] w x y z
    __global const float* opacity_logit,    // [N]
    __global const float* sh_dc,            // [N,3]
    __global const float* sh_rest,          // [N,15,3]
    int sh_out,                             // coefficients per channel written, (d+1)^2
    float cap_edge,                         // anchors with l >= cap_edge have M = SCALE_CAP
    __global float* means,                  // [N,3]
    __global float* scales,                 // [N,3]
    __global float* quats,                  // [N,4]
    __global float* opacities,              // [N]
    __global float* sh,                     // [N,sh_out,3]
    __global float* features) {             // [N,3]
  const int g = get_global_id(0);
  if (g >= n) return;
  const int a = g / CHILDREN;
  const float l = voxel[a];
  vstore3(vload3(a, pos) + vload3(g, offset) * l, g, means);
  const float3 sl = vload3(g, scale_logit);
  vstore3((float3)(sigmoid(sl.x), sigmoid(sl.y), sigmoid(sl.z)) * (l * cap_of(l, cap_edge)), g, scales);
  store_quat_opacity_sh(g, quat, opacity_logit, sh_dc, sh_rest, sh_out, quats, opacities, sh);
  vstore3(vload3(a, feature), g, features);
}

// Per Gaussian: v_offset = v_mean l, v_scale_logit = v_scale M l s (1 - s),
// v_quat = v_quat, v_opacity_logit = v_opacity o (1 - o), SH gradients copied
// for the sh_in coefficients the renderer had, zero above.
__kernel void expand_bwd(
    int n,                                  // N = A * CHILDREN
    __global const float* voxel,            // [A]
    __global const float* scale_logit,      // [N,3]
    __global const float* opacity_logit,    // [N]
    __global const float* v_means,          // [N,3]
    __global const float* v_scales,         // [N,3]
    __global const float* v_quats,          // [N,4]
    __global const float* v_opacities,      // [N]
    __global const float* v_sh,             // [N,sh_in,3]
    int sh_in,                              // coefficients per channel of v_sh
    float cap_edge,                         // as in expand_fwd
    __global float* v_offset,               // [N,3]
    __global float* v_scale_logit,          // [N,3]
    __global float* v_quat,                 // [N,4]
    __global float* v_opacity_logit,        // [N]
    __global float* v_sh_dc,                // [N,3]
    __global float* v_sh_rest) {            // [N,15,3]
  const int g = get_global_id(0);
  if (g >= n) return;
  const float l = voxel[g / CHILDREN];
  vstore3(vload3(g, v_means) * l, g, v_offset);
  const float3 sl = vload3(g, scale_logit), vs = vload3(g, v_scales) * (l * cap_of(l, cap_edge));
  vstore3((float3)(sigmoid_vjp(sl.x, vs.x), sigmoid_vjp(sl.y, vs.y), sigmoid_vjp(sl.z, vs.z)), g, v_scale_logit);
  vstore4(vload4(g, v_quats), g, v_quat);
  v_opacity_logit[g] = sigmoid_vjp(opacity_logit[g], v_opacities[g]);
  vstore3(vload3((size_t)g * sh_in, v_sh), g, v_sh_dc);
  for (int k = 1; k <= SH_REST; ++k) {
    const float3 v = k < sh_in ? vload3((size_t)g * sh_in + k, v_sh) : (float3)(0.f);
    vstore3(v, (size_t)g * SH_REST + k - 1, v_sh_rest);
  }
}

// v_feature(a) = sum over the anchor's children in child order: a fixed-order
// loop per anchor (deterministic, no atomics).
__kernel void expand_bwd_feature(
    int n_anchors,                          // A
    __global const float* v_features,       // [A*CHILDREN,3]
    __global float* v_feature) {            // [A,3]
  const int a = get_global_id(0);
  if (a >= n_anchors) return;
  float3 s = vload3((size_t)a * CHILDREN, v_features);
  for (int i = 1; i < CHILDREN; ++i) s += vload3((size_t)a * CHILDREN + i, v_features);
  vstore3(s, a, v_feature);
}
