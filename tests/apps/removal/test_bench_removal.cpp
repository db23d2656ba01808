// The removal benchmark's scorer (bench/removal/bench_removal.cpp) on a
// constructed 8x6 scene whose scores are known in closed form: the hole and
// kept PSNR, the residue, and the fill's ceiling (per pixel, the kept
// colour K plus the fill colour nearest the truth through 1 - alpha).
#include <gtest/gtest.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>

#include "host/io/npy_io.h"
#include "tests/cli_test_util.h"

namespace ag2gs {
namespace {

namespace fs = std::filesystem;

constexpr int kW = 8, kH = 6;
const cv::Vec3b kTruth(200, 150, 100);  // BGR

bool in_mask(int x, int y) {
  return x >= 2 && x < 6 && y >= 2 && y < 4;
}  // 8 pixels
bool left_half(int x) {
  return x < 4;
}

// PSNR over the mask of an image that is black on `black` of its 8 pixels
// and the truth elsewhere.
double psnr_with_black(int black) {
  double se = 0;
  for (int c = 0; c < 3; ++c) se += black * std::pow(kTruth[c] / 255.0, 2);
  return -10 * std::log10(se / (8 * 3));
}

std::string scorer() {
  const char* bin = std::getenv("AG2GS_BINARY");
  return (fs::path(bin ? bin : "./ag2gs").parent_path() / "ag2gs_bench_removal").string();
}

test::CliResult run_scorer(const std::string& args) {
  const std::string cmd = scorer() + " " + args + " 2>&1";
  test::CliResult r{-1, ""};
  FILE* p = popen(cmd.c_str(), "r");
  if (!p) return r;
  char buf[4096];
  while (fgets(buf, sizeof buf, p)) r.output += buf;
  const int status = pclose(p);
  r.code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  return r;
}

class BenchRemoval : public ::testing::Test {
 protected:
  void SetUp() override {
    ASSERT_TRUE(fs::exists(scorer())) << scorer() << " is missing: build with AG2GS_BUILD_BENCH=ON";
    dir_ = fs::temp_directory_path() / ("ag2gs_bench_removal_" + std::to_string(::getpid()));
    fs::remove_all(dir_);
    const fs::path scene = dir_ / "scene";
    fs::create_directories(scene / "removal_gt" / "box");
    fs::create_directories(scene / "gt");
    std::ofstream(scene / "synth.json")
        << R"({"objects": [{"id": 1, "category": "box"}, {"id": 2, "category": "mug"}]})";
    cv::Mat truth(kH, kW, CV_8UC3, kTruth), ids(kH, kW, CV_16UC1, cv::Scalar(0));
    cv::Mat original = truth.clone(), removed = truth.clone(), deleted = truth.clone();
    std::vector<float> alpha(kW * kH, 1.f);
    for (int y = 0; y < kH; ++y)
      for (int x = 0; x < kW; ++x) {
        if (!in_mask(x, y)) continue;
        ids.at<uint16_t>(y, x) = 1;
        original.at<cv::Vec3b>(y, x) = cv::Vec3b(0, 0, 255);
        deleted.at<cv::Vec3b>(y, x) = cv::Vec3b(0, 0, 0);  // right half: an opaque black surface
        if (left_half(x)) {
          // Left half: half covered by a surface of the truth's colour, so a
          // fill of that colour behind it gives the truth exactly.
          alpha[y * kW + x] = 0.5f;
          deleted.at<cv::Vec3b>(y, x) = kTruth / 2;
          removed.at<cv::Vec3b>(y, x) = cv::Vec3b(0, 0, 0);  // a removal that fills only the right half
        }
      }
    ids.at<uint16_t>(0, 0) = 2;  // another category's pixel, outside the mask
    cv::imwrite((scene / "removal_gt" / "box" / "view_000.png").string(), truth);
    cv::imwrite((scene / "gt" / "view_000.png").string(), ids);
    for (const auto& [name, img] :
         {std::pair<std::string, cv::Mat>{"original", original}, {"removed", removed}, {"deleted", deleted}}) {
      fs::create_directories(dir_ / name / "rgb");
      cv::imwrite((dir_ / name / "rgb" / "view_000.png").string(), img);
    }
    fs::create_directories(dir_ / "deleted" / "alpha");
    write_npy((dir_ / "deleted" / "alpha" / "view_000.npy").string(), alpha, {kH, kW});
  }
  void TearDown() override { fs::remove_all(dir_); }

