// The anchor trainer's two small per-row kernels (host: train/anchors/anchor_regularisers.h).

// Offset regulariser L_in = mean over the N offsets of exp(relu(|o|^2 - 1))
// (docs/design.md section 4; offsets in voxel units). Per offset row g: writes its
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

// Keeps the semantic features inside the unit ball after their Adam step:
// f <- f / max(1, |f|). The contrast loss L_ic = 1 / (d + 1) never stops
// pushing mask means apart; unbounded, the features drift to a scale of
// several units where the absolute thresholds of the graph stages (tau 0.05,
// the growing and clustering distances) no longer mean anything. One
// work-item per anchor.
__kernel void feature_ball(int n,
                           __global float* feature) {  // [A,3] anchor features, projected in place
  const int a = get_global_id(0);
  if (a >= n) return;
  const float3 f = vload3(a, feature);
  const float len = length(f);
  if (len > 1.f) vstore3(f / len, a, feature);
}
