// Stages 2 and 3 in training (train/trainer.h, `ag2gs train`) on the
// synthetic sample scene at -r 2 (80x60): L_prop against a double-precision
// host evaluation over the graph, the features (and only they) trained by
// stage 2, resume bit-exact across the stage boundary and inside stage 2, and
// the whole pipeline through the CLI (graph, clusters, language in the model,
// `ag2gs info`, --stages 3 re-clustering, same bytes for the same seed).
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <string>

#include "host/io/model_io.h"
#include "host/scene/scene.h"
#include "tests/cli_test_util.h"
#include "tests/io_test_util.h"
#include "tests/test_util.h"
#include "train/graph/anchor_graph.h"
#include "train/stage3/clustering.h"
#include "train/stage3/language.h"
#include "train/trainer.h"

namespace fs = std::filesystem;

namespace ag2gs {
namespace {

std::string sample_scene() {
  return test::source_path("data_samples/synth_small");
}

// 60 stage-1 iterations (growing rounds at 20 and 40, masks from 10), then 20 of stage 2.
TrainConfig stage_config() {
  TrainConfig cfg;
  cfg.iterations = 60;
  cfg.prop_iters = 20;
  cfg.seed = 6;
  cfg.anchors.top_cells = 50;
  cfg.grow_from = 20;
  cfg.grow_every = 20;
  cfg.grow_until = 40;
  cfg.grow_threshold = 1e-3;
  cfg.opacity_reset_every = 0;
  cfg.mask_from = 10;
  return cfg;
}

// L_prop of docs/design.md section 6 in double precision, straight from the CSR rows.
double host_prop_loss(const AnchorGraph& g, const std::vector<float>& f, double tau) {
  double sum = 0;
  size_t edges = 0;
  for (size_t i = 0; i < g.anchors(); ++i)
    for (int32_t e = g.row_offsets()[i]; e < g.row_offsets()[i + 1]; ++e) {
      const size_t j = static_cast<size_t>(g.neighbours()[e]);
      if (j <= i) continue;  // each undirected edge once
      double d2 = 0;
      for (int c = 0; c < 3; ++c) {
        const double x = static_cast<double>(f[i * 3 + c]) - f[j * 3 + c];
        d2 += x * x;
      }
      sum += std::exp(-d2 / (2 * tau * tau)) * d2;
      ++edges;
    }
  return edges ? sum / edges : 0;
}

TEST(TrainStages, Stage2TrainsTheFeaturesWithThePropagationLoss) {
  SceneOptions so;
  so.resolution = 2;
  auto scene = Scene::open(sample_scene(), so);
  ASSERT_NE(scene->semantics(), SemanticsKind::none);
  TrainConfig cfg = stage_config();
  // Mask losses on the features alone, so that L_prop's effect on them is
  // all that differs between the runs (with the joint default, features
  // reach the geometry through the mask losses' gradient).
  cfg.mask_geometry = false;
  TrainConfig off = cfg;
  off.w_prop = 0;
  Trainer a(test::runtime(), *scene, cfg), b(test::runtime(), *scene, off);
  EXPECT_EQ(cfg.total_iterations(), 80);
  for (int it = 0; it < cfg.iterations; ++it) {
    const StepStats sa = a.step(), sb = b.step();
    EXPECT_FALSE(sa.stage2);
    EXPECT_EQ(sa.loss, sb.loss) << it;
  }
  EXPECT_FALSE(a.has_graph());
  ASSERT_TRUE(a.model().feature() == b.model().feature());
  const int64_t feature_steps = a.adam_group("feature").steps();
  const std::vector<float> f0 = a.model().feature();
  double lprop_first = 0;
  for (int it = cfg.iterations; it < cfg.total_iterations(); ++it) {
    const StepStats sa = a.step(), sb = b.step();
    EXPECT_TRUE(sa.stage2);
    EXPECT_FALSE(sa.skipped);
    EXPECT_EQ(sa.grown + sa.pruned, 0);  // no growing in stage 2
    if (it == cfg.iterations) {
      ASSERT_TRUE(a.has_graph());
      EXPECT_TRUE(a.graph().matches(a.model()));
      EXPECT_TRUE(a.graph() == AnchorGraph::build(a.model()));
      EXPECT_GT(a.graph().edges(), 0u);
      const double ref = host_prop_loss(a.graph(), f0, cfg.prop_tau);
      std::printf("first stage-2 step: L_prop %.6e (host double %.6e), %zu anchors, %zu edges\n", sa.l_prop, ref,
                  a.anchors(), a.graph().edges());
      EXPECT_GT(ref, 0);
      EXPECT_NEAR(sa.l_prop, ref, 1e-4 * ref);
      lprop_first = sa.l_prop;
      // The loss is a sum of terms: equal up to the rounding of that sum.
      EXPECT_NEAR(sa.loss - sb.loss, cfg.w_prop * sa.l_prop, 1e-12);
    }
    EXPECT_EQ(sb.l_prop, 0);
  }
  // Every stage-2 step stepped the features.
  EXPECT_EQ(a.adam_group("feature").steps() - feature_steps, cfg.total_iterations() - cfg.iterations);
  const AnchorModel& ma = a.model();
  const AnchorModel& mb = b.model();
  EXPECT_FALSE(ma.feature() == mb.feature()) << "L_prop did not change the features";
  // The propagation term smooths: the last edge energy is below the first
  // (and below the run without it).
  const double end_a = host_prop_loss(a.graph(), ma.feature(), cfg.prop_tau);
  const double end_b = host_prop_loss(a.graph(), mb.feature(), cfg.prop_tau);
  std::printf("L_prop after stage 2: %.6e with w_prop %.3g, %.6e without (first %.6e)\n", end_a, cfg.w_prop, end_b,
              lprop_first);
  // Appearance and geometry do not see the features (mask losses on the
  // features alone): bit-identical.
  EXPECT_TRUE(ma.offset() == mb.offset());
  EXPECT_TRUE(ma.opacity_logit() == mb.opacity_logit());
  EXPECT_TRUE(ma.sh() == mb.sh());
  // The model file carries the graph and says stage 2.
  test::ScratchDir dir("train_stage2");
  a.save(dir.str());
  const ModelArchive ar = read_model_archive(dir.file("model.ag2gs"));
  ASSERT_TRUE(AnchorGraph::in_archive(ar));
  EXPECT_TRUE(AnchorGraph::from_archive(ar) == a.graph());
  EXPECT_EQ(ar.meta["train"]["stage"].get<int>(), 2);
  EXPECT_EQ(ar.meta["train"]["iteration"].get<int>(), 80);
}

TEST(TrainStages, ResumeIsBitExactAcrossTheStageBoundaryAndInsideStage2) {
  SceneOptions so;
  so.resolution = 2;
  auto scene = Scene::open(sample_scene(), so);
  const TrainConfig cfg = stage_config();
  test::ScratchDir dir("train_stage2_resume");
  {
    Trainer straight(test::runtime(), *scene, cfg);
    for (int it = 0; it < cfg.total_iterations(); ++it) straight.step();
    straight.save(dir.file("straight"));
  }
  // 60 = the boundary (no graph yet in the checkpoint), 70 = inside stage 2 (graph read back).
  for (int cut : {60, 70}) {
    const std::string name = "cut" + std::to_string(cut);
    {
      Trainer first(test::runtime(), *scene, cfg);
      for (int it = 0; it < cut; ++it) first.step();
      first.save(dir.file(name));
    }
    const ModelArchive ck = read_model_archive(dir.file(name + "/checkpoint.ag2gs"));
    EXPECT_EQ(AnchorGraph::in_archive(ck), cut > cfg.iterations) << cut;
    {
      Trainer second(test::runtime(), *scene, cfg);
      second.resume(dir.file(name));
      EXPECT_EQ(second.iteration(), cut);
      EXPECT_EQ(second.has_graph(), cut > cfg.iterations);
      for (int it = cut; it < cfg.total_iterations(); ++it) second.step();
      second.save(dir.file(name));
    }
    test::expect_same_model_files(dir.file("straight"), dir.file(name),
                                  "the straight run and the one resumed at " + std::to_string(cut));
  }
}

// The whole pipeline through the CLI: stages 1, 2, 3 by default.
TEST(TrainStages, CliRunsAllStagesAndInfoReportsThem) {
  test::ScratchDir dir("train_pipeline");
  const std::string args = "train " + sample_scene() +
                           " -r 2 --top-cells 50 --iters 90 --prop-iters 30 --seed 11 --log-every 0 --grow-from 30 "
                           "--grow-every 30 --grow-threshold 1e-3 --mask-from 10 --cluster-distance 0.2 -o ";
  // The launch log gives the device memory allocated at each launch.
  const std::string launches = dir.file("launches.txt");
  setenv("AG2GS_LAUNCH_LOG", launches.c_str(), 1);
  const test::CliResult r1 = test::run_cli(args + dir.file("a"));
  unsetenv("AG2GS_LAUNCH_LOG");
  ASSERT_EQ(r1.code, 0) << r1.output;
  EXPECT_NE(r1.output.find("stage 2"), std::string::npos) << r1.output;
  EXPECT_NE(r1.output.find("stage times"), std::string::npos) << r1.output;
  {
    // Stage 3 reads the saved model: the trainer's buffers (parameters and
    // optimiser moments among them) are released before it, so its launches
    // see less memory than any optimiser step did (under Oclgrind's race
    // detector every launch costs time in proportion to it).
    std::ifstream log(launches);
    uint64_t adam_least = UINT64_MAX, instance_most = 0;
    int n_adam = 0, n_instance = 0;
    for (std::string line; std::getline(log, line);) {
      const size_t at = line.find(" mem=");
      ASSERT_NE(at, std::string::npos) << line;
      const uint64_t mem = std::stoull(line.substr(at + 5));
      const std::string kernel = line.substr(0, line.find(' '));
      if (kernel == "adam_step") adam_least = std::min(adam_least, mem), ++n_adam;
      if (kernel == "instance_map") instance_most = std::max(instance_most, mem), ++n_instance;
    }
    ASSERT_GT(n_adam, 0);
    ASSERT_GT(n_instance, 0);
    EXPECT_LT(instance_most, adam_least) << "stage 3 ran beside the trainer's buffers";
  }
  const test::CliResult r2 = test::run_cli(args + dir.file("b"));
  ASSERT_EQ(r2.code, 0) << r2.output;
  for (const char* f : {"model.ag2gs", "point_cloud.ply", "checkpoint.ag2gs"})
    EXPECT_TRUE(test::read_bytes(dir.file(std::string("a/") + f)) == test::read_bytes(dir.file(std::string("b/") + f)))
        << f << " differs between two runs with the same seed";

  const ModelArchive ar = read_model_archive(dir.file("a/model.ag2gs"));
  const AnchorModel model = AnchorModel::from_archive(ar);
  ASSERT_TRUE(AnchorGraph::in_archive(ar));
  const AnchorGraph graph = AnchorGraph::from_archive(ar);
  EXPECT_TRUE(graph.matches(model));
  const Clustering c = clustering_from_archive(ar, model.size());
  // The clusters are those of the stored features over the stored graph.
  const std::vector<float> dist = edge_feature_distances(
      AnchorGraphView{graph.anchors(), graph.row_offsets().data(), graph.neighbours().data(), nullptr},
      model.feature());
  auto reference = [&](float max_distance) {
    ClusterConfig cc;
    cc.max_distance = max_distance;
    return cluster_anchors(
        AnchorGraphView{graph.anchors(), graph.row_offsets().data(), graph.neighbours().data(), dist.data()}, cc);
  };
  EXPECT_EQ(c.anchor_cluster, reference(0.2f).anchor_cluster);
  EXPECT_GT(c.clusters(), 0);
  const LanguageFeatures lang = language_from_archive(ar, c.clusters());
  EXPECT_EQ(lang.clusters(), c.clusters());
  std::printf("pipeline: %zu anchors, %zu edges, %d clusters, %d with language\n", model.size(), graph.edges(),
              c.clusters(), lang.with_language());

  const test::CliResult info = test::run_cli("info " + dir.file("a"));
  ASSERT_EQ(info.code, 0) << info.output;
  EXPECT_NE(info.output.find("anchor graph: " + std::to_string(model.size()) + " anchors"), std::string::npos)
      << info.output;
  EXPECT_NE(info.output.find("clusters: " + std::to_string(c.clusters()) + " over"), std::string::npos) << info.output;
  EXPECT_NE(info.output.find("language features: " + std::to_string(lang.with_language()) + " of " +
                             std::to_string(c.clusters())),
            std::string::npos)
      << info.output;

  // Re-clustering with another threshold: stage 3 alone, model replaced.
  const test::CliResult re =
      test::run_cli("train " + sample_scene() + " -o " + dir.file("a") + " --stages 3 --cluster-distance 0.05");
  ASSERT_EQ(re.code, 0) << re.output;
  const ModelArchive ar2 = read_model_archive(dir.file("a/model.ag2gs"));
  EXPECT_TRUE(AnchorModel::from_archive(ar2).feature() == model.feature());
  EXPECT_TRUE(AnchorGraph::from_archive(ar2) == graph);
  EXPECT_FLOAT_EQ(ar2.meta["clusters"]["max_distance"].get<float>(), 0.05f);
  const Clustering c2 = clustering_from_archive(ar2, model.size());
  EXPECT_EQ(c2.anchor_cluster, reference(0.05f).anchor_cluster);
  EXPECT_EQ(language_from_archive(ar2, c2.clusters()).clusters(), c2.clusters());
  std::printf("re-clustered at 0.05: %d clusters\n", c2.clusters());
  // Stage 3 on a model without stage 2 data still needs the model file.
  const test::CliResult missing =
      test::run_cli("train " + sample_scene() + " -o " + dir.file("nothing") + " --stages 3");
  EXPECT_NE(missing.code, 0);
  EXPECT_NE(missing.output.find("model.ag2gs"), std::string::npos) << missing.output;
}

// A scene without SAM masks trains stage 1 only: its features never train,
// so there is nothing for stages 2 and 3.
TEST(TrainStages, SceneWithoutMasksSkipsStages2And3) {
  test::ScratchDir dir("train_nomasks");
  fs::create_directories(dir.path() / "scene");
  for (const char* sub : {"images", "sparse"})
    fs::copy(fs::path(sample_scene()) / sub, dir.path() / "scene" / sub, fs::copy_options::recursive);
  const test::CliResult r = test::run_cli("train " + dir.file("scene") +
                                          " -r 2 --top-cells 50 --iters 30 --seed 1 --log-every 0 -o " + dir.file("m"));
  ASSERT_EQ(r.code, 0) << r.output;
  EXPECT_NE(r.output.find("stages 2 and 3 skipped"), std::string::npos) << r.output;
  const ModelArchive ar = read_model_archive(dir.file("m/model.ag2gs"));
  EXPECT_FALSE(AnchorGraph::in_archive(ar));
  EXPECT_FALSE(ar.meta.contains("clusters"));
  EXPECT_EQ(ar.meta["train"]["iteration"].get<int>(), 30);
}

}  // namespace
}  // namespace ag2gs
