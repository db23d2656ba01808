// Stage 3 clustering (train/stage3/clustering.h): union-find against a BFS
// connected-components reference on random graphs, deterministic numbering,
// the size filter, the edge tests, and the archive round trip.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <random>
#include <vector>

#include "tests/reference/clustering_reference.h"
#include "train/stage3/clustering.h"

namespace ag2gs {
namespace {

struct Csr {
  std::vector<int32_t> offsets;
  std::vector<int32_t> nb;
  std::vector<float> val;
  AnchorGraphView view() const { return {offsets.size() - 1, offsets.data(), nb.data(), val.data()}; }
};

// Random symmetric graph: `edges` undirected edges with values in [0, 0.02)
// (about half below the default distance threshold 0.01), listed in both rows,
// rows shuffled. With one_sided, each edge appears only in the row of its
// smaller end.
Csr random_graph(int A, int edges, uint32_t seed, bool one_sided = false) {
  std::mt19937 rng(seed);
  std::uniform_int_distribution<int> pick(0, A - 1);
  std::uniform_real_distribution<float> val(0.f, 0.02f);
  std::vector<std::vector<std::pair<int32_t, float>>> rows(A);
  for (int e = 0; e < edges; ++e) {
    int a = pick(rng), b = pick(rng);
    // Locality: most edges stay near the diagonal, so components of all sizes appear.
    if (e % 4 != 0) b = std::clamp(a + static_cast<int>(rng() % 7) - 3, 0, A - 1);
    const float v = val(rng);
    if (one_sided) {
      rows[std::min(a, b)].push_back({std::max(a, b), v});
    } else {
      rows[a].push_back({b, v});
      rows[b].push_back({a, v});
    }
  }
  Csr g;
  g.offsets.push_back(0);
  for (auto& r : rows) {
    std::shuffle(r.begin(), r.end(), rng);
    for (auto& [b, v] : r) {
      g.nb.push_back(b);
      g.val.push_back(v);
    }
    g.offsets.push_back(static_cast<int32_t>(g.nb.size()));
  }
  return g;
}

TEST(Clustering, MatchesBfsReferenceOnRandomGraphs) {
  for (uint32_t seed = 1; seed <= 20; ++seed) {
    const int A = 50 + static_cast<int>(seed) * 37;
    const Csr g = random_graph(A, A * 2, seed, seed % 3 == 0);
    ClusterConfig cfg;
    cfg.min_cluster_size = 1 + static_cast<int>(seed % 6);
    const Clustering c = cluster_anchors(g.view(), cfg);
    const std::vector<int32_t> want = ref::clustering_reference(g.view(), cfg);
    ASSERT_EQ(c.anchor_cluster, want) << "seed " << seed;
    // Sizes agree with the ids, every kept cluster is big enough, ids are
    // numbered by first anchor.
    std::vector<int32_t> count(c.clusters(), 0);
    int32_t last_new = -1;
    for (int a = 0; a < A; ++a) {
      const int32_t id = c.anchor_cluster[a];
      if (id < 0) continue;
      if (count[id] == 0) {
        EXPECT_EQ(id, last_new + 1);
        last_new = id;
      }
      ++count[id];
    }
    EXPECT_EQ(count, c.cluster_size);
    for (int32_t s : c.cluster_size) EXPECT_GE(s, cfg.min_cluster_size);
    size_t skipped = std::count(want.begin(), want.end(), -1);
    EXPECT_EQ(c.skipped_anchors, skipped);
    EXPECT_GE(c.components, static_cast<size_t>(c.clusters()));
  }
}

TEST(Clustering, IndependentOfEdgeOrderAndRepeatable) {
  const Csr g = random_graph(800, 1600, 7);
  ClusterConfig cfg;
  const Clustering a = cluster_anchors(g.view(), cfg);
  const Clustering b = cluster_anchors(g.view(), cfg);
  EXPECT_EQ(a.anchor_cluster, b.anchor_cluster);
  // Reverse every row, and reverse the row order of the edges as listed.
  Csr r = g;
  for (size_t a2 = 0; a2 + 1 < r.offsets.size(); ++a2) {
    std::reverse(r.nb.begin() + r.offsets[a2], r.nb.begin() + r.offsets[a2 + 1]);
    std::reverse(r.val.begin() + r.offsets[a2], r.val.begin() + r.offsets[a2 + 1]);
  }
  const Clustering c = cluster_anchors(r.view(), cfg);
  EXPECT_EQ(a.anchor_cluster, c.anchor_cluster);
  EXPECT_EQ(a.cluster_size, c.cluster_size);
  EXPECT_GT(a.clusters(), 3);  // the graph is not trivially one cluster or none
}

TEST(Clustering, DistanceAndWeightTestsAgree) {
  // Features on a line: distances d_ij, weights exp(-d^2 / (2 tau^2)).
  Csr g = random_graph(400, 900, 11);
  ClusterConfig dist;
  dist.min_cluster_size = 2;
  const Clustering a = cluster_anchors(g.view(), dist);
  const double tau = 0.05;
  const double wmin = weight_threshold_for_distance(dist.max_distance, tau);
  EXPECT_NEAR(wmin, std::exp(-0.02), 1e-8);  // 0.01f is not 0.01 exactly
  Csr w = g;
  for (float& v : w.val) v = static_cast<float>(std::exp(-double(v) * v / (2 * tau * tau)));
  ClusterConfig wc = dist;
  wc.edge_value = EdgeValue::bilateral_weight;
  wc.min_weight = static_cast<float>(wmin);
  // Edge values within float rounding of the threshold could flip; the
  // reference uses the same float values, so compare against it too.
  EXPECT_EQ(cluster_anchors(w.view(), wc).anchor_cluster, ref::clustering_reference(w.view(), wc));
  size_t differ = 0;
  const Clustering b = cluster_anchors(w.view(), wc);
  for (size_t i = 0; i < a.anchor_cluster.size(); ++i) differ += a.anchor_cluster[i] != b.anchor_cluster[i];
  EXPECT_LE(differ, a.anchor_cluster.size() / 50);
}

TEST(Clustering, SizeFilterAndThresholdEdgeCases) {
  // Chain 0-1-2-3-4 (distances 0.005), pair 5-6, single 7, and 8-9 joined by an
  // edge exactly at the threshold (not joined: strict <).
  Csr g;
  std::vector<std::vector<std::pair<int32_t, float>>> rows(10);
  auto edge = [&](int a, int b, float v) {
    rows[a].push_back({b, v});
    rows[b].push_back({a, v});
  };
  for (int i = 0; i < 4; ++i) edge(i, i + 1, 0.005f);
  edge(5, 6, 0.f);
  edge(8, 9, 0.01f);
  edge(7, 7, 0.f);  // self-loop: ignored
  g.offsets.push_back(0);
  for (auto& r : rows) {
    for (auto& [b, v] : r) {
      g.nb.push_back(b);
      g.val.push_back(v);
    }
    g.offsets.push_back(static_cast<int32_t>(g.nb.size()));
  }
  ClusterConfig cfg;  // min size 5: only the chain survives
  Clustering c = cluster_anchors(g.view(), cfg);
  EXPECT_EQ(c.anchor_cluster, (std::vector<int32_t>{0, 0, 0, 0, 0, -1, -1, -1, -1, -1}));
  EXPECT_EQ(c.components, 5u);
  EXPECT_EQ(c.skipped_anchors, 5u);
  cfg.min_cluster_size = 1;
  c = cluster_anchors(g.view(), cfg);
  EXPECT_EQ(c.anchor_cluster, (std::vector<int32_t>{0, 0, 0, 0, 0, 1, 1, 2, 3, 4}));
  // Empty graph.
  AnchorGraphView empty;
  EXPECT_EQ(cluster_anchors(empty, cfg).clusters(), 0);
}

TEST(Clustering, RejectsBadGraphs) {
  Csr g = random_graph(20, 30, 3);
  ClusterConfig cfg;
  Csr bad = g;
  bad.nb[0] = 20;
  EXPECT_THROW(cluster_anchors(bad.view(), cfg), std::invalid_argument);
  bad = g;
  bad.val[1] = NAN;
  EXPECT_THROW(cluster_anchors(bad.view(), cfg), std::invalid_argument);
  bad = g;
  bad.offsets[3] = bad.offsets[2] - 1;
  EXPECT_THROW(cluster_anchors(bad.view(), cfg), std::invalid_argument);
  cfg.min_cluster_size = 0;
  EXPECT_THROW(cluster_anchors(g.view(), cfg), std::invalid_argument);
}

TEST(Clustering, EdgeFeatureDistances) {
  Csr g = random_graph(60, 100, 5);
  std::mt19937 rng(9);
  std::uniform_real_distribution<float> u(-0.1f, 0.1f);
  std::vector<float> f(60 * 3);
  for (float& x : f) x = u(rng);
  const std::vector<float> d = edge_feature_distances(g.view(), f);
  ASSERT_EQ(d.size(), g.nb.size());
  for (int a = 0; a < 60; ++a)
    for (int64_t e = g.offsets[a]; e < g.offsets[a + 1]; ++e) {
      const int b = g.nb[e];
      const double ref = std::hypot(double(f[a * 3]) - f[b * 3], double(f[a * 3 + 1]) - f[b * 3 + 1],
                                    double(f[a * 3 + 2]) - f[b * 3 + 2]);
      EXPECT_NEAR(d[e], ref, 1e-7 * std::max(1.0, ref));
    }
  EXPECT_THROW(edge_feature_distances(g.view(), std::vector<float>(59 * 3)), std::invalid_argument);
}

TEST(Clustering, ArchiveRoundTrip) {
  const Csr g = random_graph(300, 600, 21);
  ClusterConfig cfg;
  cfg.min_cluster_size = 3;
  const Clustering c = cluster_anchors(g.view(), cfg);
  ModelArchive ar;
  clustering_to_archive(ar, c, cfg);
  const Clustering r = clustering_from_archive(ar, 300);
  EXPECT_EQ(r.anchor_cluster, c.anchor_cluster);
  EXPECT_EQ(r.cluster_size, c.cluster_size);
  EXPECT_EQ(r.components, c.components);
  EXPECT_EQ(r.skipped_anchors, c.skipped_anchors);
  EXPECT_EQ(ar.meta["clusters"]["min_cluster_size"].get<int>(), 3);
  EXPECT_THROW(clustering_from_archive(ar, 299), std::runtime_error);  // anchor count differs
  ModelArchive none;
  try {
    clustering_from_archive(none, 300);
    FAIL() << "expected an error";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("--stages 3"), std::string::npos) << e.what();
  }
  // A corrupted size table is caught.
  Clustering broken = c;
  if (!broken.cluster_size.empty()) {
    broken.cluster_size[0] += 1;
    ModelArchive ar2;
    clustering_to_archive(ar2, broken, cfg);
    EXPECT_THROW(clustering_from_archive(ar2, 300), std::runtime_error);
  }
}

}  // namespace
}  // namespace ag2gs
