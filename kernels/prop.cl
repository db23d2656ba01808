// The propagation loss of stage 2 (DESIGN.md section 4) over the anchor
// graph in CSR form (stages/anchor_graph.h), and its gradient with respect to
// the anchor features f [A,3]:
//
//   d_ij = |f_i - f_j|^2,   w_ij = exp(-d_ij / (2 tau^2))
//   L    = (1 / |E|) sum_{(i,j) in E} w_ij d_ij           (a mean over undirected edges)
//
// Gradient, per row i (each undirected edge is in rows i and j):
//   with the weights held constant (stop-gradient, the default):
//     dL/df_i = (2 / |E|) sum_{j in N(i)} w_ij (f_i - f_j)
//   with the weights differentiated too (d(w d)/dd = w (1 - d / (2 tau^2))):
//     dL/df_i = (2 / |E|) sum_{j in N(i)} w_ij (1 - d_ij / (2 tau^2)) (f_i - f_j)
//
// One work-item per anchor gathers over its own row in the row's (ascending)
// order and writes only its own gradient row: no atomics, no races, and the
// same bits whatever the scheduling. The loss of row i counts the entries
// j > i only (each edge once); rows are summed per work-group by the fixed
// tree of group_sum4 and the groups on the host in order.
//
// Defines: WG (work-group size, a power of two).

__kernel void prop_loss(int n,                          // anchors A
                        __global const int* row_offsets,  // [A+1]
                        __global const int* neighbours,   // [entries] ascending per row
                        __global const float* feature,    // [A,3]
                        __global float* grad,             // [A,3] grad += grad_scale * (|E|/2) dL/df; unused when !want_grad
                        float inv_two_tau2,               // 1 / (2 tau^2)
                        float grad_scale,                 // 2 * weight / |E|
                        int full_gradient,                // 1: differentiate the weights too
                        int want_grad,
                        __global float* partials) {       // [groups] sum of the group's row losses (unnormalised)
  __local float4 scratch[WG];
  const int i = get_global_id(0);
  float row_loss = 0.0f;
  if (i < n) {
    const float3 fi = vload3(i, feature);
    float3 g = (float3)(0.0f);
    const int end = row_offsets[i + 1];
    for (int k = row_offsets[i]; k < end; ++k) {
      const int j = neighbours[k];
      const float3 d = fi - vload3(j, feature);
      const float d2 = d.x * d.x + d.y * d.y + d.z * d.z;
      const float w = exp(-d2 * inv_two_tau2);
      if (j > i) row_loss += w * d2;
      const float c = full_gradient ? w * (1.0f - d2 * inv_two_tau2) : w;
      g += c * d;
    }
    if (want_grad) vstore3(vload3(i, grad) + grad_scale * g, i, grad);
  }
  const float4 s = group_sum4((float4)(row_loss, 0.0f, 0.0f, 0.0f), scratch);
  if (get_local_id(0) == 0) partials[get_group_id(0)] = s.x;
}
