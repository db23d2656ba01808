// The scene subcommands as scripts use them: `info` on scenes, models and
// PLYs, and the clear errors and exit codes of info/sfm/undistort.
#include <gtest/gtest.h>
#include <sys/wait.h>

#include <array>
#include <cstdio>
#include <filesystem>

#include "host/io/model_io.h"
#include "tests/cli_test_util.h"
#include "tests/io_test_util.h"

namespace fs = std::filesystem;
using ag2gs::test::ScratchDir;
using ag2gs::test::source_path;
using ag2gs::test::write_bytes;

namespace {

using Result = ag2gs::test::CliResult;
inline Result run(const std::string& args) {
  return ag2gs::test::run_cli(args);
}

void expect_has(const Result& r, const std::vector<std::string>& needles) {
  for (const std::string& n : needles)
    EXPECT_NE(r.output.find(n), std::string::npos) << "lacks '" << n << "':\n" << r.output;
}

}  // namespace

TEST(CliScene, InfoDescribesTheSyntheticSampleScene) {
  const Result r = run("info " + source_path("data_samples/synth_small") + " --eval");
  EXPECT_EQ(r.code, 0) << r.output;
  expect_has(r, {"camera models: PINHOLE x16", "images: 16 at 160x120", "14 train, 2 test", "points: 3000",
                 "language_features", "masks per view", "feature dimension: 512", "ok"});
  const Result half = run("info " + source_path("data_samples/synth_small") + " -r 2 --quick");
  EXPECT_EQ(half.code, 0) << half.output;
  expect_has(half, {"at 80x60", "downscaled on load"});
}

TEST(CliScene, InfoReportsProblemsWithANonZeroExit) {
  ScratchDir dir("cli_scene");
  fs::copy(source_path("data_samples/synth_small"), dir.path() / "s", fs::copy_options::recursive);
  write_bytes(dir.file("s/images/view_003.png"), "not an image");
  const Result r = run("info " + dir.file("s"));
  EXPECT_EQ(r.code, 1) << r.output;
  expect_has(r, {"problem:", "view_003.png", "cannot be decoded", "ag2gs info: error: 1 problem(s)"});
  fs::remove(dir.file("s/images/view_005.png"));
  const Result missing = run("info " + dir.file("s"));
  EXPECT_EQ(missing.code, 1);
  expect_has(missing, {"view_005.png", "missing"});
  const Result none = run("info " + dir.file("nothing"));
  EXPECT_EQ(none.code, 1);
  expect_has(none, {"nothing", "no such file or folder"});
}

TEST(CliScene, InfoDescribesModelsAndPlys) {
  ScratchDir dir("cli_scene");
  ag2gs::ModelArchive a;
  a.meta = {{"iteration", 42}};
  a.put<float>("anchors/pos", std::vector<float>(12, 1.f), {4, 3});
  fs::create_directories(dir.path() / "model");
  ag2gs::write_model_archive(dir.file("model/model.ag2gs"), a);
  const Result r = run("info " + dir.file("model"));
  EXPECT_EQ(r.code, 0) << r.output;
  expect_has(r, {"format version: 1", "iteration: 42", "anchors/pos", "f32", "4x3"});
  const Result ply = run("info " + source_path("data_samples/tiny_scene/gaussians.ply"));
  EXPECT_EQ(ply.code, 0);
  expect_has(ply, {"Gaussians: 300", "SH degree: 1"});
}

TEST(CliScene, SfmAndUndistortErrorsAreClear) {
  ScratchDir dir("cli_scene");
  Result r = run("sfm " + dir.file("photos") + " -o " + dir.file("out"));
  EXPECT_EQ(r.code, 1);
  expect_has(r, {"ag2gs sfm: error:", "photos", "no such folder"});
  fs::create_directories(dir.path() / "photos");
  write_bytes(dir.file("photos/a.jpg"), "x");
  write_bytes(dir.file("photos/b.jpg"), "x");
  r = run("sfm " + dir.file("photos") + " -o " + dir.file("out") + " --colmap /no/colmap");
  EXPECT_EQ(r.code, 1);
  expect_has(r, {"/no/colmap", "apt-get install colmap"});
  EXPECT_FALSE(fs::exists(dir.file("out")));
  r = run("undistort " + dir.file("nowhere") + " -o " + dir.file("out2"));
  EXPECT_EQ(r.code, 1);
  expect_has(r, {"ag2gs undistort: error:", "nowhere"});
}

// A folder holding a COLMAP model but no images/: info names the missing
// folder first, not the camera model (undistorting needs the photos too).
TEST(CliScene, InfoWithoutImagesNamesTheImageFolderFirst) {
  ScratchDir dir("cli_scene");
  fs::copy(source_path("data_samples/tiny_scene"), dir.path() / "s", fs::copy_options::recursive);
  fs::remove_all(dir.path() / "s" / "images");
  write_bytes(dir.file("s/sparse/0/cameras.txt"),
              "1 OPENCV 160 120 160 160 80 60 0.01 0 0 0\n2 OPENCV 160 120 170 170 79.5 60.5 0.01 0 0 0\n");
  const Result r = run("info " + dir.file("s"));
  EXPECT_EQ(r.code, 1) << r.output;
  expect_has(r,
             {"camera models: OPENCV x4", dir.file("s/images") + ": no image folder", "in images/", "ag2gs undistort"});
  EXPECT_EQ(r.output.find("Undistort first"), std::string::npos) << r.output;
}
