// Training state over time (train/trainer.h, `ag2gs train`) on the synthetic
// sample scene at -r 2 (80x60): the 3DGS opacity reset, checkpoints and
// resume (a run split in two gives the bytes of the straight run), and
// Ctrl-C on `ag2gs train` (checkpoint, exit status 130, --resume finishes
// with the bytes of an uninterrupted run).
#include <gtest/gtest.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <random>

#include "host/io/model_io.h"
#include "host/io/model_ply.h"
#include "host/io/ply_io.h"
#include "host/scene/scene.h"
#include "synth/synth_scene.h"
#include "tests/cli_test_util.h"
#include "tests/io_test_util.h"
#include "tests/test_util.h"
#include "train/anchors/anchor_model.h"
#include "train/trainer.h"

namespace fs = std::filesystem;

namespace ag2gs {
namespace {

std::string sample_scene() {
  return test::source_path("data_samples/synth_small");
}

std::vector<float> download(DeviceBuffer& b, size_t n) {
  std::vector<float> v;
  b.download(v, n);
  return v;
}

bool all_zero(const std::vector<float>& v) {
  return std::all_of(v.begin(), v.end(), [](float x) { return x == 0.f; });
}

// Two runs that differ only in the reset: up to the reset iteration they are
// the same, so the run with the reset must hold exactly min(p, logit(0.01))
// of the other's opacities p, with zeroed opacity moments and the other
// groups untouched; no reset once growing has stopped.
TEST(TrainState, OpacityResetCapsOpacityAndZeroesItsMoments) {
  SceneOptions so;
  so.resolution = 2;
  auto scene = Scene::open(sample_scene(), so);
  TrainConfig cfg;
  cfg.iterations = 70;  // resets while growing runs: until iteration 46 (2/3)
  cfg.seed = 2;
  cfg.anchors.top_cells = 50;
  cfg.grow_every = 0;
  cfg.opacity_reset_every = 20;
  TrainConfig off = cfg;
  off.opacity_reset_every = 0;
  Trainer a(test::runtime(), *scene, cfg), b(test::runtime(), *scene, off);
  const float cap = std::log(0.01f / 0.99f);
  for (int it = 1; it <= cfg.iterations; ++it) {
    const StepStats sa = a.step(), sb = b.step();
    EXPECT_EQ(sa.opacity_reset, it == 20 || it == 40) << it;
    EXPECT_FALSE(sb.opacity_reset);
    if (it == 20) {
      const std::vector<float>& pa = a.model().opacity_logit();
      const std::vector<float>& pb = b.model().opacity_logit();
      ASSERT_EQ(pa.size(), pb.size());
      size_t capped = 0;
      for (size_t i = 0; i < pa.size(); ++i) {
        ASSERT_EQ(pa[i], std::min(pb[i], cap)) << i;
        capped += pb[i] > cap;
      }
      std::printf("reset at 20: %zu of %zu opacities capped\n", capped, pa.size());
      EXPECT_GT(capped, pa.size() / 2);
      AdamGroup& ga = a.adam_group("opacity");
      EXPECT_TRUE(all_zero(download(ga.exp_avg(), ga.size())));
      EXPECT_TRUE(all_zero(download(ga.exp_avg_sq(), ga.size())));
      EXPECT_EQ(ga.steps(), 20);
      AdamGroup& gb = b.adam_group("opacity");
      EXPECT_FALSE(all_zero(download(gb.exp_avg(), gb.size())));
      // Other parameters are not touched by the reset.
      EXPECT_TRUE(a.model().sh() == b.model().sh());
      EXPECT_FALSE(all_zero(download(a.adam_group("sh_dc").exp_avg(), a.adam_group("sh_dc").size())));
    }
  }
}

// A callback given to step() runs after the update and before the growing
// round and opacity reset of that iteration (where 3DGS evaluates): a test
// there sees the trained opacities. It changes nothing in the training.
TEST(TrainState, EvaluationBeforeTheResetOfItsIteration) {
  SceneOptions so;
  so.resolution = 2;
  so.eval = true;
  auto scene = Scene::open(sample_scene(), so);
  TrainConfig cfg;
  cfg.iterations = 45;
  cfg.seed = 2;
  cfg.anchors.top_cells = 50;
  cfg.grow_every = 0;
  cfg.opacity_reset_every = 20;
  Trainer a(test::runtime(), *scene, cfg), b(test::runtime(), *scene, cfg);
  const std::vector<int> tests = scene->test_views();
  EvalStats before{}, after{};
  for (int it = 1; it <= 25; ++it) {
    if (it == 20) {
      bool called = false;
      const StepStats st = a.step(false, [&] {
        called = true;
        before = a.evaluate(tests);
      });
      EXPECT_TRUE(called);
      EXPECT_TRUE(st.opacity_reset);
      after = a.evaluate(tests);
    } else {
      a.step();
    }
    b.step();
  }
  std::printf("test PSNR at the reset iteration: %.3f dB before the reset, %.3f dB after\n", before.psnr, after.psnr);
  EXPECT_GT(before.psnr, after.psnr + 1.0);
  EXPECT_TRUE(a.model().opacity_logit() == b.model().opacity_logit());
  EXPECT_TRUE(a.model().sh() == b.model().sh());
}

// Growing rounds at 25 and 50, opacity resets at 30 and 60: the split at 40
// lies between a round and the next (whose statistics then span both
// halves) and between two resets.
TrainConfig split_config() {
  TrainConfig cfg;
  cfg.iterations = 80;
  cfg.seed = 4;
  cfg.anchors.top_cells = 50;
  cfg.grow_from = 25;
  cfg.grow_every = 25;
  cfg.grow_until = 70;
  cfg.grow_threshold = 1e-3;
  cfg.opacity_reset_every = 30;
  cfg.opacity_reset_pause = 10;
  cfg.mask_from = 10;
  return cfg;
}

// Trains cfg straight and split in two at iteration 40 (checkpoint, resume)
// and expects the same model files; returns the children recycled.
int expect_resume_gives_straight_bytes(const TrainConfig& cfg, const std::string& name,
                                       const std::string& scene_dir = sample_scene()) {
  SceneOptions so;
  so.resolution = 2;
  auto scene = Scene::open(scene_dir, so);
  test::ScratchDir dir(name);
  int grown = 0, resets = 0, recycled = 0;
  {
    Trainer straight(test::runtime(), *scene, cfg);
    for (int it = 0; it < cfg.iterations; ++it) {
      const StepStats st = straight.step();
      grown += st.grown;
      resets += st.opacity_reset;
      recycled += st.recycled;
    }
    straight.save(dir.file("straight"));
  }
  EXPECT_GT(grown, 0);
  EXPECT_EQ(resets, 2);
  {
    Trainer first(test::runtime(), *scene, cfg);
    for (int it = 0; it < cfg.iterations / 2; ++it) first.step();
    first.save(dir.file("split"));
  }
  // What the split left is a complete model: the PLY reads back as the
  // checkpoint's Gaussians.
  {
    ModelArchive ck = read_model_archive(dir.file("split/checkpoint.ag2gs"));
    EXPECT_EQ(ck.meta["checkpoint"]["iteration"].get<int>(), 40);
    const AnchorModel m = AnchorModel::from_archive(ck);
    // (point_cloud.ply also holds the baked sky when the model has one.)
    EXPECT_EQ(read_ply(model_objects_ply(dir.file("split"))).size(), m.gaussians());
  }
  {
    Trainer second(test::runtime(), *scene, cfg);
    second.resume(dir.file("split"));
    EXPECT_EQ(second.iteration(), 40);
    for (int it = second.iteration(); it < cfg.iterations; ++it) second.step();
    second.save(dir.file("split"));
  }
  test::expect_same_model_files(dir.file("straight"), dir.file("split"), "the straight and the resumed run");
  return recycled;
}

TEST(TrainState, ResumedRunGivesTheBytesOfTheStraightRun) {
  EXPECT_EQ(expect_resume_gives_straight_bytes(split_config(), "train_resume"), 0);
}

// The same with the switches against the gap to free Gaussians: recycling in
// the growing rounds, a scale cap on the top layer, children on the SfM points,
// the final prune after the last iteration (in the resumed half), and split
// growth, the importance prune.
TEST(TrainState, ResumeIsBitExactWithRecyclingAndAScaleCap) {
  TrainConfig cfg = split_config();
  cfg.recycle_opacity = 0.05;
  cfg.final_prune_opacity = 0.1;
  cfg.anchors.scale_cap = 8.f;
  cfg.anchors.scale_cap_layers = 1;
  cfg.anchors.init_children_at_points = true;
  cfg.grow_split = 2;
  cfg.prune_importance = 0.02;  // at iteration 75 (growing ends at 70), in the resumed half
  EXPECT_GT(expect_resume_gives_straight_bytes(cfg, "train_resume_switches"), 0);
  EXPECT_EQ(cfg.effective_prune_importance_at(), 75);
  // The importance prune goes through the checkpoint; files from before it mean off.
  EXPECT_EQ(TrainConfig::from_json(cfg.to_json()).prune_importance, 0.02);
  EXPECT_EQ(TrainConfig::from_json(cfg.to_json()).prune_importance_at, 75);
  // Split growth goes through the checkpoint; files from before it mean off.
  EXPECT_EQ(TrainConfig::from_json(cfg.to_json()).grow_split, 2.0);
  nlohmann::json old = cfg.to_json();
  old["grow"].erase("split");
  old.erase("prune_importance");
  EXPECT_EQ(TrainConfig::from_json(old).grow_split, 0.0);
  EXPECT_EQ(TrainConfig::from_json(old).prune_importance, 0.0);
}

// The same with a sky (forced: the sample's open share is below the rule's
// 5%): its coefficients and Adam moments go through the checkpoint.
TEST(TrainState, ResumeIsBitExactWithASky) {
  TrainConfig cfg = split_config();
  cfg.sky_degree = 3;
  expect_resume_gives_straight_bytes(cfg, "train_resume_sky");
  SceneOptions so;
  so.resolution = 2;
  auto scene = Scene::open(sample_scene(), so);
  Trainer t(test::runtime(), *scene, cfg);
  EXPECT_EQ(t.config().sky_degree, 3);
  EXPECT_EQ(t.sky().size(), 48u);
  EXPECT_EQ(t.adam_group("sky").rows(), 16u);
}

// The same with the far shell, on a generated room whose wall has no SfM
// points: the shell's anchors come from the scene again on resume.
TEST(TrainState, ResumeIsBitExactWithTheFarShell) {
  test::ScratchDir dir("train_resume_shell_scene");
  SynthOptions o;
  o.width = 64;
  o.height = 48;
  o.views = 12;
  o.seed = 2;
  o.feature_dim = 84;
  o.wall_points = false;
  write_synth_scene(dir.file("scene"), o);
  TrainConfig cfg = split_config();
  cfg.far_shell = true;
  expect_resume_gives_straight_bytes(cfg, "train_resume_shell", dir.file("scene"));
  SceneOptions so;
  so.resolution = 2;
  auto scene = Scene::open(dir.file("scene"), so);
  Trainer with(test::runtime(), *scene, cfg);
  cfg.far_shell = false;
  Trainer without(test::runtime(), *scene, cfg);
  EXPECT_GT(with.model().size(), without.model().size() + 20) << "the shell seeded anchors";
  EXPECT_EQ(with.config().sky_degree, 3);
  EXPECT_TRUE(TrainConfig::from_json(with.config().to_json()).far_shell);
  nlohmann::json old = with.config().to_json();
  old.erase("far_shell");
  EXPECT_FALSE(TrainConfig::from_json(old).far_shell) << "files from before the shell mean none";
}

TEST(TrainState, ResumeRefusesAnotherConfigOrScene) {
  SceneOptions so;
  so.resolution = 2;
  auto scene = Scene::open(sample_scene(), so);
  TrainConfig cfg = split_config();
  cfg.iterations = 4;
  cfg.grow_every = 0;
  test::ScratchDir dir("train_resume_bad");
  {
    Trainer t(test::runtime(), *scene, cfg);
    t.step();
    t.save(dir.file("m"));
  }
  auto expect_error = [&](Scene& s, const TrainConfig& c, const std::string& dir_name, const std::string& want) {
    Trainer t(test::runtime(), s, c);
    try {
      t.resume(dir.file(dir_name));
      ADD_FAILURE() << "resume accepted: expected an error with '" << want << "'";
    } catch (const std::runtime_error& e) {
      EXPECT_NE(std::string(e.what()).find(want), std::string::npos) << e.what();
      EXPECT_NE(std::string(e.what()).find("checkpoint"), std::string::npos) << e.what();
    }
    EXPECT_EQ(t.iteration(), 0);
  };
  TrainConfig other_seed = cfg;
  other_seed.seed = 5;
  expect_error(*scene, other_seed, "m", "seed");
  TrainConfig other_lr = cfg;
  other_lr.opacity_lr = 0.02;
  expect_error(*scene, other_lr, "m", "opacity_lr");
  SceneOptions so4 = so;
  so4.resolution = 4;
  auto scene4 = Scene::open(sample_scene(), so4);
  expect_error(*scene4, cfg, "m", "another scene");
  expect_error(*scene, cfg, "missing", "no checkpoint");
  // The library accepts the right one.
  Trainer ok(test::runtime(), *scene, cfg);
  ok.resume(dir.file("m"));
  EXPECT_EQ(ok.iteration(), 1);
}

// test::run_cli_interrupted_when, once a progress line of iteration >=
// `after` has appeared ("info: it      7/120  loss ...").
test::CliResult run_cli_interrupted(const std::string& args, int after, int sig = SIGINT, int times = 1) {
  return test::run_cli_interrupted_when(
      args,
      [after](const std::string& line) {
        const size_t at = line.find(" it ");
        return at != std::string::npos && std::atoi(line.c_str() + at + 4) >= after;
      },
      sig, times);
}

// `timeout T ag2gs train` signals the process and its group, so one SIGTERM
// can arrive twice back to back: it is one request (saved, exit 143), not
// "second signal: aborting without saving" (issue 42, 3 runs in 20).
TEST(TrainState, ASigtermDeliveredTwiceAtOnceStillSaves) {
  test::ScratchDir dir("train_sigterm_twice");
  const test::CliResult cut = run_cli_interrupted(
      "train " + sample_scene() + " -r 2 --iters 200 --stages 1 --seed 5 --log-every 1 -o " + dir.file("cut"), 5,
      SIGTERM, 2);
  ASSERT_EQ(cut.code, 143) << cut.output;
  EXPECT_EQ(cut.output.find("aborting without saving"), std::string::npos) << cut.output;
  EXPECT_NE(cut.output.find("--resume"), std::string::npos) << cut.output;
  EXPECT_TRUE(std::filesystem::exists(dir.file("cut/checkpoint.ag2gs")));
}

// A signal before the first iteration stops the run with nothing written; one
// during stage 3 lets it finish (its model file is written whole) and the run
// exits with the signal's status (issue 42: stage 3 exited 0, and a signal in
// the first moments met the default handler).
TEST(TrainState, SignalsBeforeTrainingAndInStageThreeExitWithTheirStatus) {
  test::ScratchDir dir("train_signal_edges");
  const auto early = test::run_cli_interrupted_when(
      "train " + sample_scene() + " -r 4 --iters 20 --seed 5 -o " + dir.file("early"),
      [](const std::string& line) { return line.find("checked the") != std::string::npos; }, SIGTERM);
  EXPECT_EQ(early.code, 143) << early.output;
  EXPECT_NE(early.output.find("before training started"), std::string::npos) << early.output;
  EXPECT_FALSE(std::filesystem::exists(dir.file("early/model.ag2gs"))) << early.output;
  EXPECT_FALSE(std::filesystem::exists(dir.file("early/checkpoint.ag2gs"))) << early.output;

  const auto late = test::run_cli_interrupted_when(
      "train " + sample_scene() + " -r 4 --iters 20 --prop-iters 4 --seed 5 -o " + dir.file("late"),
      [](const std::string& line) { return line.find("point_cloud.ply (") != std::string::npos; }, SIGTERM);
  EXPECT_EQ(late.code, 143) << late.output;
  EXPECT_NE(late.output.find("during the last stage"), std::string::npos) << late.output;
  const ModelArchive m = read_model_archive(dir.file("late/model.ag2gs"));
  EXPECT_TRUE(m.meta.contains("clusters")) << "stage 3 finished before the exit";
}

// train --force over a trained model, stopped after its first checkpoint:
// the old metrics.json does not stay beside the new model files (issue 42).
TEST(TrainState, ForcedRunStoppedMidwayLeavesNoStaleMetrics) {
  test::ScratchDir dir("train_force_metrics");
  const std::string run = "train " + sample_scene() + " -r 4 --stages 1 --seed 5 --log-every 1 -o " + dir.file("m");
  ASSERT_EQ(test::run_cli(run + " --iters 4").code, 0);
  ASSERT_TRUE(std::filesystem::exists(dir.file("m/metrics.json")));
  const test::CliResult cut = run_cli_interrupted(run + " --iters 200 --force --save-every 3", 5, SIGTERM);
  ASSERT_EQ(cut.code, 143) << cut.output;
  EXPECT_TRUE(std::filesystem::exists(dir.file("m/checkpoint.ag2gs")));
  EXPECT_FALSE(std::filesystem::exists(dir.file("m/metrics.json"))) << cut.output;
  // Finished, the run writes its own.
  ASSERT_EQ(test::run_cli(run + " --resume").code, 0);
  EXPECT_TRUE(std::filesystem::exists(dir.file("m/metrics.json")));
}

TEST(TrainState, CtrlCSavesACheckpointThatResumesToTheSameBytes) {
  test::ScratchDir dir("train_sigint");
  const std::string scene = sample_scene();
  const std::string args = "train " + scene +
                           " -r 2 --top-cells 50 --iters 120 --seed 9 --log-every 1 --grow-from 20 --grow-every 20 "
                           "--grow-threshold 1e-3 --opacity-reset-every 30 -o ";
  const test::CliResult straight = test::run_cli(args + dir.file("straight"));
  ASSERT_EQ(straight.code, 0) << straight.output;

  const test::CliResult cut = run_cli_interrupted(args + dir.file("cut"), 5);
  ASSERT_EQ(cut.code, 130) << cut.output;
  EXPECT_NE(cut.output.find("--resume"), std::string::npos) << cut.output;
  const ModelArchive ck = read_model_archive(dir.file("cut/checkpoint.ag2gs"));
  const int at = ck.meta["checkpoint"]["iteration"].get<int>();
  std::printf("interrupted at iteration %d of 120\n", at);
  EXPECT_GE(at, 5);
  EXPECT_LT(at, 120) << "the run finished before the interrupt: make it longer";
  EXPECT_EQ(read_ply(model_objects_ply(dir.file("cut"))).size(), AnchorModel::from_archive(ck).gaussians());

  const test::CliResult resumed =
      test::run_cli("train " + scene + " -o " + dir.file("cut") + " --resume --log-every 0");
  ASSERT_EQ(resumed.code, 0) << resumed.output;
  EXPECT_NE(resumed.output.find("resuming"), std::string::npos) << resumed.output;
  test::expect_same_model_files(dir.file("straight"), dir.file("cut"),
                                "the uninterrupted and the interrupted + resumed run");
}

// The command the run printed after "continue with".
std::string printed_resume_command(const std::string& output) {
  const size_t at = output.find("continue with\n");
  if (at == std::string::npos) return "";
  const size_t start = output.find("ag2gs ", at);
  const size_t end = output.find('\n', start);
  return start == std::string::npos ? "" : output.substr(start + 6, end - start - 6);
}

// SIGTERM (job schedulers, `docker stop`, `timeout`) at an iteration drawn
// at random: exit 143 with a checkpoint, and the printed command alone, run
// as printed, gives the bytes of the uninterrupted run, stages included.
TEST(TrainState, SigtermAtARandomIterationResumesToTheSameBytesWithItsStages) {
  test::ScratchDir dir("train_sigterm");
  const std::string scene = sample_scene();
  const std::string args = "train " + scene +
                           " -r 2 --iters 90 --stages 1 --seed 5 --log-every 1 --grow-from 20 --grow-every 20 "
                           "--grow-threshold 1e-3 -o ";
  const test::CliResult straight = test::run_cli(args + dir.file("straight"));
  ASSERT_EQ(straight.code, 0) << straight.output;

  std::random_device entropy;
  const int after = 3 + static_cast<int>(entropy() % 60);
  std::printf("SIGTERM after iteration %d of 90\n", after);
  const test::CliResult cut = run_cli_interrupted(args + dir.file("cut"), after, SIGTERM);
  ASSERT_EQ(cut.code, 143) << cut.output;
  EXPECT_NE(cut.output.find("SIGTERM: checkpoint at iteration"), std::string::npos) << cut.output;
  const std::string resume = printed_resume_command(cut.output);
  ASSERT_NE(resume.find("--resume"), std::string::npos) << cut.output;
  EXPECT_EQ(resume.find("--stages"), std::string::npos) << "the checkpoint should hold the stages: " << resume;
  const ModelArchive ck = read_model_archive(dir.file("cut/checkpoint.ag2gs"));
  EXPECT_EQ(ck.meta["checkpoint"]["run"]["stages"], nlohmann::json::array({1}));
  EXPECT_LT(ck.meta["checkpoint"]["iteration"].get<int>(), 90);

  const test::CliResult resumed = test::run_cli(resume + " --log-every 0");
  ASSERT_EQ(resumed.code, 0) << resumed.output;
  EXPECT_EQ(resumed.output.find("stage 2: "), std::string::npos) << "stage 2 ran on resume: " << resumed.output;
  EXPECT_EQ(resumed.output.find("stage 3"), std::string::npos) << "stage 3 ran on resume: " << resumed.output;
  test::expect_same_model_files(dir.file("straight"), dir.file("cut"),
                                "the uninterrupted and the SIGTERM + resumed run");
}

TEST(TrainState, SighupSavesACheckpointAndTheBaselineKeepsItsModelOnSigterm) {
  test::ScratchDir dir("train_sighup");
  const std::string scene = sample_scene();
  const test::CliResult hup =
      run_cli_interrupted("train " + scene + " -r 4 --iters 400 --log-every 1 -o " + dir.file("hup"), 3, SIGHUP);
  EXPECT_EQ(hup.code, 129) << hup.output;
  EXPECT_TRUE(fs::exists(dir.file("hup/checkpoint.ag2gs"))) << hup.output;
  const test::CliResult base =
      run_cli_interrupted("baseline " + scene + " -r 4 --iters 400 --log-every 1 -o " + dir.file("base"), 3, SIGTERM);
  EXPECT_EQ(base.code, 143) << base.output;
  EXPECT_TRUE(fs::exists(dir.file("base/point_cloud.ply"))) << base.output;
  EXPECT_NE(base.output.find("the model so far"), std::string::npos) << base.output;
}

}  // namespace
}  // namespace ag2gs
