// ag2gs_bench_stage3: time of stage 3 (clustering, instance maps, scoring and
// language attachment) on a trained model and its scene, and the instance-map
// kernel against the forward render per view (kernel times from profiling
// events, median over repeats).
//
// The graph here is a neighbourhood built by brute force (docs/design.md
// section 6 describes the real one): anchors whose top-layer cells are equal
// or 26-neighbours are connected.
//
//   ag2gs_bench_stage3 MODEL_DIR SCENE_DIR [--repeats N] [--max-distance D] [--out FILE]
#include <CLI/CLI.hpp>
#include <Eigen/Core>
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <map>
#include <unordered_map>
#include <vector>

#include "host/device/cl_runtime.h"
#include "host/io/model_io.h"
#include "host/render/renderer.h"
#include "host/scene/scene.h"
#include "train/anchors/anchor_model.h"
#include "train/anchors/expander.h"
#include "train/stage3/clustering.h"
#include "train/stage3/instance_map.h"
#include "train/stage3/language.h"

using namespace ag2gs;

namespace {

double median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  return v.empty() ? 0.0 : v[v.size() / 2];
}

struct Graph {
  std::vector<int32_t> offsets;
  std::vector<int32_t> nb;
};

Graph neighbourhood_graph(const AnchorModel& m) {
  const size_t A = m.size();
  std::unordered_map<uint64_t, std::vector<int32_t>> by_cell;
  std::vector<Eigen::Vector3i> top(A);
  for (size_t a = 0; a < A; ++a) {
    const Eigen::Vector3i c(m.cell()[3 * a], m.cell()[3 * a + 1], m.cell()[3 * a + 2]);
    top[a] = m.grid().parent_cell(m.layer()[a], c, 0);
    by_cell[anchor_voxel_key(0, top[a])].push_back(static_cast<int32_t>(a));
  }
  Graph g;
  g.offsets.push_back(0);
  for (size_t a = 0; a < A; ++a) {
    std::vector<int32_t> row;
    for (int dz = -1; dz <= 1; ++dz)
      for (int dy = -1; dy <= 1; ++dy)
        for (int dx = -1; dx <= 1; ++dx) {
          auto it = by_cell.find(anchor_voxel_key(0, top[a] + Eigen::Vector3i(dx, dy, dz)));
          if (it == by_cell.end()) continue;
          for (int32_t b : it->second)
            if (b != static_cast<int32_t>(a)) row.push_back(b);
        }
    std::sort(row.begin(), row.end());
    g.nb.insert(g.nb.end(), row.begin(), row.end());
    g.offsets.push_back(static_cast<int32_t>(g.nb.size()));
  }
  return g;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"stage 3 timing"};
  std::string model_dir, scene_dir;
  int repeats = 5;
  float max_distance = 0.01f;
  std::string out_path;
  app.add_option("model", model_dir, "trained model folder (model.ag2gs)")->required();
  app.add_option("scene", scene_dir, "its scene folder")->required();
  app.add_option("--repeats", repeats, "repeats of the per-view timing");
  app.add_option("--max-distance", max_distance, "clustering feature-distance threshold");
  app.add_option("--out", out_path, "write the clusters and language features to this archive (determinism checks)");
  CLI11_PARSE(app, argc, argv);

  Runtime rt(-1);
  std::printf("device: %s (%s), vector width %d\n", rt.info().name.c_str(), rt.info().platform.c_str(),
              rt.vector_width());
  const AnchorModel model = AnchorModel::from_archive(read_model_archive(model_dir + "/model.ag2gs"));
  auto scene = Scene::open(scene_dir);
  const std::vector<int> views = scene->train_views();
  std::printf("model: %zu anchors, %zu Gaussians; scene: %zu training views\n", model.size(), model.gaussians(),
              views.size());

  auto t0 = std::chrono::steady_clock::now();
  const Graph graph = neighbourhood_graph(model);
  const double graph_ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
  AnchorGraphView gv{model.size(), graph.offsets.data(), graph.nb.data(), nullptr};
  std::printf("graph (brute-force neighbourhood, not timed as stage 3): %zu directed edges in %.1f ms\n",
              graph.nb.size(), graph_ms);

  Stage3Config cfg;
  cfg.cluster.max_distance = max_distance;
  // Warm-up run (kernel builds), then the timed one.
  run_stage3(rt, model, gv, *scene, views, cfg);
  const Stage3Result r = run_stage3(rt, model, gv, *scene, views, cfg);
  const LanguageStats& s = r.stats;
  std::printf("stage 3: %d clusters (%zu components, %zu anchors skipped), %d with a language feature\n",
              r.clustering.clusters(), r.clustering.components, r.clustering.skipped_anchors,
              r.language.with_language());
  std::printf("stage 3 wall: cluster %.2f ms + attach %.1f ms (expand %.1f, render %.1f, instance %.1f, "
              "download+score %.1f) over %d views = %.1f ms total; %zu pairs, %zu matches\n",
              r.cluster_ms, s.total_ms, s.expand_ms, s.render_ms, s.instance_ms, s.score_ms, s.views,
              r.cluster_ms + s.total_ms, s.pairs, s.matches);

  if (!out_path.empty()) {
    ModelArchive ar;
    clustering_to_archive(ar, r.clustering, cfg.cluster);
    language_to_archive(ar, r.language, cfg.language);
    write_model_archive(out_path, ar);
    std::printf("wrote %s\n", out_path.c_str());
  }

  // Kernel times per view: forward render vs instance map.
  DeviceAnchors anchors(rt);
  anchors.upload(model);
  DeviceGaussians gaussians(rt);
  Expander expander(rt);
  expander.forward(anchors, gaussians, 0);
  Renderer renderer(rt);
  InstanceMapper mapper(rt);
  mapper.set_clusters(r.clustering.anchor_cluster, model.children());
  RenderSettings settings;
  settings.sh_degree = 0;
  rt.set_profiling(true);
  std::vector<double> fwd, blend, inst;
  for (int rep = 0; rep < repeats; ++rep)
    for (int v : views) {
      rt.take_timings();
      renderer.forward(gaussians, scene->views()[v].camera, settings);
      mapper.compute(renderer);
      rt.queue().finish();
      std::map<std::string, double> t = rt.take_timings();
      double f = 0;
      for (auto& [k, ms] : t)
        if (k != "instance_map") f += ms;
      fwd.push_back(f);
      blend.push_back(t["blend_fwd"]);
      inst.push_back(t["instance_map"]);
    }
  rt.set_profiling(false);
  std::printf("per view (kernel time, median of %zu): forward render %.3f ms (of which blend_fwd %.3f ms), "
              "instance map %.3f ms (%.0f%% of the forward)\n",
              fwd.size(), median(fwd), median(blend), median(inst), 100.0 * median(inst) / std::max(1e-9, median(fwd)));
  return 0;
}
