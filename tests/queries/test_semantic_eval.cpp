// Scoring of clusters against ground truth (queries/semantic_eval): the
// adjusted Rand index against hand-computed values, purity, the per-object
// category check, and anchor ground truth on the synthetic sample against the
// objects' boxes from synth.json.
#include <gtest/gtest.h>

#include <cmath>
#include <filesystem>
#include <nlohmann/json.hpp>

#include "host/scene/scene.h"
#include "queries/semantic_eval.h"
#include "tests/io_test_util.h"
#include "tests/test_util.h"

namespace ag2gs {
namespace {
using namespace ag2gs::test;

TEST(SemanticEval, AdjustedRandIndexKnownValues) {
  // Identical partitions (up to renaming) score 1.
  EXPECT_DOUBLE_EQ(adjusted_rand_index({0, 0, 1, 1, 2}, {7, 7, 3, 3, -1}), 1.0);
  // {0,0,1,1} vs {0,0,1,2}: index 1, sum_a 2, sum_b 1, pairs 6:
  // expected 2/6, max 1.5 -> (1 - 1/3) / (1.5 - 1/3) = 4/7.
  EXPECT_NEAR(adjusted_rand_index({0, 0, 1, 1}, {0, 0, 1, 2}), 4.0 / 7.0, 1e-12);
  // {0,0,0,1,1,1} vs {0,0,1,1,2,2}: index 2, sum_a 6, sum_b 3, pairs 15:
  // expected 18/15 = 1.2, max 4.5 -> 0.8 / 3.3.
  EXPECT_NEAR(adjusted_rand_index({0, 0, 0, 1, 1, 1}, {0, 0, 1, 1, 2, 2}), 0.8 / 3.3, 1e-12);
  // Symmetric in its arguments.
  EXPECT_NEAR(adjusted_rand_index({0, 0, 1, 2}, {0, 0, 1, 1}), 4.0 / 7.0, 1e-12);
  // Every item merged into one cluster against a real split: 0.
  EXPECT_NEAR(adjusted_rand_index({0, 0, 1, 1}, {5, 5, 5, 5}), 0.0, 1e-12);
  EXPECT_THROW(adjusted_rand_index({0, 1}, {0}), std::invalid_argument);
}

TEST(SemanticEval, PurityAndAriOverObjectAnchors) {
  // truth: 6 anchors of object 1, 4 of object 2, 2 background, 1 unknown.
  const std::vector<int32_t> truth = {1, 1, 1, 1, 1, 1, 2, 2, 2, 2, 0, 0, -1};
  // Cluster 0 holds five of object 1 and one of object 2; cluster 1 three of
  // object 2 and both background anchors; one anchor of object 1 unclustered.
  const std::vector<int32_t> clusters = {0, 0, 0, 0, 0, -1, 0, 1, 1, 1, 1, 1, 0};
  const ClusterQuality q = cluster_quality(truth, clusters);
  EXPECT_EQ(q.object_anchors, 10u);
  EXPECT_EQ(q.clustered_anchors, 11u);  // the unknown and the unclustered anchor are out
  EXPECT_NEAR(q.purity, (5.0 + 3.0) / 11.0, 1e-12);
  // ARI over the 10 object anchors; the unclustered one is a singleton.
  EXPECT_NEAR(q.ari, adjusted_rand_index({1, 1, 1, 1, 1, 1, 2, 2, 2, 2}, {0, 0, 0, 0, 0, -5, 0, 1, 1, 1}), 1e-12);
  EXPECT_LT(q.ari, 0.7);
  const ClusterQuality perfect = cluster_quality({1, 1, 2, 2, 0}, {4, 4, 9, 9, 3});
  EXPECT_DOUBLE_EQ(perfect.purity, 1.0);
  EXPECT_DOUBLE_EQ(perfect.ari, 1.0);
}

TEST(SemanticEval, ObjectCategories) {
  const int dim = 4;
  const std::vector<std::pair<std::string, std::vector<float>>> vocab = {
      {"red mug", {1, 0, 0, 0}}, {"blue box", {0, 1, 0, 0}}, {"green ball", {0, 0, 1, 0}}};
  const std::vector<std::pair<int, std::string>> objects = {{1, "red mug"}, {2, "blue box"}, {3, "green ball"}};
  // Object 1 -> cluster 0 (red-ish feature), object 2 -> cluster 1 (closer to
  // the ball than the box: wrong), object 3 -> no clustered anchor.
  const std::vector<int32_t> truth = {1, 1, 1, 2, 2, 3};
  const std::vector<int32_t> clusters = {0, 0, 1, 1, 1, -1};
  const std::vector<float> language = {0.9f, 0.1f, 0.f,  0.f,   // cluster 0
                                       0.f,  0.4f, 0.6f, 0.f};  // cluster 1
  const auto r = object_categories(truth, clusters, objects, language, dim, vocab);
  ASSERT_EQ(r.size(), 3u);
  EXPECT_EQ(r[0].cluster, 0);
  EXPECT_NEAR(r[0].cluster_share, 2.0 / 3.0, 1e-12);
  EXPECT_EQ(r[0].predicted, "red mug");
  EXPECT_TRUE(r[0].correct);
  EXPECT_NEAR(r[0].cosine_true, 0.9 / std::sqrt(0.82), 1e-6);
  EXPECT_EQ(r[1].predicted, "green ball");
  EXPECT_FALSE(r[1].correct);
  EXPECT_EQ(r[2].cluster, -1);
  EXPECT_FALSE(r[2].correct);
  // A cluster without a language feature (zero row) predicts nothing.
  const auto z = object_categories({1}, {0}, {{1, "red mug"}}, std::vector<float>(dim, 0.f), dim, vocab);
  EXPECT_TRUE(z[0].predicted.empty());
  EXPECT_FALSE(z[0].correct);
}

// Anchors made opaque blobs at their voxel centres on the synthetic sample:
// the anchors the views label as object k lie in (or at one voxel from)
// object k's box, and most anchors well inside a box get its id.
TEST(SemanticEval, AnchorGroundTruthOnTheSyntheticSample) {
  const std::string dir = source_path("data_samples/synth_small");
  auto scene = Scene::open(dir);
  AnchorConfig config;
  config.top_cells = 50;
  config.init_layer = 0;
  const VoxelGrid grid = VoxelGrid::from_bounds(scene->bounds(), config);
  AnchorModel model;
  model.initialise_from_points(scene->points(), scene->colors(), grid, config, 1);
  const int K = config.children;
  for (size_t g = 0; g < model.size() * K; ++g) {
    for (int c = 0; c < 3; ++c) model.offset()[3 * g + c] = 0.f, model.scale_logit()[3 * g + c] = 0.4f;
    model.opacity_logit()[g] = 6.f;
  }
  std::vector<int> views;
  for (size_t v = 0; v < scene->views().size(); ++v) views.push_back(int(v));
  const std::vector<int32_t> truth = anchor_ground_truth(runtime(), model, *scene, views);
  ASSERT_EQ(truth.size(), model.size());

  nlohmann::json synth = nlohmann::json::parse(read_bytes(dir + "/synth.json"));
  const double l = grid.voxel(0);
  auto inside = [&](const nlohmann::json& o, const Eigen::Vector3d& p, double margin) {
    const Eigen::Vector3d c(o["centre"][0], o["centre"][1], o["centre"][2]);
    const double yaw = o["yaw"];
    const Eigen::Vector3d d = p - c;
    const double x = std::cos(yaw) * d.x() + std::sin(yaw) * d.y(), y = -std::sin(yaw) * d.x() + std::cos(yaw) * d.y();
    return std::abs(x) <= 0.5 * double(o["size"][0]) + margin && std::abs(y) <= 0.5 * double(o["size"][1]) + margin &&
           std::abs(d.z()) <= 0.5 * double(o["size"][2]) + margin;
  };
  int labelled = 0, labelled_in_box = 0, deep = 0, deep_right = 0, known = 0;
  for (size_t a = 0; a < model.size(); ++a) {
    const Eigen::Vector3d p(model.pos()[3 * a], model.pos()[3 * a + 1], model.pos()[3 * a + 2]);
    known += truth[a] >= 0;
    for (const auto& o : synth["objects"]) {
      const int id = o["id"];
      if (truth[a] == id) {
        ++labelled;
        labelled_in_box += inside(o, p, 1.0 * l);
      }
      if (truth[a] >= 0 && inside(o, p, 0.0)) {  // centre inside the object's box
        ++deep;
        deep_right += truth[a] == id;
      }
    }
  }
  std::printf("anchors %zu known %d labelled %d (in box %d) inside a box %d (right %d)\n", model.size(), known,
              labelled, labelled_in_box, deep, deep_right);
  EXPECT_GT(known, int(model.size()) / 2);
  ASSERT_GT(labelled, 20);
  EXPECT_GE(labelled_in_box, 0.9 * labelled) << labelled_in_box << " of " << labelled;
  ASSERT_GT(deep, 5);
  EXPECT_GE(deep_right, 0.8 * deep) << deep_right << " of " << deep;
}

TEST(SemanticEval, Errors) {
  ScratchDir dir("semantic_eval");
  expect_error_with<std::runtime_error>([&] { read_synth_objects(dir.path().string()); },
                                        {"synth.json", "ag2gs synth"});
  write_bytes(dir.file("synth.json"), "{\"objects\": [{\"id\": 1}]}");
  expect_error_with<std::runtime_error>([&] { read_synth_objects(dir.path().string()); }, {"synth.json", "category"});
  // The synthetic sample without its gt/ folder.
  const auto copy = dir.path() / "scene";
  std::filesystem::copy(source_path("data_samples/synth_small"), copy, std::filesystem::copy_options::recursive);
  std::filesystem::remove_all(copy / "gt");
  auto scene = Scene::open(copy.string());
  expect_error_with<std::runtime_error>([&] { read_gt_ids(*scene, 0); }, {"gt", "ag2gs synth"});
}

}  // namespace
}  // namespace ag2gs
