// The propagation loss of stage 2 (docs/design.md section 6) over the anchor
// graph (train/graph/anchor_graph.h), and its gradient with respect to the anchor
// features f [A,3]:
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
// Two passes, so that the exponential is evaluated once per undirected edge
// in straight-line code (it dominates the cost; on CPUs PoCL then vectorises
// it across work-items):
//   prop_edges: one work-item per undirected edge e = (i, j), i < j, stores
//     c_e (w_ij, or w_ij (1 - d_ij / (2 tau^2))) and sums w_ij d_ij per
//     work-group in the fixed tree of group_sum4 (the host sums the groups in
//     order). The edge list is padded to whole work-groups with (0, 0) edges,
//     whose d = 0 adds exactly 0.
//   prop_grad: one work-item per anchor gathers c_e (f_i - f_j) over its own
//     CSR row in the row's (ascending) order and writes only its own row.
// No atomics, no races: the same bits whatever the scheduling.
//
// Defines: WG (work-group size, a power of two).

__kernel void prop_edges(__global const int* edge_i,    // [padded edges] i < j (padding: 0)
                         __global const int* edge_j,    // [padded edges]
                         __global const float* feature,  // [A,3]
                         __global float* coef,           // [padded edges] out: c_e
                         float inv_two_tau2,             // 1 / (2 tau^2)
                         int full_gradient,              // 1: differentiate the weights too
                         __global float* partials) {     // [groups] out: sum of w d over the group's edges
  __local float4 scratch[WG];
  const int e = get_global_id(0);
  const float3 d = vload3(edge_i[e], feature) - vload3(edge_j[e], feature);
  const float d2 = d.x * d.x + d.y * d.y + d.z * d.z;
  const float w = exp(-d2 * inv_two_tau2);
  coef[e] = full_gradient ? w * (1.0f - d2 * inv_two_tau2) : w;
  const float4 s = group_sum4((float4)(w * d2, 0.0f, 0.0f, 0.0f), scratch);
  if (get_local_id(0) == 0) partials[get_group_id(0)] = s.x;
}

__kernel void prop_grad(int n,                            // anchors A
                        __global const int* row_offsets,  // [A+1]
                        __global const int* neighbours,   // [entries] ascending per row
                        __global const int* entry_edge,   // [entries] undirected edge id of each entry
                        __global const float* feature,    // [A,3]
                        __global const float* coef,       // [padded edges] from prop_edges
                        float grad_scale,                 // 2 * weight / |E|
                        __global float* grad) {           // [A,3] grad += grad_scale * sum_j c (f_i - f_j)
  const int i = get_global_id(0);
  if (i >= n) return;
  const float3 fi = vload3(i, feature);
  float3 g = (float3)(0.0f);
  const int end = row_offsets[i + 1];
  for (int k = row_offsets[i]; k < end; ++k) g += coef[entry_edge[k]] * (fi - vload3(neighbours[k], feature));
  vstore3(vload3(i, grad) + grad_scale * g, i, grad);
}
