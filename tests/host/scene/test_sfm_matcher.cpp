// What `ag2gs sfm` decides and shows without running COLMAP: the matcher
// chosen from the photos' names (video frames -> sequential), COLMAP's
// progress lines, and the progress run_sfm prints while a stand-in `colmap`
// script runs (fast; tests/host/scene/test_sfm.cpp runs the real COLMAP).
#include <gtest/gtest.h>
#include <sys/stat.h>

#include <cstdio>
#include <filesystem>
#include <opencv2/imgcodecs.hpp>
#include <string>
#include <vector>

#include "host/scene/sfm.h"
#include "tests/io_test_util.h"

namespace fs = std::filesystem;
using namespace ag2gs;
using ag2gs::test::ScratchDir;
using ag2gs::test::write_bytes;

namespace {

// `n` names printf'd from `pattern` with numbers first, first + step, ...
std::vector<std::string> frames(const char* pattern, int n, int first = 1, int step = 1) {
  std::vector<std::string> names;
  for (int i = 0; i < n; ++i) {
    char buf[64];
    std::snprintf(buf, sizeof buf, pattern, first + i * step);
    names.push_back(buf);
  }
  return names;
}

bool has(const std::string& text, const std::string& needle) {
  return text.find(needle) != std::string::npos;
}

}  // namespace

TEST(SfmMatcher, VideoFrameNamesAboveFortyImagesGetTheSequentialMatcher) {
  MatcherChoice c = choose_matcher(frames("frame_%04d.jpg", 50));
  EXPECT_EQ(c.matcher, "sequential");
  EXPECT_TRUE(has(c.reason, "50 photos")) << c.reason;
  EXPECT_TRUE(has(c.reason, "frame_0001.jpg .. frame_0050.jpg, step 1")) << c.reason;
  EXPECT_TRUE(has(c.reason, "1225 pairs")) << c.reason;
  EXPECT_EQ(choose_matcher(frames("%04d.png", 60)).matcher, "sequential");
  EXPECT_EQ(choose_matcher(frames("IMG_%d.JPG", 45, 1234)).matcher, "sequential");
  // Every 5th frame extracted: evenly stepped.
  c = choose_matcher(frames("out%05d.png", 80, 5, 5));
  EXPECT_EQ(c.matcher, "sequential");
  EXPECT_TRUE(has(c.reason, "step 5")) << c.reason;
  // A few blurry frames deleted (2 of 59 steps are 2): still a sequence.
  std::vector<std::string> dropped = frames("frame_%04d.jpg", 60);
  dropped.erase(dropped.begin() + 30);
  dropped.erase(dropped.begin() + 10);
  EXPECT_EQ(choose_matcher(dropped).matcher, "sequential");
  // The order given does not matter: COLMAP pairs neighbours in name order.
  std::vector<std::string> shuffled = frames("frame_%04d.jpg", 50);
  std::swap(shuffled[0], shuffled[40]);
  std::swap(shuffled[7], shuffled[22]);
  EXPECT_EQ(choose_matcher(shuffled).matcher, "sequential");
}

TEST(SfmMatcher, FewPhotosOrUnorderedNamesGetTheExhaustiveMatcher) {
  MatcherChoice c = choose_matcher(frames("frame_%04d.jpg", kSequentialMinImages));
  EXPECT_EQ(c.matcher, "exhaustive");
  EXPECT_TRUE(has(c.reason, "40 photos, few enough to match all 780 pairs")) << c.reason;
  EXPECT_EQ(choose_matcher(frames("frame_%04d.jpg", kSequentialMinImages + 1)).matcher, "sequential");
  EXPECT_EQ(choose_matcher({}).matcher, "exhaustive");
  EXPECT_EQ(choose_matcher({"a.jpg"}).matcher, "exhaustive");
  // Unpadded numbers sort frame_1, frame_10, frame_11, ...: not neighbours.
  c = choose_matcher(frames("frame_%d.jpg", 60));
  EXPECT_EQ(c.matcher, "exhaustive");
  EXPECT_TRUE(has(c.reason, "name order")) << c.reason;
  // Names without numbers.
  std::vector<std::string> words;
  for (int i = 0; i < 50; ++i)
    words.push_back("statue_" + std::string(1, static_cast<char>('a' + i % 26)) +
                    std::string(1, static_cast<char>('a' + i / 26)) + ".jpg");
  c = choose_matcher(words);
  EXPECT_EQ(c.matcher, "exhaustive");
  EXPECT_TRUE(has(c.reason, "no frame numbers")) << c.reason;
  // Photos from a camera, numbered but taken irregularly.
  std::vector<std::string> irregular;
  for (int i = 0, n = 1000; i < 50; ++i, n += 1 + (i * 7) % 13)
    irregular.push_back("DSC_" + std::to_string(n) + ".JPG");
  c = choose_matcher(irregular);
  EXPECT_EQ(c.matcher, "exhaustive");
  EXPECT_TRUE(has(c.reason, "step")) << c.reason;
  // Two cameras' files in one folder.
  std::vector<std::string> mixed = frames("IMG_%04d.jpg", 25);
  for (const std::string& n : frames("DSC_%04d.jpg", 25)) mixed.push_back(n);
  c = choose_matcher(mixed);
  EXPECT_EQ(c.matcher, "exhaustive");
  EXPECT_TRUE(has(c.reason, "more than one pattern")) << c.reason;
  // Too many gaps: 1 in 5 frames missing.
  std::vector<std::string> gappy, all = frames("frame_%04d.jpg", 75);
  for (size_t i = 0; i < all.size(); ++i)
    if (i % 5 != 2) gappy.push_back(all[i]);
  c = choose_matcher(gappy);
  EXPECT_EQ(c.matcher, "exhaustive");
  EXPECT_TRUE(has(c.reason, "skip too often")) << c.reason;
}

