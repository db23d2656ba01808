// Plain-loop reference of stage 3's clustering: breadth-first search.
#include "tests/reference/clustering_reference.h"

#include <queue>

namespace ag2gs::ref {

std::vector<int32_t> clustering_reference(const AnchorGraphView& g, const ClusterConfig& cfg) {
  const int A = static_cast<int>(g.anchors);
  std::vector<std::vector<int>> adj(A);
  for (int a = 0; a < A; ++a)
    for (int64_t e = g.row_offsets[a]; e < g.row_offsets[a + 1]; ++e) {
      const double v = g.edge_values[e];
      const bool pass = cfg.edge_value == EdgeValue::feature_distance ? v < cfg.max_distance : v > cfg.min_weight;
      if (pass) {
        adj[a].push_back(g.neighbours[e]);
        adj[g.neighbours[e]].push_back(a);
      }
    }
  std::vector<int32_t> comp(A, -2), out(A, -1);
  int next = 0;
  for (int s = 0; s < A; ++s) {
    if (comp[s] != -2) continue;
    std::vector<int> members{s};
    comp[s] = s;
    std::queue<int> q;
    q.push(s);
    while (!q.empty()) {
      int x = q.front();
      q.pop();
      for (int y : adj[x])
        if (comp[y] == -2) {
          comp[y] = s;
          members.push_back(y);
          q.push(y);
        }
    }
    if (static_cast<int>(members.size()) >= cfg.min_cluster_size) {
      for (int m : members) out[m] = next;
      ++next;
    }
  }
  return out;
}

}  // namespace ag2gs::ref