  std::string args(const std::string& extra) const {
    return (dir_ / "scene").string() + " --category box --original " + (dir_ / "original").string() + " --removed " +
           (dir_ / "removed").string() + " --json " + (dir_ / "score.json").string() + " " + extra;
  }
  nlohmann::json score() const {
    nlohmann::json j;
    std::ifstream(dir_ / "score.json") >> j;
    return j;
  }
  fs::path dir_;
};

TEST_F(BenchRemoval, TheCeilingFillsBehindWhatTheModelShows) {
  const auto r = run_scorer(args("--deleted " + (dir_ / "deleted").string()));
  ASSERT_EQ(r.code, 0) << r.output;
  const nlohmann::json j = score();
  EXPECT_EQ(j["mask_pixels"].get<int>(), 8);
  // The removal is black on the left half (4 of 8 pixels); the ceiling
  // reaches the truth on the left half and keeps the opaque black of the
  // right half, which no fill behind it can change.
  EXPECT_NEAR(j["removed"]["hole_psnr"].get<double>(), psnr_with_black(4), 1e-9);
  EXPECT_NEAR(j["ceiling"]["hole_psnr"].get<double>(), psnr_with_black(4), 1e-9);
  EXPECT_NEAR(j["original"]["residue"].get<double>(), 1.0, 1e-12);
  EXPECT_NEAR(j["ceiling"]["residue"].get<double>(), 0.0, 1e-12);
  EXPECT_TRUE(j["ceiling"]["kept_psnr"].is_null());  // outside the mask it is no image to score
  EXPECT_NE(r.output.find("ceiling "), std::string::npos) << r.output;
}

TEST_F(BenchRemoval, TheCeilingAddsAtMostWhatTheModelLeavesOpen) {
  // Every mask pixel a black surface of alpha 0.75: a white fill behind it
  // adds at most 0.25 x 255 = 63.75 to each channel, below the truth's.
  std::vector<float> alpha(kW * kH, 1.f);
  cv::Mat deleted = cv::imread((dir_ / "deleted" / "rgb" / "view_000.png").string());
  for (int y = 0; y < kH; ++y)
    for (int x = 0; x < kW; ++x)
      if (in_mask(x, y)) {
        alpha[y * kW + x] = 0.75f;
        deleted.at<cv::Vec3b>(y, x) = cv::Vec3b(0, 0, 0);
      }
  cv::imwrite((dir_ / "deleted" / "rgb" / "view_000.png").string(), deleted);
  write_npy((dir_ / "deleted" / "alpha" / "view_000.npy").string(), alpha, {kH, kW});
  const auto r = run_scorer(args("--deleted " + (dir_ / "deleted").string()));
  ASSERT_EQ(r.code, 0) << r.output;
  double se = 0;
  for (int c = 0; c < 3; ++c) se += std::pow((kTruth[c] - 64) / 255.0, 2);
  EXPECT_NEAR(score()["ceiling"]["hole_psnr"].get<double>(), -10 * std::log10(se / 3), 1e-9);
}

TEST_F(BenchRemoval, DeletedRendersOverASkyAreRefused) {
  // alpha 0 where the render is not black: rendered over a background.
  std::vector<float> alpha(kW * kH, 1.f);
  alpha[0] = 0.f;
  write_npy((dir_ / "deleted" / "alpha" / "view_000.npy").string(), alpha, {kH, kW});
  const auto r = run_scorer(args("--deleted " + (dir_ / "deleted").string()));
  EXPECT_NE(r.code, 0);
  EXPECT_NE(r.output.find("--bg 0,0,0"), std::string::npos) << r.output;
}

TEST_F(BenchRemoval, WithoutDeletedRendersThereIsNoCeiling) {
  const auto r = run_scorer(args(""));
  ASSERT_EQ(r.code, 0) << r.output;
  EXPECT_FALSE(score().contains("ceiling"));
  EXPECT_EQ(r.output.find("ceiling "), std::string::npos) << r.output;
}

TEST_F(BenchRemoval, AnAlphaOfTheWrongSizeIsRefused) {
  write_npy((dir_ / "deleted" / "alpha" / "view_000.npy").string(), std::vector<float>(4, 1.f), {2, 2});
  const auto r = run_scorer(args("--deleted " + (dir_ / "deleted").string()));
  EXPECT_NE(r.code, 0);
  EXPECT_NE(r.output.find("--outputs rgb,alpha --bg 0,0,0"), std::string::npos) << r.output;
  fs::remove(dir_ / "deleted" / "alpha" / "view_000.npy");
  const auto missing = run_scorer(args("--deleted " + (dir_ / "deleted").string()));
  EXPECT_NE(missing.code, 0);
  EXPECT_NE(missing.output.find("view_000.npy"), std::string::npos) << missing.output;
}

}  // namespace
}  // namespace ag2gs
