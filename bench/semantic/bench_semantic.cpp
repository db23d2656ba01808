// Stages 2 and 3 against exact ground truth: on a model trained on
// a scene made by `ag2gs synth`, the purity and adjusted Rand index of the
// anchor clusters against the objects, and for each object whether its
// cluster's language feature is closest to the object's own category.
//
//   ag2gs_bench_semantic MODEL_DIR SCENE_DIR [-r R] [--json OUT.json]
#include <spdlog/spdlog.h>

#include <CLI/CLI.hpp>
#include <cstdio>
#include <filesystem>
#include <nlohmann/json.hpp>

#include "host/device/cl_runtime.h"
#include "host/io/atomic_file.h"
#include "host/io/model_io.h"
#include "host/io/semantic_io.h"
#include "host/scene/scene.h"
#include "queries/semantic_eval.h"
#include "train/anchors/anchor_model.h"
#include "train/stage3/clustering.h"
#include "train/stage3/language.h"

using namespace ag2gs;
namespace fs = std::filesystem;

int main(int argc, char** argv) {
  CLI::App app{"Cluster purity / ARI and category accuracy of a trained model on a synthetic scene"};
  std::string model_dir, scene_dir, json_out;
  int resolution = 1;
  app.add_option("model_dir", model_dir, "Model folder (model.ag2gs with clusters and language features)")->required();
  app.add_option("scene_dir", scene_dir, "The synthetic scene it was trained on (gt/, synth.json, vocab.json)")
      ->required();
  app.add_option("-r,--resolution", resolution, "Render the views at 1/R size (default 1)");
  app.add_option("--json", json_out, "Also write the numbers here");
  CLI11_PARSE(app, argc, argv);
  try {
    Runtime rt(-1);
    const fs::path model_path = fs::is_directory(model_dir) ? fs::path(model_dir) / "model.ag2gs" : fs::path(model_dir);
    const ModelArchive ar = read_model_archive(model_path.string());
    const AnchorModel model = AnchorModel::from_archive(ar);
    const Clustering clustering = clustering_from_archive(ar, model.size());
    const LanguageFeatures language = language_from_archive(ar, clustering.clusters());
    SceneOptions so;
    so.resolution = resolution;
    auto scene = Scene::open(scene_dir, so);
    std::vector<int> views;
    for (size_t v = 0; v < scene->views().size(); ++v) views.push_back(int(v));
    const auto truth = anchor_ground_truth(rt, model, *scene, views);
    const ClusterQuality q = cluster_quality(truth, clustering.anchor_cluster);
    const Vocabulary vocab = read_vocabulary((fs::path(scene_dir) / "vocab.json").string());
    std::vector<std::pair<std::string, std::vector<float>>> entries(vocab.phrases.begin(), vocab.phrases.end());
    const auto objects = read_synth_objects(scene_dir);
    const auto cats = object_categories(truth, clustering.anchor_cluster, objects, language.features, language.dim,
                                        entries);
    int correct = 0;
    std::printf("anchors %zu, clusters %d (%zu anchors unclustered), with language %d\n", model.size(),
                clustering.clusters(), clustering.skipped_anchors, language.with_language());
    std::printf("object anchors %zu: purity %.4f, ARI %.4f\n", q.object_anchors, q.purity, q.ari);
    std::printf("| object | category | anchors | cluster | share | predicted | cos(true) | ok |\n|---|---|---:|---:|---:|---|---:|---|\n");
    nlohmann::json jo = nlohmann::json::array();
    for (const auto& r : cats) {
      correct += r.correct;
      std::printf("| %d | %s | %d | %d | %.2f | %s | %.3f | %s |\n", r.object, r.category.c_str(), r.anchors, r.cluster,
                  r.cluster_share, r.predicted.empty() ? "-" : r.predicted.c_str(), r.cosine_true,
                  r.correct ? "yes" : "no");
      jo.push_back({{"object", r.object}, {"category", r.category}, {"anchors", r.anchors}, {"cluster", r.cluster},
                    {"cluster_share", r.cluster_share}, {"predicted", r.predicted}, {"cosine_true", r.cosine_true},
                    {"correct", r.correct}});
    }
    const double acc = objects.empty() ? 0.0 : double(correct) / objects.size();
    std::printf("right category: %d of %zu objects (%.1f%%)\n", correct, objects.size(), 100 * acc);
    if (!json_out.empty()) {
      nlohmann::json j = {{"model", model_path.string()}, {"scene", scene_dir}, {"anchors", model.size()},
                          {"clusters", clustering.clusters()}, {"with_language", language.with_language()},
                          {"object_anchors", q.object_anchors}, {"purity", q.purity}, {"ari", q.ari},
                          {"category_accuracy", acc}, {"objects", jo}};
      AtomicFile f(json_out);
      f.write(j.dump(1) + "\n");
      f.commit();
    }
  } catch (const std::exception& e) {
    std::fprintf(stderr, "ag2gs_bench_semantic: %s\n", e.what());
    return 1;
  }
  return 0;
}