TEST(SfmMatcher, ColmapProgressLinesGiveUnitsDoneOfTotal) {
  ColmapProgress p;
  ASSERT_TRUE(parse_colmap_progress("Processed file [3/50]", &p));
  EXPECT_EQ(p.unit, "image");
  EXPECT_EQ(p.done, 3);
  EXPECT_EQ(p.total, 50);
  // COLMAP 3.8 completes the line when the block is done.
  ASSERT_TRUE(parse_colmap_progress("Matching block [2/4, 3/4] in 12.345s", &p));
  EXPECT_EQ(p.unit, "block");
  EXPECT_EQ(p.done, 7);
  EXPECT_EQ(p.total, 16);
  // Newer COLMAP logs it when the block starts.
  ASSERT_TRUE(parse_colmap_progress("I0101 12:00:00.000 42 pairing.cc:100] Matching block [2/4, 3/4]", &p));
  EXPECT_EQ(p.done, 6);
  ASSERT_TRUE(parse_colmap_progress("Matching image [5/50] in 0.512s", &p));
  EXPECT_EQ(p.unit, "image");
  EXPECT_EQ(p.done, 5);
  EXPECT_EQ(p.total, 50);
  EXPECT_FALSE(parse_colmap_progress("Elapsed time: 0.012 [minutes]", &p));
}

// run_sfm against a stand-in colmap: the matcher line, the matcher and block
// size it passes, and throttled progress with an ETA for both matchers.
TEST(SfmMatcher, RunSfmSaysWhichMatcherAndShowsMatchingProgress) {
  ScratchDir dir("sfm_matcher");
  const std::string fake = dir.file("colmap");
  write_bytes(
      fake,
      "#!/bin/sh\n"
      "echo \"$@\" >> " +
          dir.file("args.txt") +
          "\n"
          "case \"$1\" in\n"
          "  feature_extractor) i=1; while [ $i -le 50 ]; do echo \"Processed file [$i/50]\"; i=$((i+1)); done;;\n"
          "  exhaustive_matcher) for a in 1 2 3 4; do for b in 1 2 3 4; do "
          "printf 'Matching block [%d/4, %d/4]' $a $b; echo ' in 0.010s'; done; done;;\n"
          "  sequential_matcher) i=1; while [ $i -le 50 ]; do echo \"Matching image [$i/50] in 0.01s\"; "
          "i=$((i+1)); done;;\n"
          "  *) echo 'stand-in: no model'; exit 1;;\n"
          "esac\n");
  ::chmod(fake.c_str(), 0755);
  fs::create_directories(dir.path() / "frames");
  fs::create_directories(dir.path() / "photos");
  const cv::Mat big(1000, 2000, CV_8UC3, cv::Scalar(1, 2, 3));
  for (int i = 1; i <= 50; ++i) {
    char name[32];
    std::snprintf(name, sizeof name, "frame_%04d.png", i);
    if (i == 1)
      cv::imwrite((dir.path() / "frames" / name).string(), big);
    else
      write_bytes((dir.path() / "frames" / name).string(), "x");
    write_bytes((dir.path() / "photos" /
                 ("p" + std::string(1, static_cast<char>('a' + i % 26)) +
                  std::string(1, static_cast<char>('a' + i / 26)) + ".jpg"))
                    .string(),
                "x");
  }
  auto run = [&](const std::string& images, const std::string& matcher) {
    SfmOptions o;
    o.colmap = fake;
    o.matcher = matcher;
    std::string lines;
    o.progress = [&](const std::string& l) { lines += l + "\n"; };
    EXPECT_THROW(run_sfm(dir.file(images), dir.file("out_" + images + matcher), o), std::runtime_error);
    return lines;
  };
  std::string log = run("frames", "auto");
  EXPECT_TRUE(has(log, "matcher: sequential, 50 photos named as an ordered sequence")) << log;
  EXPECT_TRUE(has(log, "SIFT on 2000x1000 photos reduced to 1600 px")) << log;
  ASSERT_TRUE(has(log, "matching (sequential) ...")) << log;
  log = log.substr(log.find("matching (sequential) ..."));  // the matcher's lines, not the extractor's
  EXPECT_TRUE(has(log, "  image 1/50 (2%)")) << log;        // the first at once
  EXPECT_TRUE(has(log, "  image 5/50 (10%)")) << log;       // then one per 10%
  EXPECT_FALSE(has(log, "  image 6/50")) << log;
  EXPECT_TRUE(has(log, "  image 45/50 (90%)")) << log;
  EXPECT_TRUE(has(log, "left")) << log;

  log = run("photos", "auto");
  EXPECT_TRUE(has(log, "matcher: exhaustive, the names carry no frame numbers")) << log;
  EXPECT_TRUE(has(log, "SIFT on at most 1600 px")) << log;  // the first photo is not decodable here
  EXPECT_TRUE(has(log, "matching (exhaustive) ...")) << log;
  EXPECT_TRUE(has(log, "  block 1/16 (6%)")) << log;
  EXPECT_TRUE(has(log, "  block 2/16 (12%)")) << log;
  EXPECT_TRUE(has(log, "  block 15/16 (93%)")) << log;
  EXPECT_TRUE(has(log, "about")) << log;
  const std::string args = ag2gs::test::read_bytes(dir.file("args.txt"));
  EXPECT_TRUE(has(args, "exhaustive_matcher --database_path")) << args;
  EXPECT_TRUE(has(args, "--ExhaustiveMatching.block_size 13")) << args;  // 50 photos in 4 blocks

  log = run("frames", "exhaustive");
  EXPECT_TRUE(has(log, "matcher: exhaustive, as --matcher says")) << log;
}
