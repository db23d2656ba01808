// Small kernels of the stage-1 training loop (stages/trainer.cpp).

// Offset regulariser L_in = mean over the N offsets of exp(relu(|o|^2 - 1))
// (DESIGN.md section 3; offsets in voxel units). Per offset row g: writes its
// term to value[g] (the host sums them in double when it logs) and adds
// weight / N * d term / d o to grad[g]. One work-item per row, no atomics.
__kernel void offset_reg(int n, float scale,           // scale = weight / N
                         __global const float* offset,  // [N,3]
                         __global float* grad,          // [N,3] dL/d offset, added to
                         __global float* value) {       // [N] exp(relu(|o|^2 - 1))
  const int g = get_global_id(0);
  if (g >= n) return;
  const float3 o = vload3(g, offset);
  const float r = dot(o, o) - 1.f;
  if (r > 0.f) {
    const float e = exp(r);
    value[g] = e;
    vstore3(vload3(g, grad) + (scale * e * 2.f) * o, g, grad);
  } else {
    value[g] = 1.f;
  }
}
