// The free-Gaussian baseline (train/baseline/free_trainer.h): the stored parameters
// of 3DGS -> the activated Gaussians the renderer draws, the backward of that
// map, and the densification statistics. One work-item per Gaussian, no
// atomics: every result is bit-reproducible.
// The SH are stored split, DC [N,3] and rest [N,15,3], so that the optimiser
// can give the two their own learning rates (as kernels/expander.cl does).


// scale = exp(log_scale), opacity = sigmoid(opacity_logit), mean and quat as
// stored, sh = (dc, rest[0 .. sh_out-2]), feature = 0 (no semantic feature).
__kernel void free_activate(
    int n,                                  // N Gaussians
    __global const float* mean,             // [N,3]
    __global const float* log_scale,        // [N,3]
    __global const float* quat,             // [N,4] w x y z
    __global const float* opacity_logit,    // [N]
    __global const float* sh_dc,            // [N,3]
    __global const float* sh_rest,          // [N,15,3]
    int sh_out,                             // coefficients per channel written, (d+1)^2
    __global float* means,                  // [N,3]
    __global float* scales,                 // [N,3]
    __global float* quats,                  // [N,4]
    __global float* opacities,              // [N]
    __global float* sh,                     // [N,sh_out,3]
    __global float* features) {             // [N,3]
  const int g = get_global_id(0);
  if (g >= n) return;
  vstore3(vload3(g, mean), g, means);
  vstore3(exp(vload3(g, log_scale)), g, scales);
  store_quat_opacity_sh(g, quat, opacity_logit, sh_dc, sh_rest, sh_out, quats, opacities, sh);
  vstore3((float3)(0.f), g, features);
}

// v_log_scale = v_scale * exp(log_scale) (d exp(x)/dx = exp(x)),
// v_opacity_logit = v_opacity o (1 - o), SH gradients split into DC and rest
// for the sh_in coefficients the renderer had, zero above. The mean and quat
// gradients are the renderer's own buffers (identity maps).
__kernel void free_activate_bwd(
    int n,                                  // N
    __global const float* log_scale,        // [N,3]
    __global const float* opacity_logit,    // [N]
    __global const float* v_scales,         // [N,3]
    __global const float* v_opacities,      // [N]
    __global const float* v_sh,             // [N,sh_in,3]
    int sh_in,                              // coefficients per channel of v_sh
    __global float* v_log_scale,            // [N,3]
    __global float* v_opacity_logit,        // [N]
    __global float* v_sh_dc,                // [N,3]
    __global float* v_sh_rest) {            // [N,15,3]
  const int g = get_global_id(0);
  if (g >= n) return;
  vstore3(vload3(g, v_scales) * exp(vload3(g, log_scale)), g, v_log_scale);
  v_opacity_logit[g] = sigmoid_vjp(opacity_logit[g], v_opacities[g]);
  vstore3(vload3((size_t)g * sh_in, v_sh), g, v_sh_dc);
  for (int k = 1; k <= SH_REST; ++k) {
    const float3 v = k < sh_in ? vload3((size_t)g * sh_in + k, v_sh) : (float3)(0.f);
    vstore3(v, (size_t)g * SH_REST + k - 1, v_sh_rest);
  }
}

// Densification statistics of one view (3DGS's add_densification_stats and
// max_radii2D): where Gaussian g is visible (radii > 0), the norm of its
// screen-space positional gradient in the threshold's units (scale_x = W/2,
// scale_y = H/2: NDC, in which 3DGS's 2e-4 is given) is added to grad_sum,
// count goes up by one and max_radius keeps the largest radius. A non-finite
// norm adds nothing but the view still counts.
__kernel void free_densify_accumulate(
    int n,                            // N
    __global const float* v_means2d,  // [N,2] dL/d(u, v), pixels
    __global const int* radii,        // [N]   > 0 = visible in this view
    float scale_x, float scale_y,     // pixels -> threshold units
    __global float* grad_sum,         // [N]
    __global int* count,              // [N]
    __global int* max_radius) {       // [N]   pixels
  const int g = get_global_id(0);
  if (g >= n) return;
  const int r = radii[g];
  if (r <= 0) return;
  const float2 v = vload2(g, v_means2d);
  const float gx = v.x * scale_x, gy = v.y * scale_y;
  const float norm = sqrt(gx * gx + gy * gy);
  if (isfinite(norm)) grad_sum[g] += norm;
  count[g] += 1;
  max_radius[g] = max(max_radius[g], r);
}
