#include "train/stage3/clustering.h"

#include <cmath>
#include <numeric>
#include <stdexcept>
#include <string>

#include "host/io/json_input.h"

namespace ag2gs {

namespace {

[[noreturn]] void fail_archive(const ModelArchive& archive, const std::string& what) {
  throw std::runtime_error("model " + (archive.source.empty() ? std::string("(in memory)") : archive.source) + ": " +
                           what);
}

// Disjoint sets with union by size and path halving.
class DisjointSets {
 public:
  explicit DisjointSets(size_t n) : parent_(n), size_(n, 1) { std::iota(parent_.begin(), parent_.end(), 0); }
  int32_t find(int32_t x) {
    while (parent_[x] != x) {
      parent_[x] = parent_[parent_[x]];
      x = parent_[x];
    }
    return x;
  }
  void unite(int32_t a, int32_t b) {
    a = find(a);
    b = find(b);
    if (a == b) return;
    if (size_[a] < size_[b]) std::swap(a, b);
    parent_[b] = a;
    size_[a] += size_[b];
  }
  int32_t size_of_root(int32_t root) const { return size_[root]; }

 private:
  std::vector<int32_t> parent_, size_;
};

}  // namespace

// Offsets and neighbour ids only (edge values are not needed by every caller).
static void check_structure(const AnchorGraphView& g) {
  if (g.anchors == 0) return;
  if (g.anchors > static_cast<size_t>(INT32_MAX)) throw std::invalid_argument("anchor graph: more than 2^31-1 anchors");
  if (!g.row_offsets) throw std::invalid_argument("anchor graph: row_offsets is null");
  if (g.row_offsets[0] != 0) throw std::invalid_argument("anchor graph: row_offsets[0] must be 0");
  for (size_t a = 0; a < g.anchors; ++a)
    if (g.row_offsets[a + 1] < g.row_offsets[a])
      throw std::invalid_argument("anchor graph: row_offsets decrease at row " + std::to_string(a));
  const size_t E = g.edges();
  if (E > 0 && !g.neighbours) throw std::invalid_argument("anchor graph: neighbours is null but the graph has edges");
  for (size_t e = 0; e < E; ++e)
    if (g.neighbours[e] < 0 || static_cast<size_t>(g.neighbours[e]) >= g.anchors)
      throw std::invalid_argument("anchor graph: neighbour " + std::to_string(g.neighbours[e]) + " of edge " +
                                  std::to_string(e) + " is outside [0, " + std::to_string(g.anchors) + ")");
}

void AnchorGraphView::validate() const {
  check_structure(*this);
  const size_t E = edges();
  if (E > 0 && !edge_values) throw std::invalid_argument("anchor graph: edge_values is null but the graph has edges");
  for (size_t e = 0; e < E; ++e)
    if (!std::isfinite(edge_values[e]))
      throw std::invalid_argument("anchor graph: edge " + std::to_string(e) + " has a non-finite value");
}

void ClusterConfig::validate() const {
  if (!(max_distance >= 0.f) || !std::isfinite(max_distance))
    throw std::invalid_argument("clustering: max_distance must be finite and >= 0");
  if (!(min_weight >= 0.f && min_weight <= 1.f))
    throw std::invalid_argument("clustering: min_weight must lie in [0, 1]");
  if (min_cluster_size < 1) throw std::invalid_argument("clustering: min_cluster_size must be >= 1");
}

double weight_threshold_for_distance(double max_distance, double tau) {
  return std::exp(-max_distance * max_distance / (2.0 * tau * tau));
}

Clustering cluster_anchors(const AnchorGraphView& graph, const ClusterConfig& config) {
  graph.validate();
  config.validate();
  const size_t A = graph.anchors;
  DisjointSets sets(A);
  for (size_t a = 0; a < A; ++a)
    for (int64_t e = graph.row_offsets[a]; e < graph.row_offsets[a + 1]; ++e)
      if (config.joins(graph.edge_values[e])) sets.unite(static_cast<int32_t>(a), graph.neighbours[e]);

  // Number the components in order of their smallest anchor id: the first
  // anchor met of a component (scanning ids upwards) is its smallest.
  Clustering out;
  out.anchor_cluster.assign(A, -1);
  std::vector<int32_t> id_of_root(A, -2);  // -2 = component not met yet
  for (size_t a = 0; a < A; ++a) {
    const int32_t r = sets.find(static_cast<int32_t>(a));
    if (id_of_root[r] == -2) {
      ++out.components;
      const int32_t size = sets.size_of_root(r);
      if (size >= config.min_cluster_size) {
        id_of_root[r] = out.clusters();
        out.cluster_size.push_back(size);
      } else {
        id_of_root[r] = -1;
      }
    }
    out.anchor_cluster[a] = id_of_root[r];
    if (id_of_root[r] < 0) ++out.skipped_anchors;
  }
  return out;
}

std::vector<float> edge_feature_distances(const AnchorGraphView& graph, const std::vector<float>& features) {
  check_structure(graph);
  if (features.size() != graph.anchors * 3)
    throw std::invalid_argument("edge_feature_distances: features hold " + std::to_string(features.size()) +
                                " values, expected [A,3] = " + std::to_string(graph.anchors * 3));
  const size_t E = graph.edges();
  std::vector<float> d(E);
  for (size_t a = 0; a < graph.anchors; ++a)
    for (int64_t e = graph.row_offsets[a]; e < graph.row_offsets[a + 1]; ++e) {
      const size_t b = static_cast<size_t>(graph.neighbours[e]);
      double s = 0;
      for (int c = 0; c < 3; ++c) {
        const double x = static_cast<double>(features[a * 3 + c]) - features[b * 3 + c];
        s += x * x;
      }
      d[e] = static_cast<float>(std::sqrt(s));
    }
  return d;
}

void clustering_to_archive(ModelArchive& archive, const Clustering& clustering, const ClusterConfig& config) {
  const int64_t A = static_cast<int64_t>(clustering.anchor_cluster.size());
  archive.put("clusters/anchor_cluster", clustering.anchor_cluster, {A});
  archive.put("clusters/size", clustering.cluster_size, {static_cast<int64_t>(clustering.cluster_size.size())});
  archive.meta["clusters"] = {
      {"format", 1},
      {"count", clustering.clusters()},
      {"components", clustering.components},
      {"skipped_anchors", clustering.skipped_anchors},
      {"edge_value", config.edge_value == EdgeValue::feature_distance ? "feature_distance" : "bilateral_weight"},
      {"max_distance", config.max_distance},
      {"min_weight", config.min_weight},
      {"min_cluster_size", config.min_cluster_size}};
}

Clustering clustering_from_archive(const ModelArchive& archive, size_t anchors) {
  if (!archive.has("clusters/anchor_cluster") || !archive.meta.contains("clusters"))
    fail_archive(archive, "has no clusters; run stage 3 (ag2gs train --stages 3) on it first");
  Clustering out;
  out.anchor_cluster = archive.get<int32_t>("clusters/anchor_cluster", {static_cast<int64_t>(anchors)});
  out.cluster_size = archive.get<int32_t>("clusters/size", {-1});
  try {
    out.components = archive.meta.at("clusters").at("components").get<size_t>();
  } catch (const nlohmann::json::exception& e) {
    fail_archive(archive, std::string("meta 'clusters' is incomplete or mistyped: ") + json_error_text(e));
  }
  const int32_t C = out.clusters();
  std::vector<int32_t> count(C, 0);
  for (size_t a = 0; a < anchors; ++a) {
    const int32_t c = out.anchor_cluster[a];
    if (c < -1 || c >= C)
      fail_archive(archive, "clusters/anchor_cluster[" + std::to_string(a) + "] = " + std::to_string(c) +
                                " is outside [-1, " + std::to_string(C) + ")");
    if (c < 0)
      ++out.skipped_anchors;
    else
      ++count[c];
  }
  if (count != out.cluster_size)
    fail_archive(archive, "clusters/size disagrees with the anchors counted in clusters/anchor_cluster");
  return out;
}

}  // namespace ag2gs
