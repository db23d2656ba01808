#include "train/stage3/stage3.h"

#include <spdlog/spdlog.h>

#include <chrono>
#include <cmath>
#include <filesystem>
#include <stdexcept>

#include "host/io/model_io.h"
#include "train/anchors/anchor_model.h"
#include "train/graph/anchor_graph.h"
#include "train/model_check.h"
#include "train/stage3/clustering.h"

namespace fs = std::filesystem;

namespace ag2gs {

Stage3Summary run_stage3_on_model(Runtime& rt, Scene& scene, const std::string& model_dir,
                                  const std::vector<int>& views, const Stage3Config& config) {
  const auto t0 = std::chrono::steady_clock::now();
  const std::string path = (fs::path(model_dir) / "model.ag2gs").string();
  if (!fs::exists(path))
    throw std::runtime_error("no model " + path + " for stage 3; train stage 1 (and 2) into " + model_dir + " first");
  ModelArchive archive = read_model_archive(path);
  const AnchorModel model = check_model_archive(archive);
  AnchorGraph graph;
  if (AnchorGraph::in_archive(archive)) graph = AnchorGraph::from_archive(archive);
  if (!AnchorGraph::in_archive(archive) || !graph.matches(model)) {
    spdlog::info("stage 3: {} has no current anchor graph (no stage 2?); building it", path);
    graph = AnchorGraph::build(model);
    graph.to_archive(archive);
  }
  const AnchorGraphView gv{graph.anchors(), graph.row_offsets().data(), graph.neighbours().data(), nullptr};
  Stage3Summary sum;
  sum.anchors = model.size();
  Clustering clustering;
  if (scene.semantics() == SemanticsKind::language_features) {
    Stage3Result r = run_stage3(rt, model, gv, scene, views, config);
    clustering = std::move(r.clustering);
    sum.language = true;
    sum.with_language = r.language.with_language();
    sum.stats = r.stats;
    sum.cluster_ms = r.cluster_ms;
    language_to_archive(archive, r.language, config.language);
  } else {
    const auto tc = std::chrono::steady_clock::now();
    std::vector<float> values = edge_feature_distances(gv, model.feature());
    if (config.cluster.edge_value == EdgeValue::bilateral_weight)
      for (float& v : values) v = static_cast<float>(std::exp(-double(v) * v / (2.0 * config.tau * config.tau)));
    AnchorGraphView g = gv;
    g.edge_values = values.data();
    clustering = cluster_anchors(g, config.cluster);
    sum.cluster_ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - tc).count();
    // A language entry from an earlier run would describe other clusters.
    ModelArchive kept;
    kept.source = archive.source;
    kept.meta = archive.meta;
    kept.meta.erase("language");
    for (const auto& [name, t] : archive.arrays())
      if (name.rfind("clusters/language", 0) != 0) kept.put_tensor(name, t);
    archive = std::move(kept);
    spdlog::info(
        "stage 3: scene {} has no CLIP features (language_features/<stem>_f.npy): clusters only, no "
        "language features attached",
        scene.dir());
  }
  sum.clusters = clustering.clusters();
  sum.components = clustering.components;
  sum.skipped_anchors = clustering.skipped_anchors;
  clustering_to_archive(archive, clustering, config.cluster);
  write_model_archive(path, archive);
  sum.total_ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
  return sum;
}

}  // namespace ag2gs
