// Growing statistics (docs/design.md section 3, train/densify/anchor_growth.h): after each
// backward pass, per child Gaussian g (row g = a * K + i, the renderer's row),
// the norm of its screen-space positional gradient where it was visible, the
// number of such iterations, and the last iteration it was visible.
// One work-item per child, each summing only its own entries in iteration
// order: no atomics, so the sums are bit-reproducible.

// scale_x, scale_y turn the renderer's pixel gradients into the units the
// threshold is given in: W/2 and H/2 for NDC (3DGS: u = ((ndc + 1) W - 1) / 2,
// so dL/dndc = dL/du * W/2), 1 for pixels. A non-finite norm adds nothing to
// the sum but the view still counts as a visibility.
__kernel void growth_accumulate(
    int n,                            // N children
    __global const float* v_means2d,  // [N,2] dL/d(u, v), pixels
    __global const int* radii,        // [N]   > 0 = visible in this view
    float scale_x, float scale_y,     // pixels -> threshold units
    int step,                         // this accumulation's number (1, 2, ...)
    __global float* grad_sum,         // [N]   sum of norms over visible views
    __global int* count,              // [N]   visible views
    __global int* last_seen) {        // [N]   step of the last visible view
  const int g = get_global_id(0);
  if (g >= n) return;
  if (radii[g] <= 0) return;
  const float2 v = vload2(g, v_means2d);
  const float gx = v.x * scale_x, gy = v.y * scale_y;
  const float norm = sqrt(gx * gx + gy * gy);
  if (isfinite(norm)) grad_sum[g] += norm;
  count[g] += 1;
  last_seen[g] = step;
}
