// Stage-1 training (train/trainer.h, `ag2gs train`) on the synthetic sample
// scene at -r 2 (80x60): the loss falls and PSNR rises, the same seed gives
// byte-identical model files, the files read back, and bad output folders or
// scenes without points fail before any training.
#include <gtest/gtest.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <numeric>

#include "host/io/model_io.h"
#include "host/io/model_ply.h"
#include "host/io/ply_io.h"
#include "host/render/importance.h"
#include "host/scene/scene.h"
#include "tests/io_test_util.h"
#include "tests/test_util.h"
#include "train/anchors/anchor_model.h"
#include "train/anchors/expander.h"
#include "train/train_common.h"
#include "train/trainer.h"

namespace fs = std::filesystem;

namespace ag2gs {
namespace {

struct Result {
  int code;
  std::string output;
};

Result run_cli(const std::string& args) {
  const char* bin = std::getenv("AG2GS_BINARY");
  std::string cmd = std::string(bin ? bin : "./ag2gs") + " " + args + " 2>&1";
  Result r{-1, ""};
  FILE* p = popen(cmd.c_str(), "r");
  if (!p) return r;
  std::array<char, 4096> buf;
  while (fgets(buf.data(), buf.size(), p)) r.output += buf.data();
  int status = pclose(p);
  r.code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  return r;
}

std::string sample_scene() {
  return test::source_path("data_samples/synth_small");
}

TEST(Train, LossFallsAndTrainingPsnrRises) {
  SceneOptions so;
  so.resolution = 2;
  so.eval = true;
  auto scene = Scene::open(sample_scene(), so);
  TrainConfig cfg;
  cfg.iterations = 200;
  cfg.seed = 3;
  cfg.anchors.top_cells = 50;   // coarser voxels than the default 200: fewer Gaussians, a faster test
  cfg.white_background = true;  // the sample's sky is bright
  // The Gaussians alone: a learned sky starts from its fit to the photos
  // and would take the first part of the fall (tests/host/render/test_sky.cpp).
  cfg.sky_degree = -1;
  Trainer trainer(test::runtime(), *scene, cfg);
  const std::vector<int> train = scene->train_views();
  ASSERT_GT(trainer.anchors(), 0u);
  EXPECT_EQ(trainer.gaussians(), trainer.anchors() * cfg.anchors.children);

  const EvalStats before = trainer.evaluate(train);
  const size_t epoch = train.size();
  double first = 0, last = 0;
  std::vector<double> losses;
  for (int it = 0; it < cfg.iterations; ++it) {
    StepStats st = trainer.step(true);
    ASSERT_FALSE(st.skipped) << "iteration " << st.iteration;
    ASSERT_TRUE(std::isfinite(st.loss));
    ASSERT_TRUE(st.with_offset_loss);
    losses.push_back(st.loss - cfg.w_offset * st.offset_reg);  // L_in >= 1 is a constant floor
  }
  for (size_t i = 0; i < epoch; ++i) first += losses[i] / epoch;
  for (size_t i = losses.size() - epoch; i < losses.size(); ++i) last += losses[i] / epoch;
  const EvalStats after = trainer.evaluate(train);
  std::printf("loss first epoch %.4f, last epoch %.4f; train PSNR %.2f -> %.2f dB, SSIM %.3f -> %.3f\n", first, last,
              before.psnr, after.psnr, before.ssim, after.ssim);
  EXPECT_LT(last, 0.7 * first);
  EXPECT_GT(after.psnr, before.psnr + 3.5);  // measured: 15.8 -> 20.2 dB (CPU)
  EXPECT_GT(after.ssim, before.ssim);
  EXPECT_EQ(trainer.iteration(), cfg.iterations);
  EXPECT_EQ(trainer.active_sh_degree(), 3);
}

TEST(Train, GrowingAndPruningKeepTheModelAndOptimiserConsistent) {
  SceneOptions so;
  so.resolution = 2;
  auto scene = Scene::open(sample_scene(), so);
  TrainConfig cfg;
  cfg.iterations = 80;
  cfg.anchors.top_cells = 50;
  cfg.white_background = true;
  cfg.grow_from = 40;
  cfg.grow_every = 40;
  cfg.grow_threshold = 1e-3;
  cfg.prune_opacity = 0.12;  // above the initial 0.1: prunes anchors whose children did not gain opacity
  Trainer trainer(test::runtime(), *scene, cfg);
  const size_t a0 = trainer.anchors();
  int grown = 0, pruned = 0;
  for (int it = 0; it < cfg.iterations; ++it) {
    StepStats st = trainer.step();
    ASSERT_FALSE(st.skipped) << "iteration " << st.iteration;
    ASSERT_TRUE(std::isfinite(st.loss)) << "iteration " << st.iteration;
    grown += st.grown;
    pruned += st.pruned;
  }
  std::printf("anchors %zu -> %zu: grew %d, pruned %d\n", a0, trainer.anchors(), grown, pruned);
  EXPECT_GT(grown, 0);
  EXPECT_GT(pruned, 0);
  EXPECT_EQ(trainer.anchors(), a0 + grown - pruned);
  const AnchorModel& m = trainer.model();
  m.check();
  EXPECT_EQ(m.size(), trainer.anchors());
  for (float x : m.offset()) ASSERT_TRUE(std::isfinite(x));
  for (float x : m.opacity_logit()) ASSERT_TRUE(std::isfinite(x));
  // Every remaining voxel is taken once and findable.
  for (size_t a = 0; a < m.size(); ++a)
    ASSERT_EQ(m.find(m.layer()[a], Eigen::Vector3i(m.cell()[3 * a], m.cell()[3 * a + 1], m.cell()[3 * a + 2])),
              static_cast<int>(a));
}

// The final prune (TrainConfig::final_prune_opacity) runs once, after the
// last stage-1 iteration: the anchors whose children's mean opacity is below
// the threshold go, every other anchor keeps its bits, and the optimiser
// follows the rows (a stage-2 step after it runs). With the threshold 0
// nothing is removed.
TEST(Train, FinalPruneRemovesFadedAnchorsAndKeepsTheRest) {
  SceneOptions so;
  so.resolution = 2;
  auto scene = Scene::open(sample_scene(), so);
  TrainConfig cfg;
  cfg.iterations = 30;
  cfg.anchors.top_cells = 50;
  cfg.white_background = true;
  cfg.grow_from = 1000;          // no growing rounds
  const double threshold = 0.1;  // the initial opacity: about half the anchors fall below it in 30 steps
  size_t removed = 0;
  for (double t : {0.0, threshold}) {
    cfg.final_prune_opacity = t;
    Trainer trainer(test::runtime(), *scene, cfg);
    for (int it = 0; it + 1 < cfg.iterations; ++it) ASSERT_FALSE(trainer.step().skipped);
    const size_t a0 = trainer.anchors();
    StepStats last = trainer.step();
    ASSERT_FALSE(last.skipped);
    if (t == 0) {
      EXPECT_EQ(trainer.anchors(), a0);
      EXPECT_EQ(last.pruned, 0);
      continue;
    }
    // The model a step without the prune would have left: the same run with t = 0.
    Trainer ref_trainer(test::runtime(), *scene, [&] {
      TrainConfig c = cfg;
      c.final_prune_opacity = 0;
      return c;
    }());
    for (int it = 0; it < cfg.iterations; ++it) ASSERT_FALSE(ref_trainer.step().skipped);
    const AnchorModel& ref = ref_trainer.model();
    const AnchorModel& m = trainer.model();
    m.check();
    size_t below = 0;
    for (size_t a = 0; a < ref.size(); ++a) below += mean_opacity_below(ref, a, threshold);
    removed = a0 - trainer.anchors();
    std::printf("final prune at %.2f: %zu of %zu anchors removed\n", threshold, removed, a0);
    EXPECT_EQ(static_cast<size_t>(last.pruned), removed);
    EXPECT_EQ(removed, below);
    EXPECT_GT(removed, 0u);
    EXPECT_LT(removed, a0);
    // The kept anchors, in their order, with their children's bits.
    const int K = m.children();
    size_t r = 0;
    for (size_t a = 0; a < ref.size(); ++a) {
      if (mean_opacity_below(ref, a, threshold)) continue;
      ASSERT_LT(r, m.size());
      for (int i = 0; i < K; ++i) {
        ASSERT_EQ(m.opacity_logit()[r * K + i], ref.opacity_logit()[a * K + i]);
        for (int c = 0; c < 3; ++c) ASSERT_EQ(m.offset()[(r * K + i) * 3 + c], ref.offset()[(a * K + i) * 3 + c]);
      }
      ++r;
    }
    EXPECT_EQ(r, m.size());
    for (size_t a = 0; a < m.size(); ++a) EXPECT_FALSE(mean_opacity_below(m, a, threshold));
    // Stage 2 goes on from the pruned model.
    StepStats st2 = trainer.step();
    EXPECT_TRUE(st2.stage2);
    EXPECT_FALSE(st2.skipped);
  }
}

// The importance prune (TrainConfig::prune_importance) runs once, at its
// iteration: the anchors that draw least over the training views
// (blend_weight_sums of the model at that iteration, checked against the
// reference in test_render_backward; least_drawing_anchors, checked below)
// go while together they draw at most the share, the others keep their bits
// in their order, and training goes on from the rows left.
TEST(Train, ImportancePruneRemovesTheAnchorsThatDrawLeast) {
  SceneOptions so;
  so.resolution = 2;
  so.eval = true;
  auto scene = Scene::open(sample_scene(), so);
  TrainConfig cfg;
  cfg.iterations = 30;
  cfg.anchors.top_cells = 50;
  cfg.white_background = true;
  cfg.grow_from = 1000;  // no growing rounds
  cfg.prune_importance_at = 20;
  // Iterations 1-25 at half the resolution: the prune walks the views at
  // the size its step renders at.
  // (The sample has masks; steps with the mask losses render at full
  // resolution, so they start after the prune.)
  cfg.downscales = 1;
  cfg.res_schedule = 25;
  cfg.mask_from = 25;
  ASSERT_EQ(cfg.resolution_level(cfg.prune_importance_at - 1), 1);
  Trainer ref_trainer(test::runtime(), *scene, cfg);
  for (int it = 0; it < cfg.prune_importance_at; ++it) ASSERT_FALSE(ref_trainer.step().skipped);
  const AnchorModel ref = ref_trainer.model();
  // The measure, from the model the pruning run holds at that iteration.
  Runtime& rt = test::runtime();
  DeviceAnchors da(rt);
  da.upload(ref);
  DeviceGaussians dg(rt);
  // The trainer's SH degree during that step: that of iteration at - 1.
  Expander(rt).forward(da, dg,
                       std::min(cfg.anchors.sh_degree, (cfg.prune_importance_at - 1) / cfg.effective_sh_interval()));
  std::vector<Camera> cams;
  for (int v : scene->train_views()) cams.push_back(downscaled_camera(scene->views()[v].camera, 2));
  Renderer r(rt);
  RenderSettings settings;
  settings.lowpass = cfg.lowpass_at_level(1);
  const std::vector<double> per_child = blend_weight_sums(r, dg, cams, settings);
  const int K = ref.children();
  cfg.prune_importance = 0.02;
  const std::vector<uint8_t> expected = least_drawing_anchors(per_child, K, cfg.prune_importance);
  Trainer trainer(test::runtime(), *scene, cfg);
  int pruned = 0;
  for (int it = 0; it < cfg.prune_importance_at; ++it) pruned += trainer.step().pruned;
  const AnchorModel& m = trainer.model();
  m.check();
  size_t r_row = 0, below = 0;
  double total = 0, removed_weight = 0;
  for (size_t a = 0; a < ref.size(); ++a) {
    double drawn = 0;
    for (int i = 0; i < K; ++i) drawn += per_child[a * K + i];
    total += drawn;
    if (!expected[a]) {
      ++below;
      removed_weight += drawn;
      continue;
    }
    ASSERT_LT(r_row, m.size());
    for (int i = 0; i < K; ++i) {
      ASSERT_EQ(m.opacity_logit()[r_row * K + i], ref.opacity_logit()[a * K + i]);
      for (int c = 0; c < 3; ++c) ASSERT_EQ(m.offset()[(r_row * K + i) * 3 + c], ref.offset()[(a * K + i) * 3 + c]);
    }
    ++r_row;
  }
  std::printf("importance prune of %.0f%%: %zu of %zu anchors removed, drawing %.3f%%\n", 100 * cfg.prune_importance,
              below, ref.size(), 100 * removed_weight / total);
  EXPECT_EQ(r_row, m.size());
  EXPECT_EQ(static_cast<size_t>(pruned), below);
  EXPECT_GT(below, ref.size() / 20);
  EXPECT_LE(removed_weight, cfg.prune_importance * total);
  // Training goes on from the pruned rows, through the last iteration.
  for (int it = cfg.prune_importance_at; it < cfg.iterations; ++it) ASSERT_FALSE(trainer.step().skipped);
  // An iteration outside stage 1 is refused.
  TrainConfig late = cfg;
  late.prune_importance_at = cfg.iterations + 1;
  EXPECT_THROW(late.validate(), std::invalid_argument);
}

// least_drawing_anchors against the rule worked by hand: 4 anchors of 2
// children drawing 3, 1, 6 and 1 px (total 11); ties go by index.
TEST(Train, LeastDrawingAnchorsTakeTheLeastWhileUnderTheShare) {
  const std::vector<double> per_child = {1, 2, 0.5, 0.5, 6, 0, 0, 1};
  using Keep = std::vector<uint8_t>;
  EXPECT_EQ(least_drawing_anchors(per_child, 2, 0.0), (Keep{1, 1, 1, 1}));
  EXPECT_EQ(least_drawing_anchors(per_child, 2, 1.5 / 11), (Keep{1, 0, 1, 1}));  // 1 fits, 1 + 1 does not
  EXPECT_EQ(least_drawing_anchors(per_child, 2, 2.5 / 11), (Keep{1, 0, 1, 0}));
  EXPECT_EQ(least_drawing_anchors(per_child, 2, 4.9 / 11), (Keep{1, 0, 1, 0}));  // + 3 would make 5
  EXPECT_EQ(least_drawing_anchors(per_child, 2, 5.5 / 11), (Keep{0, 0, 1, 0}));
  EXPECT_EQ(least_drawing_anchors(per_child, 2, 1.0), (Keep{0, 0, 1, 0}));  // never every anchor
  EXPECT_THROW(least_drawing_anchors(per_child, 3, 0.1), std::invalid_argument);
}

TEST(Train, ViewOrderIsASeededPermutationPerEpoch) {
  SceneOptions so;
  so.resolution = 2;
  auto scene = Scene::open(sample_scene(), so);
  TrainConfig cfg;
  cfg.iterations = 10;
  cfg.seed = 7;
  Trainer a(test::runtime(), *scene, cfg);
  const size_t n = scene->train_views().size();
  for (int epoch = 0; epoch < 3; ++epoch) {
    std::vector<int> seen;
    for (size_t i = 0; i < n; ++i) seen.push_back(a.view_for_iteration(static_cast<int>(epoch * n + i)));
    std::sort(seen.begin(), seen.end());
    EXPECT_EQ(seen, scene->train_views()) << "epoch " << epoch;
  }
  cfg.seed = 8;
  Trainer b(test::runtime(), *scene, cfg);
  int differ = 0;
  for (int i = 0; i < static_cast<int>(n); ++i) differ += a.view_for_iteration(i) != b.view_for_iteration(i);
  EXPECT_GT(differ, 0);
}

// One growing round at iteration 40 (threshold raised so that it adds a few
// dozen anchors, not thousands: keeps the test fast).
const std::string kGrow = "--grow-from 40 --grow-every 40 --grow-threshold 1e-3";

TEST(Train, SameSeedGivesByteIdenticalModelFiles) {
  test::ScratchDir dir("train_det");
  const std::string args =
      "train " + sample_scene() + " -r 2 --top-cells 50 --iters 60 --seed 5 --log-every 0 --stages 1 " + kGrow + " -o ";
  Result r1 = run_cli(args + dir.file("a"));
  ASSERT_EQ(r1.code, 0) << r1.output;
  Result r2 = run_cli(args + dir.file("b"));
  ASSERT_EQ(r2.code, 0) << r2.output;
  EXPECT_EQ(r1.output.find("step skipped"), std::string::npos) << r1.output;  // finite after growing too
  for (const char* f : {"model.ag2gs", "point_cloud.ply"}) {
    const std::string a = test::read_bytes(dir.file(std::string("a/") + f));
    const std::string b = test::read_bytes(dir.file(std::string("b/") + f));
    ASSERT_FALSE(a.empty()) << f;
    EXPECT_TRUE(a == b) << f << " differs between two runs with the same seed";
  }
  Result r3 = run_cli("train " + sample_scene() + " -r 2 --top-cells 50 --iters 60 --seed 6 --log-every 0 --stages 1 " +
                      kGrow + " -o " + dir.file("c"));
  ASSERT_EQ(r3.code, 0) << r3.output;
  EXPECT_FALSE(test::read_bytes(dir.file("a/model.ag2gs")) == test::read_bytes(dir.file("c/model.ag2gs")));

  // The files read back: the archive as an anchor model with the run's
  // iteration and seed, the PLY as one Gaussian per child.
  ModelArchive archive = read_model_archive(dir.file("a/model.ag2gs"));
  AnchorModel model = AnchorModel::from_archive(archive);
  EXPECT_EQ(archive.meta["train"]["iteration"].get<int>(), 60);
  EXPECT_EQ(archive.meta["train"]["seed"].get<uint64_t>(), 5u);
  EXPECT_EQ(archive.meta["train"]["config"]["iterations"].get<int>(), 60);
  EXPECT_GT(std::count(model.layer().begin(), model.layer().end(), 1), 0) << "no anchor grew on layer 1";
  // The log's growing round accounts for the anchor count (initial + grown -
  // pruned; growing also adds anchors on a child's own layer).
  const size_t at = r1.output.find("iteration 40: grew ");
  ASSERT_NE(at, std::string::npos) << r1.output;
  int grew = 0, pruned = 0, after = 0;
  // (A round over its budget says how many more asked between the two.)
  ASSERT_EQ(std::sscanf(r1.output.c_str() + at, "iteration 40: grew %d anchors", &grew), 1) << r1.output;
  const size_t pruned_at = r1.output.find("pruned ", at);
  ASSERT_NE(pruned_at, std::string::npos) << r1.output;
  ASSERT_EQ(std::sscanf(r1.output.c_str() + pruned_at, "pruned %d -> %d anchors", &pruned, &after), 2) << r1.output;
  EXPECT_GT(grew, 0);
  // The importance prune (at iteration 50, halfway from the end of growing
  // to the last iteration) says what it removed.
  int least = 0;
  const size_t least_at = r1.output.find("iteration 50: removed the ");
  ASSERT_NE(least_at, std::string::npos) << r1.output;
  ASSERT_EQ(std::sscanf(r1.output.c_str() + least_at, "iteration 50: removed the %d anchors", &least), 1);
  EXPECT_GT(least, 0);
  EXPECT_EQ(static_cast<size_t>(after - least), model.size());
  const size_t init_at = r1.output.find("anchors: ");
  ASSERT_NE(init_at, std::string::npos);
  EXPECT_EQ(std::stoul(r1.output.substr(init_at + 9)) + grew - pruned - least, model.size());
  GaussianSet ply = read_ply(model_objects_ply(dir.file("a")));  // without a baked sky
  EXPECT_EQ(ply.size(), model.gaussians());
  EXPECT_EQ(ply.sh_degree, 3);
  GaussianSet ref = expand_reference(model, 3);
  ASSERT_EQ(ref.size(), ply.size());
  for (size_t i = 0; i < ply.means.size(); ++i) ASSERT_EQ(ply.means[i], ref.means[i]) << i;
  for (size_t i = 0; i < ply.opacities.size(); ++i) ASSERT_NEAR(ply.opacities[i], ref.opacities[i], 1e-6) << i;
}

TEST(Train, EvalWritesTestMetrics) {
  test::ScratchDir dir("train_eval");
  Result r = run_cli("train " + sample_scene() +
                     " -r 2 --top-cells 50 --white-bg --iters 30 --eval --test-every 15 --log-every 10 --stages 1 -o " +
                     dir.file("m"));
  ASSERT_EQ(r.code, 0) << r.output;
  EXPECT_NE(r.output.find("anchors"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("it/s"), std::string::npos) << r.output;
  std::ifstream f(dir.file("m/metrics.json"));
  ASSERT_TRUE(f) << r.output;
  nlohmann::json m = nlohmann::json::parse(f);
  ASSERT_EQ(m["test"].size(), 2u) << m.dump();
  EXPECT_EQ(m["test"][0]["iteration"].get<int>(), 15);
  EXPECT_EQ(m["final"]["iteration"].get<int>(), 30);
  EXPECT_GT(m["final"]["psnr"].get<double>(), 5.0);
  EXPECT_EQ(m["test_views"].get<int>(), 2);
  // Step times: the median and 90th percentile of the steps without an
  // evaluation, and the median after the last growing round (iteration 20).
  EXPECT_NE(r.output.find("step time: median"), std::string::npos) << r.output;
  const double median = m["ms_per_iteration_median"].get<double>(), p90 = m["ms_per_iteration_p90"].get<double>();
  EXPECT_GT(median, 0.0);
  EXPECT_LE(median, p90);
  EXPECT_GT(m["ms_per_iteration_median_after_growing"].get<double>(), 0.0);
}

TEST(Train, UnwritableModelDirFailsBeforeTraining) {
  test::ScratchDir dir("train_unwritable");
  test::write_bytes(dir.file("file"), "not a folder");
  Result r = run_cli("train " + sample_scene() + " -r 2 --iters 5 -o " + dir.file("file/model"));
  EXPECT_EQ(r.code, 1) << r.output;
  EXPECT_NE(r.output.find(dir.file("file/model")), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("cannot be created"), std::string::npos) << r.output;
  EXPECT_EQ(r.output.find("iterations"), std::string::npos) << "training started: " << r.output;
}

TEST(Train, SceneWithoutPointsFailsClearly) {
  test::ScratchDir dir("train_nopoints");
  const fs::path scene = dir.path() / "scene";
  fs::create_directories(scene / "sparse" / "0");
  fs::copy(fs::path(sample_scene()) / "images", scene / "images", fs::copy_options::recursive);
  for (const char* f : {"cameras.bin", "images.bin"})
    fs::copy_file(fs::path(sample_scene()) / "sparse/0" / f, scene / "sparse/0" / f);
  test::write_bytes((scene / "sparse/0/points3D.bin").string(), std::string(8, '\0'));  // zero points
  Result r = run_cli("train " + scene.string() + " -r 2 --iters 5 -o " + dir.file("m"));
  EXPECT_EQ(r.code, 1) << r.output;
  EXPECT_NE(r.output.find("points3D"), std::string::npos) << r.output;
  EXPECT_FALSE(fs::exists(dir.file("m/model.ag2gs")));

  // The library refuses too.
  SceneOptions so;
  so.resolution = 2;
  auto s = Scene::open(scene.string(), so);
  EXPECT_THROW(Trainer(test::runtime(), *s, TrainConfig{}), std::runtime_error);
}

}  // namespace
}  // namespace ag2gs
