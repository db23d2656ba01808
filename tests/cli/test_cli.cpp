// The ag2gs program as scripts use it: render's output paths, exit codes and
// error messages that name the file and the fix.
#include <gtest/gtest.h>

#include <array>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <opencv2/imgcodecs.hpp>

#include "host/io/model_io.h"
#include "host/io/model_ply.h"
#include "tests/cli_test_util.h"

namespace fs = std::filesystem;

namespace {

using Result = ag2gs::test::CliResult;
inline Result run(const std::string& args) {
  return ag2gs::test::run_cli(args);
}

std::string src() {
  const char* s = std::getenv("AG2GS_SOURCE_DIR");
  return s ? s : ".";
}

fs::path temp(const std::string& name) {
  fs::path d = fs::path(testing::TempDir()) / ("ag2gs_cli_" + name + "_" + std::to_string(::getpid()));
  fs::remove_all(d);
  return d;
}

TEST(Cli, DevicesListsTheDefault) {
  Result r = run("devices");
  EXPECT_EQ(r.code, 0) << r.output;
  EXPECT_NE(r.output.find("(default"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("fp64"), std::string::npos) << r.output;
}

TEST(Cli, RenderWritesOnePngPerViewAtTheCameraResolution) {
  fs::path out = temp("render");
  std::string scene = src() + "/data_samples/tiny_scene";
  Result r = run("render --ply " + scene + "/gaussians.ply --scene " + scene + " -o " + out.string());
  ASSERT_EQ(r.code, 0) << r.output;
  for (int i = 0; i < 4; ++i) {
    fs::path f = out / "rgb" / ("view_00" + std::to_string(i) + ".png");
    ASSERT_TRUE(fs::exists(f)) << f;
    cv::Mat img = cv::imread(f.string());
    EXPECT_EQ(img.cols, 160);
    EXPECT_EQ(img.rows, 120);
    EXPECT_GT(cv::countNonZero(img.reshape(1)), 100) << "the blobs should be visible";
  }
  // -r 2, --views by stem, a background colour, extras.
  fs::path out2 = temp("render2");
  r = run("render --ply " + scene + "/gaussians.ply --scene " + scene + " -o " + out2.string() +
          " --views view_001,view_003.png -r 2 --bg 1,1,1 --extras");
  ASSERT_EQ(r.code, 0) << r.output;
  cv::Mat img = cv::imread((out2 / "rgb" / "view_001.png").string());
  EXPECT_EQ(img.cols, 80);
  EXPECT_EQ(img.rows, 60);
  EXPECT_EQ(img.at<cv::Vec3b>(0, 0), cv::Vec3b(255, 255, 255)) << "white background in the corner";
  EXPECT_FALSE(fs::exists(out2 / "rgb" / "view_000.png"));
  EXPECT_TRUE(fs::exists(out2 / "depth" / "view_003.png"));
  EXPECT_TRUE(fs::exists(out2 / "alpha" / "view_003.png"));
  // A rerun with other settings into the same folder is refused and leaves
  // the earlier renders as they were; --force replaces them.
  const std::string before = ag2gs::test::read_file((out2 / "rgb" / "view_001.png").string());
  r = run("render --ply " + scene + "/gaussians.ply --scene " + scene + " -o " + out2.string() + " --views view_001");
  EXPECT_NE(r.code, 0) << r.output;
  EXPECT_NE(r.output.find("rgb/view_001.png"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("--force"), std::string::npos) << r.output;
  EXPECT_EQ(ag2gs::test::read_file((out2 / "rgb" / "view_001.png").string()), before);
  r = run("render --ply " + scene + "/gaussians.ply --scene " + scene + " -o " + out2.string() +
          " --views view_001 --force");
  ASSERT_EQ(r.code, 0) << r.output;
  EXPECT_NE(ag2gs::test::read_file((out2 / "rgb" / "view_001.png").string()), before)
      << "-r 1 and a black background now";
  fs::remove_all(out);
  fs::remove_all(out2);
}

TEST(Cli, BadInputGivesAClearErrorAndNonZeroExit) {
  std::string scene = src() + "/data_samples/tiny_scene";
  fs::path dir = temp("bad");
  fs::create_directories(dir);
  std::ofstream(dir / "junk.ply") << "this is not a ply\n";
  Result r = run("render --ply " + (dir / "junk.ply").string() + " --scene " + scene + " -o " + (dir / "o").string());
  EXPECT_NE(r.code, 0);
  EXPECT_NE(r.output.find("junk.ply"), std::string::npos) << r.output;

  r = run("render --ply " + scene + "/gaussians.ply --scene " + dir.string() + " -o " + (dir / "o").string());
  EXPECT_NE(r.code, 0);
  EXPECT_NE(r.output.find("sparse"), std::string::npos) << r.output;

  r = run("render --ply " + scene + "/gaussians.ply --scene " + scene + " -o " + (dir / "o").string() +
          " --views no_such_view");
  EXPECT_NE(r.code, 0);
  EXPECT_NE(r.output.find("no_such_view"), std::string::npos) << r.output;

  r = run("render --ply " + scene + "/gaussians.ply --scene " + scene + " -o " + (dir / "o").string() + " --bg 1,x,1");
  EXPECT_NE(r.code, 0);
  EXPECT_NE(r.output.find("--bg"), std::string::npos) << r.output;
  // Colours outside [0,1], NaN or a fourth number (issue 42: accepted).
  for (const char* bg : {"2,2,2", "nan,0,0", "1,1,1,1", "-0.5,0,0"}) {
    r = run("render --ply " + scene + "/gaussians.ply --scene " + scene + " -o " + (dir / "o").string() + " --bg " +
            bg);
    EXPECT_EQ(r.code, 1) << bg;
    EXPECT_NE(r.output.find("--bg '" + std::string(bg) + "'"), std::string::npos) << r.output;
    EXPECT_FALSE(fs::exists(dir / "o")) << bg;
  }
  // -r 0 meant "the default" in render, query and view (issue 42): refused.
  r = run("render --ply " + scene + "/gaussians.ply --scene " + scene + " -o " + (dir / "o").string() + " -r 0");
  EXPECT_NE(r.code, 0);
  EXPECT_NE(r.output.find("--resolution: Value 0 not in range 1 to 64"), std::string::npos) << r.output;
  EXPECT_FALSE(fs::exists(dir / "o"));
  // -o '' wrote into the current folder (issue 42): refused, naming the flag.
  r = run("render --ply " + scene + "/gaussians.ply --scene " + scene + " -o ''");
  EXPECT_NE(r.code, 0);
  EXPECT_NE(r.output.find("--out: must name a file or folder"), std::string::npos) << r.output;
  // A mistyped command names the nearest (issue 42: "A subcommand is required").
  r = run("trian " + scene + " -o " + (dir / "o").string());
  EXPECT_EQ(r.code, 2);
  EXPECT_NE(r.output.find("unknown command 'trian'; did you mean 'train'?"), std::string::npos) << r.output;
  r = run("--device 0 rendr");
  EXPECT_NE(r.output.find("did you mean 'render'?"), std::string::npos) << r.output;
  // Learning rates and loss weights out of range are refused naming the flag
  // (issue 42: --w-dist 1e30 wrote Inf into Adam's state; --lr-sh -1 named
  // an internal field).
  for (const std::string& flag :
       {"--w-dist 1e30", "--w-prop 1e30", "--w-is 1e7", "--lr-sh -1", "--lr-offset nan", "--grow-threshold 0"}) {
    r = run("train " + src() + "/data_samples/synth_small -o " + (dir / "t").string() + " --iters 1 " + flag);
    EXPECT_NE(r.code, 0) << flag;
    EXPECT_NE(r.output.find(flag.substr(0, flag.find(' ')) + ": must be a number in"), std::string::npos)
        << flag << ": " << r.output;
    EXPECT_FALSE(fs::exists(dir / "t")) << flag;
  }
  r = run("xyzzyplugh");
  EXPECT_EQ(r.code, 2);
  EXPECT_EQ(r.output.find("did you mean"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("The commands: "), std::string::npos) << r.output;

  r = run("--device 99 devices");
  EXPECT_NE(r.code, 0);
  r = run("devices --device 99");  // global options may follow the subcommand
  EXPECT_NE(r.code, 0);
  EXPECT_NE(r.output.find("ag2gs devices"), std::string::npos) << r.output;

  r = run("render --scene " + scene);  // missing required options
  EXPECT_NE(r.code, 0);
  fs::remove_all(dir);
}

}  // namespace

TEST(Cli, RenderModelFolderWithViewSetsAndOutputs) {
  const std::string scene = src() + "/data_samples/tiny_scene";
  fs::path dir = temp("model");
  fs::create_directories(dir / "model");
  fs::copy_file(scene + "/gaussians.ply", dir / "model" / "point_cloud.ply");
  // 4 views: test = every 8th in name order = view_000 only.
  Result r = run("render " + (dir / "model").string() + " --scene " + scene + " -o " + (dir / "o").string() +
                 " --views test --outputs rgb,depth,alpha,feature");
  ASSERT_EQ(r.code, 0) << r.output;
  EXPECT_NE(r.output.find("views/s"), std::string::npos) << r.output;
  for (const char* o : {"rgb", "depth", "alpha", "feature"}) {
    EXPECT_TRUE(fs::exists(dir / "o" / o / "view_000.png")) << o;
    EXPECT_FALSE(fs::exists(dir / "o" / o / "view_001.png")) << o;
  }
  for (const char* o : {"depth", "alpha", "feature"}) EXPECT_TRUE(fs::exists(dir / "o" / o / "view_000.npy")) << o;
  EXPECT_FALSE(fs::exists(dir / "o" / "rgb" / "view_000.npy"));
  r = run("render " + (dir / "model").string() + " --scene " + scene + " -o " + (dir / "t").string() +
          " --views train");
  ASSERT_EQ(r.code, 0) << r.output;
  EXPECT_FALSE(fs::exists(dir / "t" / "rgb" / "view_000.png"));
  EXPECT_TRUE(fs::exists(dir / "t" / "rgb" / "view_003.png"));
  EXPECT_FALSE(fs::exists(dir / "t" / "depth"));
  // Errors: unknown output, a folder that is not a model, both sources.
  r = run("render " + (dir / "model").string() + " --scene " + scene + " -o " + (dir / "x").string() +
          " --outputs rgb,normals");
  EXPECT_EQ(r.code, 1);
  EXPECT_NE(r.output.find("unknown output 'normals'"), std::string::npos) << r.output;
  r = run("render " + dir.string() + " --scene " + scene + " -o " + (dir / "x").string());
  EXPECT_EQ(r.code, 1);
  EXPECT_NE(r.output.find("no point_cloud.ply"), std::string::npos) << r.output;
  r = run("render " + (dir / "model").string() + " --ply " + scene + "/gaussians.ply --scene " + scene + " -o " +
          (dir / "x").string());
  EXPECT_EQ(r.code, 1);
  EXPECT_NE(r.output.find("not both"), std::string::npos) << r.output;
  fs::remove_all(dir);
}

// A model folder's point_cloud.ply must be its model.ag2gs's: one copied in
// from another model (same scene, another seed: as many Gaussians,
// elsewhere) or another file altogether is refused, naming the file and the
// way out; rendered alone with --ply it still renders.
TEST(Cli, RenderRefusesAModelFoldersPlyFromAnotherModel) {
  const std::string scene = src() + "/data_samples/synth_small";
  fs::path dir = temp("ply_of_another");
  for (const char* seed : {"1", "2"}) {
    Result t = run("train " + scene + " -o " + (dir / seed).string() +
                   " -r 2 --top-cells 50 --iters 3 --stages 1 --log-every 0 --seed " + seed);
    ASSERT_EQ(t.code, 0) << t.output;
  }
  const std::string a = (dir / "1").string();
  Result r = run("render " + a + " --scene " + scene + " -o " + (dir / "ok").string());
  ASSERT_EQ(r.code, 0) << r.output;
  // The file render reads: point_cloud_objects.ply when the model has a sky.
  const std::string target = ag2gs::model_objects_ply(a);
  fs::copy_file(ag2gs::model_objects_ply((dir / "2").string()), target, fs::copy_options::overwrite_existing);
  r = run("render " + a + " --scene " + scene + " -o " + (dir / "x").string());
  EXPECT_EQ(r.code, 1);
  EXPECT_NE(r.output.find(".ply: Gaussian "), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("not written from this model"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("--ply"), std::string::npos) << r.output;
  EXPECT_FALSE(fs::exists(dir / "x"));
  fs::copy_file(src() + "/data_samples/tiny_scene/gaussians.ply", target, fs::copy_options::overwrite_existing);
  r = run("render " + a + " --scene " + scene + " -o " + (dir / "x").string());
  EXPECT_EQ(r.code, 1);
  EXPECT_NE(r.output.find("Gaussians where"), std::string::npos) << r.output;
  r = run("render --ply " + target + " --scene " + scene + " -o " + (dir / "alone").string());
  EXPECT_EQ(r.code, 0) << r.output;
  fs::remove_all(dir);
}

// --init-layer picks the voxel layer the SfM points seed: the top layer by
// default, every layer with -1 (the log line "per layer a/b/c"); a layer the
// grid does not have is refused before training.
// --preset appearance sets its switches (they reach the saved model), and a
// flag given explicitly wins over the preset.
TEST(Cli, TrainPresetsDefaultAppearanceAndPaperExplicitFlagsWin) {
  const std::string scene = src() + "/data_samples/synth_small";
  const fs::path dir = temp("preset");
  const std::string common = "train " + scene + " -r 2 --iters 2 --stages 1 --top-cells 50 --log-every 0 -o ";
  auto config_of = [](const fs::path& model) {
    const ag2gs::ModelArchive ar = ag2gs::read_model_archive((model / "model.ag2gs").string());
    return ar.meta.at("anchors").at("config");
  };
  // The default is the appearance setting.
  Result def = run(common + (dir / "default").string());
  ASSERT_EQ(def.code, 0) << def.output;
  // The log line names every setting a preset sets, with the values used.
  auto logged = [](const Result& r, const std::string& preset, const std::vector<std::string>& settings) {
    const size_t at = r.output.find("preset " + preset + ":");
    ASSERT_NE(at, std::string::npos) << r.output;
    const std::string line = r.output.substr(at, r.output.find('\n', at) - at) + " ";
    for (const std::string& s : settings) EXPECT_NE(line.find(" " + s + " "), std::string::npos) << s << " in " << line;
  };
  logged(def, "default", {"--scale-cap 64", "--children 2", "--init-layers 2", "--init-children-at-points"});
  EXPECT_EQ(config_of(dir / "default").at("scale_cap").get<float>(), 64.f);
  EXPECT_EQ(config_of(dir / "default").at("children").get<int>(), 2);
  EXPECT_EQ(config_of(dir / "default").at("init_layers").get<int>(), 2);
  EXPECT_TRUE(config_of(dir / "default").at("init_children_at_points").get<bool>());

  // --preset paper: the method as published; the explicit --top-cells wins.
  Result paper = run(common + (dir / "paper").string() + " --preset paper");
  ASSERT_EQ(paper.code, 0) << paper.output;
  logged(paper, "paper",
         {"--top-cells 50", "--children 5", "--init-layers 1", "--scale-cap 1", "--grow-budget 0", "--max-gaussians 0",
          "--sky-degree -1", "--downscales 0", "--init-children-random", "--far-shell false"});
  EXPECT_EQ(config_of(dir / "paper").at("scale_cap").get<float>(), 1.f);
  EXPECT_EQ(config_of(dir / "paper").at("children").get<int>(), 5);
  EXPECT_EQ(config_of(dir / "paper").at("init_layers").get<int>(), 1);
  EXPECT_EQ(config_of(dir / "paper").at("top_cells").get<int>(), 50);
  Result paper200 = run("train " + scene + " -r 2 --iters 1 --stages 1 --log-every 0 --preset paper -o " +
                        (dir / "paper200").string());
  ASSERT_EQ(paper200.code, 0) << paper200.output;
  EXPECT_EQ(config_of(dir / "paper200").at("top_cells").get<int>(), 200);

  Result app = run(common + (dir / "app").string() + " --preset appearance --children 4");
  ASSERT_EQ(app.code, 0) << app.output;
  logged(app, "appearance",
         {"--scale-cap 64", "--children 4", "--init-layers 2", "--init-children-at-points", "--grow-budget 0.1",
          "--grow-min-seen 0.1", "--grow-split 4", "--far-shell true", "--recycle-opacity 0.02",
          "--final-prune-opacity 0.015", "--prune-importance 0.01", "--lr-offset 0.01", "--lr-scaling 0.01"});
  const auto c = config_of(dir / "app");
  EXPECT_EQ(c.at("scale_cap").get<float>(), 64.f);
  EXPECT_EQ(c.at("children").get<int>(), 4);
  EXPECT_TRUE(c.at("init_children_at_points").get<bool>());

  Result bad = run(common + (dir / "bad").string() + " --preset fast");
  EXPECT_NE(bad.code, 0);
  EXPECT_NE(bad.output.find("--preset"), std::string::npos) << bad.output;
  fs::remove_all(dir);
}

// --sparse names the model folder for train and baseline too (the scene-folder
// rule's error suggests it); without it such a scene is refused naming --sparse.
TEST(Cli, TrainAndBaselineTakeSparse) {
  const fs::path dir = temp("sparse_flag");
  const fs::path scene = dir / "scene";
  fs::create_directories(scene);
  fs::copy(src() + "/data_samples/synth_small/images", scene / "images", fs::copy_options::recursive);
  fs::copy(src() + "/data_samples/synth_small/sparse/0", scene / "colmap", fs::copy_options::recursive);
  const std::string common = "--iters 1 -r 2 --log-every 0 --top-cells 50 ";
  Result none = run("train " + scene.string() + " " + common + "--stages 1 -o " + (dir / "none").string());
  EXPECT_NE(none.code, 0);
  EXPECT_NE(none.output.find("--sparse"), std::string::npos) << none.output;
  Result tr = run("train " + scene.string() + " " + common + "--stages 1 --sparse colmap -o " + (dir / "t").string());
  EXPECT_EQ(tr.code, 0) << tr.output;
  Result bl =
      run("baseline " + scene.string() + " --iters 1 -r 2 --log-every 0 --sparse colmap -o " + (dir / "b").string());
  EXPECT_EQ(bl.code, 0) << bl.output;
  fs::remove_all(dir);
}

TEST(Cli, TrainInitLayerSeedsTheChosenLayers) {
  const std::string scene = src() + "/data_samples/synth_small";
  const fs::path dir = temp("init_layer");
  auto per_layer = [](const std::string& log) {
    const auto at = log.find("(per layer ");
    if (at == std::string::npos) return std::array<long, 3>{-1, -1, -1};
    std::array<long, 3> n{};
    std::sscanf(log.c_str() + at, "(per layer %ld/%ld/%ld", &n[0], &n[1], &n[2]);
    return n;
  };
  // (Without the far shell, which at -r 2 would seed the first seeded layer
  // from the sample's open pixels too.)
  const std::string common =
      "train " + scene + " -r 2 --iters 1 --stages 1 --top-cells 50 --log-every 0 --far-shell false -o ";
  Result top = run(common + (dir / "top").string() + " --init-layers 1");
  ASSERT_EQ(top.code, 0) << top.output;
  const auto t = per_layer(top.output);
  EXPECT_GT(t[0], 0) << top.output;
  EXPECT_EQ(t[1], 0);
  EXPECT_EQ(t[2], 0);
  // The default seeds the top layer and the next.
  Result two = run(common + (dir / "two").string());
  ASSERT_EQ(two.code, 0) << two.output;
  const auto d = per_layer(two.output);
  EXPECT_EQ(d[0], t[0]) << two.output;
  EXPECT_GT(d[1], d[0]);
  EXPECT_EQ(d[2], 0);
  // From layer 1 down: layers 1 and 2.
  Result low = run(common + (dir / "low").string() + " --init-layer 1");
  ASSERT_EQ(low.code, 0) << low.output;
  const auto l = per_layer(low.output);
  EXPECT_EQ(l[0], 0) << low.output;
  EXPECT_EQ(l[1], d[1]);
  EXPECT_GT(l[2], l[1]);
  Result all = run(common + (dir / "all").string() + " --init-layer -1");
  ASSERT_EQ(all.code, 0) << all.output;
  const auto a = per_layer(all.output);
  EXPECT_EQ(a[0], t[0]) << all.output;
  EXPECT_GT(a[1], a[0]);  // 4x finer voxels: more of them are occupied
  EXPECT_GT(a[2], a[1]);
  Result bad = run(common + (dir / "bad").string() + " --init-layer 3");
  EXPECT_NE(bad.code, 0);
  EXPECT_NE(bad.output.find("init_layer"), std::string::npos) << bad.output;
  EXPECT_FALSE(fs::exists(dir / "bad" / "model.ag2gs"));
  Result none = run(common + (dir / "none").string() + " --init-layers 0");
  EXPECT_NE(none.code, 0);
  EXPECT_NE(none.output.find("--init-layers"), std::string::npos) << none.output;
  fs::remove_all(dir);
}

// One scene-folder rule for every subcommand: render finds a model in
// sparse/ without the 0/ level as train and info do, and its errors name the
// folder looked at and --sparse.
TEST(Cli, RenderFindsTheModelInSparseWithoutZeroAndNamesSparseInErrors) {
  const std::string scene = src() + "/data_samples/tiny_scene";
  const fs::path dir = temp("flat");
  fs::create_directories(dir);
  fs::copy(scene, dir / "s", fs::copy_options::recursive);
  for (const auto& e : fs::directory_iterator(dir / "s" / "sparse" / "0"))
    fs::rename(e.path(), dir / "s" / "sparse" / e.path().filename());
  fs::remove(dir / "s" / "sparse" / "0");
  const std::string ply = " --ply " + scene + "/gaussians.ply";
  Result r = run("render" + ply + " --scene " + (dir / "s").string() + " -o " + (dir / "o").string());
  ASSERT_EQ(r.code, 0) << r.output;
  EXPECT_TRUE(fs::exists(dir / "o" / "rgb" / "view_003.png"));
  EXPECT_NE(r.output.find("cameras from " + (dir / "s" / "sparse").string() + ";"), std::string::npos) << r.output;
  // info finds the same model (tiny_scene has no images: it then stops there).
  Result info = run("info --quick " + (dir / "s").string());
  EXPECT_NE(info.output.find("COLMAP model: " + (dir / "s" / "sparse").string() + " (text)"), std::string::npos)
      << info.output;

  // The model elsewhere: found with --sparse, and the error says so.
  fs::rename(dir / "s" / "sparse", dir / "s" / "colmap");
  r = run("render" + ply + " --scene " + (dir / "s").string() + " -o " + (dir / "o2").string());
  EXPECT_EQ(r.code, 1);
  for (const std::string& n : {(dir / "s" / "sparse").string(), std::string("sparse/0/"), std::string("--sparse")})
    EXPECT_NE(r.output.find(n), std::string::npos) << "lacks '" << n << "':\n" << r.output;
  r = run("render" + ply + " --scene " + (dir / "s").string() + " --sparse colmap -o " + (dir / "o2").string());
  EXPECT_EQ(r.code, 0) << r.output;
  info = run("info --quick " + (dir / "s").string() + " --sparse colmap");
  EXPECT_NE(info.output.find("COLMAP model: " + (dir / "s" / "colmap").string() + " (text)"), std::string::npos)
      << info.output;
  r = run("render" + ply + " --scene " + (dir / "s").string() + " --sparse sparse/1 -o " + (dir / "o3").string());
  EXPECT_EQ(r.code, 1);
  EXPECT_NE(r.output.find((dir / "s" / "sparse" / "1").string() + ": no such folder"), std::string::npos) << r.output;
  fs::remove_all(dir);
}

// render without -r uses the resolution the model was trained at (as query
// does); an explicit -r wins; a .ply with no record beside it stays at 1.
TEST(Cli, RenderDefaultsToTheModelsTrainingResolution) {
  const std::string scene = src() + "/data_samples/synth_small";  // 160x120 cameras
  const fs::path dir = temp("render_res");
  Result t =
      run("train " + scene + " -r 2 --iters 2 --stages 1 --top-cells 50 --log-every 0 -o " + (dir / "model").string());
  ASSERT_EQ(t.code, 0) << t.output;
  auto size_of = [](const fs::path& png) {
    const cv::Mat img = cv::imread(png.string());
    return std::make_pair(img.cols, img.rows);
  };
  const std::string common = " --scene " + scene + " --views view_000 -o ";
  Result r = run("render " + (dir / "model").string() + common + (dir / "a").string());
  ASSERT_EQ(r.code, 0) << r.output;
  EXPECT_EQ(size_of(dir / "a" / "rgb" / "view_000.png"), std::make_pair(80, 60));
  EXPECT_NE(r.output.find("rendering at 1/2 resolution: the model was trained at -r 2"), std::string::npos) << r.output;
  r = run("render " + (dir / "model").string() + common + (dir / "b").string() + " -r 1");
  ASSERT_EQ(r.code, 0) << r.output;
  EXPECT_EQ(size_of(dir / "b" / "rgb" / "view_000.png"), std::make_pair(160, 120));
  EXPECT_NE(r.output.find("-r 1 given"), std::string::npos) << r.output;
  // --ply inside the model folder: the same record.
  r = run("render --ply " + (dir / "model" / "point_cloud.ply").string() + common + (dir / "c").string());
  ASSERT_EQ(r.code, 0) << r.output;
  EXPECT_EQ(size_of(dir / "c" / "rgb" / "view_000.png"), std::make_pair(80, 60));
  // A baseline model: point_cloud.ply + metrics.json (written with --eval).
  fs::create_directories(dir / "baseline");
  fs::copy_file(dir / "model" / "point_cloud.ply", dir / "baseline" / "point_cloud.ply");
  std::ofstream(dir / "baseline" / "metrics.json") << R"({"model": "baseline", "resolution": 4})";
  r = run("render " + (dir / "baseline").string() + common + (dir / "d").string());
  ASSERT_EQ(r.code, 0) << r.output;
  EXPECT_EQ(size_of(dir / "d" / "rgb" / "view_000.png"), std::make_pair(40, 30));
  // A bare .ply: full resolution, and the log says why.
  fs::create_directories(dir / "bare");
  fs::copy_file(dir / "model" / "point_cloud.ply", dir / "bare" / "g.ply");
  r = run("render --ply " + (dir / "bare" / "g.ply").string() + common + (dir / "e").string());
  ASSERT_EQ(r.code, 0) << r.output;
  EXPECT_EQ(size_of(dir / "e" / "rgb" / "view_000.png"), std::make_pair(160, 120));
  EXPECT_NE(r.output.find("rendering at 1/1 resolution: no record of the training -r"), std::string::npos) << r.output;
  fs::remove_all(dir);
}
