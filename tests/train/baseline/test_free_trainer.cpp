// The free-Gaussian baseline (train/baseline/free_trainer.h, `ag2gs baseline`):
// densification decisions against an independent double-precision CPU
// reference written the way 3DGS's densify_and_prune is (masks over the
// growing set), split samples against their formula, device statistics
// against the host renderer's gradients, a short run on the sample scene
// (PSNR rises, densification changes the count), byte-identical PLYs for the
// same seed across PoCL thread counts, and the CLI's errors.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <random>
#include <tuple>

#include "host/io/ply_io.h"
#include "host/losses/image_loss.h"
#include "host/scene/scene.h"
#include "tests/cli_test_util.h"
#include "tests/io_test_util.h"
#include "tests/reference/densify_reference.h"
#include "tests/test_util.h"
#include "train/baseline/free_trainer.h"

namespace fs = std::filesystem;

namespace ag2gs {
namespace {

std::string sample_scene() {
  return test::source_path("data_samples/synth_small");
}

using Row = ref::DensifyRow;  // kind (0 kept, 1 clone, 2 split), source, sample

// A constructed set around the thresholds: scales on both sides of the
// clone/split limit and of the world-size limit, opacities on both sides of
// the prune level, gradients on both sides of the threshold, unseen rows.
void constructed_set(size_t n, uint32_t seed, FreeGaussians* g, DensifyStats* s) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(0, 1);
  g->resize(n);
  s->grad_sum.resize(n);
  s->count.resize(n);
  s->max_radius.resize(n);
  for (size_t i = 0; i < n; ++i) {
    for (int k = 0; k < 3; ++k) {
      g->mean[i * 3 + k] = static_cast<float>(u(rng) * 4 - 2);
      g->log_scale[i * 3 + k] = static_cast<float>(std::log(0.002) + u(rng) * (std::log(0.6) - std::log(0.002)));
      g->sh_dc[i * 3 + k] = static_cast<float>(u(rng) - 0.5);
    }
    Eigen::Vector4d q(u(rng) - 0.5, u(rng) - 0.5, u(rng) - 0.5, u(rng) - 0.5);
    for (int k = 0; k < 4; ++k) g->quat[i * 4 + k] = static_cast<float>(q[k] * 3);
    const double o = std::exp(std::log(0.001) + u(rng) * (std::log(0.9) - std::log(0.001)));
    g->opacity_logit[i] = static_cast<float>(std::log(o / (1 - o)));
    for (int k = 0; k < 45; ++k) g->sh_rest[i * 45 + k] = static_cast<float>(u(rng) - 0.5);
    s->count[i] = static_cast<int>(u(rng) * 5);  // 0..4, 0 = never seen
    s->grad_sum[i] = static_cast<float>(s->count[i] * 2e-4 * (0.3 + 1.4 * u(rng)));
    s->max_radius[i] = static_cast<int>(u(rng) * 40);
  }
}

std::vector<Row> rows_of(const DensifyPlan& p) {
  std::vector<Row> r;
  for (size_t i = 0; i < p.source.size(); ++i)
    r.emplace_back(static_cast<int>(p.kind[i]), p.source[i], p.split_sample[i]);
  return r;
}

TEST(FreeTrainer, DensificationDecisionsMatchTheReference) {
  FreeTrainConfig c;
  const double extent = 3.0;  // clone limit 0.03, world limit 0.3
  int clones = 0, splits = 0, pruned = 0;
  for (uint32_t seed : {1u, 2u, 3u}) {
    for (bool big : {false, true}) {
      FreeGaussians g;
      DensifyStats s;
      constructed_set(200, seed, &g, &s);
      const DensifyPlan plan = plan_densification(g, s, c, extent, big);
      std::vector<Row> got = rows_of(plan), want = ref::densify_reference(g, s, c, extent, big);
      ASSERT_EQ(plan.after, got.size());
      EXPECT_EQ(plan.before, g.size());
      // The documented order: kept rows, clones, split samples, each by source.
      EXPECT_TRUE(std::is_sorted(got.begin(), got.end())) << "seed " << seed;
      std::sort(want.begin(), want.end());
      EXPECT_EQ(got, want) << "seed " << seed << " prune_big " << big;
      EXPECT_EQ(static_cast<size_t>(plan.after), g.size() + plan.cloned + plan.split - plan.pruned);
      const std::vector<int> adam = plan.adam_rows();
      for (size_t r = 0; r < adam.size(); ++r)
        EXPECT_EQ(adam[r], plan.kind[r] == RowKind::kept ? plan.source[r] : -1) << r;
      clones += plan.cloned;
      splits += plan.split;
      pruned += plan.pruned;
    }
  }
  // The constructed sets exercise every branch.
  EXPECT_GT(clones, 10);
  EXPECT_GT(splits, 10);
  EXPECT_GT(pruned, 10);
  // Statistics of another row count are refused.
  FreeGaussians g;
  DensifyStats s;
  constructed_set(5, 9, &g, &s);
  s.count.pop_back();
  EXPECT_THROW(plan_densification(g, s, c, extent, false), std::invalid_argument);
}

TEST(FreeTrainer, SplitSamplesAndClonesFollowTheirFormulas) {
  FreeTrainConfig c;
  c.prune_opacity = 0;  // keep every row: this test is about the values
  FreeGaussians g;
  DensifyStats s;
  constructed_set(120, 7, &g, &s);
  const DensifyPlan plan = plan_densification(g, s, c, 3.0, false);
  ASSERT_GT(plan.split, 5);
  const FreeGaussians out = apply_densification(g, plan, 42, 700);
  ASSERT_EQ(out.size(), plan.after);
  const FreeGaussians again = apply_densification(g, plan, 42, 700);
  EXPECT_EQ(out.mean, again.mean);
  const FreeGaussians other = apply_densification(g, plan, 43, 700);
  EXPECT_NE(out.mean, other.mean);
  for (size_t r = 0; r < out.size(); ++r) {
    const size_t i = plan.source[r];
    for (int k = 0; k < 4; ++k) ASSERT_EQ(out.quat[r * 4 + k], g.quat[i * 4 + k]);
    ASSERT_EQ(out.opacity_logit[r], g.opacity_logit[i]);
    for (int k = 0; k < 45; ++k) ASSERT_EQ(out.sh_rest[r * 45 + k], g.sh_rest[i * 45 + k]);
    if (plan.kind[r] != RowKind::split) {
      for (int k = 0; k < 3; ++k) {
        ASSERT_EQ(out.mean[r * 3 + k], g.mean[i * 3 + k]);
        ASSERT_EQ(out.log_scale[r * 3 + k], g.log_scale[i * 3 + k]);
      }
      continue;
    }
    // mean + R(q) diag(s) z, R from the normalised quaternion (w, x, y, z).
    const std::array<double, 3> z = split_normal(42, 700, static_cast<int>(i), plan.split_sample[r]);
    double w = g.quat[i * 4], x = g.quat[i * 4 + 1], y = g.quat[i * 4 + 2], q3 = g.quat[i * 4 + 3];
    const double nq = std::sqrt(w * w + x * x + y * y + q3 * q3);
    w /= nq, x /= nq, y /= nq, q3 /= nq;
    const double R[3][3] = {{1 - 2 * (y * y + q3 * q3), 2 * (x * y - w * q3), 2 * (x * q3 + w * y)},
                            {2 * (x * y + w * q3), 1 - 2 * (x * x + q3 * q3), 2 * (y * q3 - w * x)},
                            {2 * (x * q3 - w * y), 2 * (y * q3 + w * x), 1 - 2 * (x * x + y * y)}};
    for (int a = 0; a < 3; ++a) {
      double d = 0;
      for (int b = 0; b < 3; ++b) d += R[a][b] * std::exp(static_cast<double>(g.log_scale[i * 3 + b])) * z[b];
      ASSERT_NEAR(out.mean[r * 3 + a], g.mean[i * 3 + a] + d, 2e-6) << "row " << r;
      ASSERT_NEAR(std::exp(static_cast<double>(out.log_scale[r * 3 + a])),
                  std::exp(static_cast<double>(g.log_scale[i * 3 + a])) / 1.6,
                  1e-6 * std::exp(static_cast<double>(g.log_scale[i * 3 + a])));
    }
  }
  // The draws are standard normal: moments over many (seed, iteration, row, sample).
  double m1 = 0, m2 = 0;
  const int draws = 20000;
  for (int d = 0; d < draws; ++d) {
    const std::array<double, 3> z = split_normal(5, d / 100, d % 100, d % 2);
    for (double v : z) m1 += v, m2 += v * v;
  }
  m1 /= 3 * draws;
  m2 /= 3 * draws;
  EXPECT_NEAR(m1, 0, 0.03);
  EXPECT_NEAR(m2, 1, 0.04);
}

TEST(FreeTrainer, InitialisationFromPointsIs3dgs) {
  // Four points on a line with spacing 1 and a fifth far away.
  std::vector<Eigen::Vector3d> p = {{0, 0, 0}, {1, 0, 0}, {2, 0, 0}, {3, 0, 0}, {0, 0, 10}};
  std::vector<Eigen::Vector3<uint8_t>> col(5, Eigen::Vector3<uint8_t>(255, 0, 128));
  const FreeGaussians g = FreeGaussians::from_points(p, col, 0.1f);
  ASSERT_EQ(g.size(), 5u);
  // Brute-force mean squared distance to the 3 nearest.
  for (size_t i = 0; i < p.size(); ++i) {
    std::vector<double> d;
    for (size_t j = 0; j < p.size(); ++j)
      if (j != i) d.push_back((p[i] - p[j]).squaredNorm());
    std::sort(d.begin(), d.end());
    const double want = std::log(std::sqrt((d[0] + d[1] + d[2]) / 3));
    for (int k = 0; k < 3; ++k) EXPECT_NEAR(g.log_scale[i * 3 + k], want, 1e-6) << i;
    EXPECT_EQ(g.quat[i * 4], 1.f);
    EXPECT_NEAR(1 / (1 + std::exp(-g.opacity_logit[i])), 0.1, 1e-6);
    EXPECT_NEAR(g.sh_dc[i * 3] * 0.28209479177387814 + 0.5, 1.0, 1e-6);
    EXPECT_NEAR(g.sh_dc[i * 3 + 1] * 0.28209479177387814 + 0.5, 0.0, 1e-6);
  }
  // A larger random cloud: the sweep agrees with brute force.
  std::mt19937 rng(4);
  std::uniform_real_distribution<double> u(-1, 1);
  std::vector<Eigen::Vector3d> q(300);
  for (auto& v : q) v = Eigen::Vector3d(u(rng), u(rng), 0.1 * u(rng));
  const FreeGaussians h = FreeGaussians::from_points(q, {}, 0.1f);
  for (size_t i = 0; i < q.size(); ++i) {
    std::vector<double> d;
    for (size_t j = 0; j < q.size(); ++j)
      if (j != i) d.push_back((q[i] - q[j]).squaredNorm());
    std::nth_element(d.begin(), d.begin() + 3, d.end());
    std::sort(d.begin(), d.begin() + 3);
    ASSERT_NEAR(h.log_scale[i * 3], std::log(std::sqrt((d[0] + d[1] + d[2]) / 3)), 1e-6) << i;
  }
}

// ------------------------------------------------------------------ device
TEST(FreeTrainer, DeviceStatisticsMatchTheRenderersGradients) {
  SceneOptions so;
  so.resolution = 4;
  auto scene = Scene::open(sample_scene(), so);
  FreeTrainConfig c;
  c.iterations = 10;
  c.densify_every = 0;
  FreeTrainer trainer(test::runtime(), *scene, c);
  const FreeGaussians g0 = trainer.download();
  const int view = trainer.view_for_iteration(0);
  FreeStepStats st = trainer.step();
  ASSERT_FALSE(st.skipped);
  ASSERT_EQ(st.view, view);
  const DensifyStats s = trainer.download_stats();

  // The same view rendered from the host with the initial parameters.
  GaussianSet set = g0.to_stored_set(0);
  for (float& x : set.scales) x = std::exp(x);
  for (float& x : set.opacities) x = 1 / (1 + std::exp(-x));
  Renderer renderer(test::runtime());
  const Camera& cam = scene->views()[view].camera;
  RenderOutput out = renderer.render(set, cam);
  ImageLoss loss(test::runtime());
  OutputGrads og;
  loss.forward_backward(out.rgb, scene->image(view)->rgb, out.width, out.height, kSsimLambda, &og.rgb);
  GaussianGrads gr = renderer.render_backward(og);
  int visible = 0;
  for (size_t i = 0; i < set.size(); ++i) {
    const bool vis = out.radii[i] > 0;
    visible += vis;
    ASSERT_EQ(s.count[i], vis ? 1 : 0) << i;
    ASSERT_EQ(s.max_radius[i], vis ? out.radii[i] : 0) << i;
    const double gx = gr.means2d[i * 2] * 0.5 * cam.width, gy = gr.means2d[i * 2 + 1] * 0.5 * cam.height;
    const double want = vis ? std::sqrt(gx * gx + gy * gy) : 0.0;
    ASSERT_NEAR(s.grad_sum[i], want, 1e-3 * want + 1e-10) << i;
  }
  EXPECT_GT(visible, 100);

  // An opacity reset caps every opacity at 0.01.
  FreeTrainConfig r = c;
  r.opacity_reset_every = 2;
  r.densify_until = 10;
  FreeTrainer t2(test::runtime(), *scene, r);
  t2.step();
  FreeStepStats st2 = t2.step();
  EXPECT_TRUE(st2.opacity_reset);
  for (float o : t2.download().opacity_logit) ASSERT_LE(1 / (1 + std::exp(-o)), 0.01 + 1e-6);
}

TEST(FreeTrainer, ShortRunRaisesPsnrAndDensifies) {
  SceneOptions so;
  so.resolution = 2;
  auto scene = Scene::open(sample_scene(), so);
  FreeTrainConfig c;
  c.iterations = 150;
  c.seed = 2;
  c.densify_from = 50;
  c.densify_every = 50;
  c.densify_until = 150;
  FreeTrainer trainer(test::runtime(), *scene, c);
  const size_t n0 = trainer.gaussians();
  EXPECT_EQ(n0, scene->points().size());
  const std::vector<int> train = scene->train_views();
  const EvalStats before = trainer.evaluate(train);
  int rounds = 0, added = 0;
  for (int it = 0; it < c.iterations; ++it) {
    FreeStepStats st = trainer.step();
    ASSERT_FALSE(st.skipped) << st.iteration;
    if (st.densified) {
      ++rounds;
      added += st.cloned + st.split;
    }
  }
  const EvalStats after = trainer.evaluate(train);
  std::printf("train PSNR %.2f -> %.2f dB; Gaussians %zu -> %zu (%d rounds, %d cloned or split)\n", before.psnr,
              after.psnr, n0, trainer.gaussians(), rounds, added);
  EXPECT_EQ(rounds, 3);
  EXPECT_GT(added, 0);
  EXPECT_NE(trainer.gaussians(), n0);
  EXPECT_GT(after.psnr, before.psnr + 2.0);
}

// ------------------------------------------------------------------ CLI
const std::string kDensify =
    "--densify-from 20 --densify-every 20 --densify-until 60 --opacity-reset-every 20 --log-every 0";

TEST(FreeTrainer, SameSeedGivesByteIdenticalPlyAcrossThreadCounts) {
  test::ScratchDir dir("baseline_det");
  const char* bin = std::getenv("AG2GS_BINARY");
  const std::string exe = bin ? bin : "./ag2gs";
  auto run = [&](int threads, int seed, const std::string& out) {
    const std::string cmd = "POCL_MAX_PTHREAD_COUNT=" + std::to_string(threads) + " " + exe + " baseline " +
                            sample_scene() + " -r 2 --iters 60 --seed " + std::to_string(seed) + " " + kDensify +
                            " -o " + dir.file(out) + " 2>&1";
    return std::system(cmd.c_str());
  };
  ASSERT_EQ(run(1, 5, "a"), 0);
  ASSERT_EQ(run(2, 5, "b"), 0);
  ASSERT_EQ(run(2, 6, "c"), 0);
  const std::string a = test::read_bytes(dir.file("a/point_cloud.ply"));
  ASSERT_FALSE(a.empty());
  EXPECT_TRUE(a == test::read_bytes(dir.file("b/point_cloud.ply"))) << "1 vs 2 PoCL threads";
  EXPECT_FALSE(a == test::read_bytes(dir.file("c/point_cloud.ply"))) << "another seed, the same file";
  // A standard 3DGS file: SH degree 3 after 60 iterations (one step every 15), no feature columns.
  const GaussianSet ply = read_ply(dir.file("a/point_cloud.ply"));
  EXPECT_EQ(ply.sh_degree, 3);
  EXPECT_GT(ply.size(), 0u);
  EXPECT_EQ(a.find("feat_0"), std::string::npos);
}

TEST(FreeTrainer, CliProgressEvalMetricsAndErrors) {
  test::ScratchDir dir("baseline_cli");
  test::CliResult r = test::run_cli("baseline " + sample_scene() +
                                    " -r 2 --iters 40 --eval --test-every 20 --log-every 20 --densify-from 20 "
                                    "--densify-every 20 -o " +
                                    dir.file("m"));
  ASSERT_EQ(r.code, 0) << r.output;
  for (const char* needle : {"PSNR", "Gaussians", "it/s", "ETA", "cloned", "[test] iteration 40"})
    EXPECT_NE(r.output.find(needle), std::string::npos) << needle << "\n" << r.output;
  std::ifstream f(dir.file("m/metrics.json"));
  ASSERT_TRUE(f) << r.output;
  const nlohmann::json m = nlohmann::json::parse(f);
  ASSERT_EQ(m["test"].size(), 2u) << m.dump();
  EXPECT_EQ(m["test"][0]["iteration"].get<int>(), 20);
  EXPECT_EQ(m["final"]["iteration"].get<int>(), 40);
  EXPECT_GT(m["final"]["psnr"].get<double>(), 5.0);
  EXPECT_EQ(m["test_views"].get<int>(), 2);
  EXPECT_EQ(m["gaussians"].get<size_t>(), read_ply(dir.file("m/point_cloud.ply")).size());

  // --test-views holds out the named image (implies --eval); --test-at adds evaluations.
  r = test::run_cli("baseline " + sample_scene() +
                    " -r 2 --iters 20 --test-views view_003 --test-at 10 --log-every 0 -o " + dir.file("named"));
  ASSERT_EQ(r.code, 0) << r.output;
  const nlohmann::json named = nlohmann::json::parse(std::ifstream(dir.file("named/metrics.json")));
  EXPECT_EQ(named["test_views"].get<int>(), 1);
  ASSERT_EQ(named["test"].size(), 2u) << named.dump();
  EXPECT_EQ(named["test"][0]["iteration"].get<int>(), 10);

  // An unwritable model folder fails before training.
  test::write_bytes(dir.file("file"), "not a folder");
  r = test::run_cli("baseline " + sample_scene() + " -r 2 --iters 5 -o " + dir.file("file/model"));
  EXPECT_EQ(r.code, 1) << r.output;
  EXPECT_NE(r.output.find("cannot be created"), std::string::npos) << r.output;
  EXPECT_EQ(r.output.find("iterations"), std::string::npos) << "training started: " << r.output;

  // A scene without points names the points file.
  const fs::path scene = dir.path() / "scene";
  fs::create_directories(scene / "sparse" / "0");
  fs::copy(fs::path(sample_scene()) / "images", scene / "images", fs::copy_options::recursive);
  for (const char* name : {"cameras.bin", "images.bin"})
    fs::copy_file(fs::path(sample_scene()) / "sparse/0" / name, scene / "sparse/0" / name);
  test::write_bytes((scene / "sparse/0/points3D.bin").string(), std::string(8, '\0'));
  r = test::run_cli("baseline " + scene.string() + " -r 2 --iters 5 -o " + dir.file("n"));
  EXPECT_EQ(r.code, 1) << r.output;
  EXPECT_NE(r.output.find("points3D"), std::string::npos) << r.output;
  EXPECT_FALSE(fs::exists(dir.file("n/point_cloud.ply")));
  SceneOptions so;
  so.resolution = 2;
  auto s = Scene::open(scene.string(), so);
  EXPECT_THROW(FreeTrainer(test::runtime(), *s, FreeTrainConfig{}), std::runtime_error);
}

}  // namespace
}  // namespace ag2gs
