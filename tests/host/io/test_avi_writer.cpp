// The Motion-JPEG AVI writer (host/io/avi_writer.h) against an independent
// reader, OpenCV's (its built-in MJPEG backend): frame count, size, rate and
// pixels; the RIFF structure walked by hand (every size consistent, the
// index pointing at the frames); and the refusals.
#include <gtest/gtest.h>
#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <opencv2/core.hpp>
#include <opencv2/videoio.hpp>
#include <string>
#include <vector>

#include "host/io/avi_writer.h"

namespace ag2gs {
namespace {

namespace fs = std::filesystem;

fs::path scratch(const std::string& name) {
  const fs::path dir = fs::temp_directory_path() / ("ag2gs_test_avi_" + std::to_string(::getpid()));
  fs::create_directories(dir);
  return dir / name;
}

// Frame f: a horizontal ramp in red, green = f / frames, blue = 1 - red.
std::vector<float> frame(int w, int h, int f, int frames) {
  std::vector<float> rgb(static_cast<size_t>(w) * h * 3);
  for (int y = 0; y < h; ++y)
    for (int x = 0; x < w; ++x) {
      float* p = &rgb[(static_cast<size_t>(y) * w + x) * 3];
      p[0] = static_cast<float>(x) / (w - 1);
      p[1] = static_cast<float>(f) / frames;
      p[2] = 1.f - p[0];
    }
  return rgb;
}

uint32_t le32(const std::string& b, size_t at) {
  return static_cast<uint32_t>(static_cast<unsigned char>(b[at])) |
         static_cast<uint32_t>(static_cast<unsigned char>(b[at + 1])) << 8 |
         static_cast<uint32_t>(static_cast<unsigned char>(b[at + 2])) << 16 |
         static_cast<uint32_t>(static_cast<unsigned char>(b[at + 3])) << 24;
}

TEST(AviWriter, OpenCVReadsTheFramesBack) {
  const int w = 37, h = 22, frames = 5;  // odd sizes: JPEG pads its blocks, the frame must not show it
  const fs::path path = scratch("ramp.avi");
  {
    MjpegAviWriter avi(path.string(), w, h, 12.5);
    for (int f = 0; f < frames; ++f) avi.write_rgb(frame(w, h, f, frames));
    EXPECT_EQ(avi.frames(), frames);
    avi.close();
  }
  cv::VideoCapture video(path.string(), cv::CAP_OPENCV_MJPEG);
  ASSERT_TRUE(video.isOpened());
  EXPECT_EQ(video.get(cv::CAP_PROP_FRAME_COUNT), frames);
  EXPECT_NEAR(video.get(cv::CAP_PROP_FPS), 12.5, 1e-6);
  EXPECT_EQ(video.get(cv::CAP_PROP_FRAME_WIDTH), w);
  EXPECT_EQ(video.get(cv::CAP_PROP_FRAME_HEIGHT), h);
  cv::Mat bgr;
  for (int f = 0; f < frames; ++f) {
    ASSERT_TRUE(video.read(bgr)) << "frame " << f;
    ASSERT_EQ(bgr.cols, w);
    ASSERT_EQ(bgr.rows, h);
    // JPEG at quality 95 on a smooth ramp loses a few levels (measured:
    // mean 0.78-0.86, worst 4-5 levels over the 5 frames).
    const std::vector<float> want = frame(w, h, f, frames);
    double sum = 0, worst = 0;
    for (int y = 0; y < h; ++y)
      for (int x = 0; x < w; ++x)
        for (int c = 0; c < 3; ++c) {
          const double got = bgr.at<cv::Vec3b>(y, x)[2 - c];
          const double e = std::abs(got - std::round(255.0 * want[(static_cast<size_t>(y) * w + x) * 3 + c]));
          sum += e;
          worst = std::max(worst, e);
        }
    EXPECT_LT(sum / (w * h * 3), 1.5) << "frame " << f;
    EXPECT_LE(worst, 10.0) << "frame " << f;
  }
  EXPECT_FALSE(video.read(bgr));
  fs::remove_all(path.parent_path());
}

TEST(AviWriter, TheRiffSizesAndTheIndexAgree) {
  const fs::path path = scratch("structure.avi");
  const int frames = 3;
  {
    MjpegAviWriter avi(path.string(), 16, 8, 25);
    for (int f = 0; f < frames; ++f) avi.write_rgb(frame(16, 8, f, frames));
  }  // the destructor finishes the file
  std::ifstream in(path, std::ios::binary);
  const std::string b((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  ASSERT_GT(b.size(), 300u);
  EXPECT_EQ(b.substr(0, 4), "RIFF");
  EXPECT_EQ(le32(b, 4), b.size() - 8);
  EXPECT_EQ(b.substr(8, 4), "AVI ");
  // hdrl: avih's frame count and size, strh's rate and length.
  EXPECT_EQ(b.substr(12, 4), "LIST");
  EXPECT_EQ(b.substr(20, 8), std::string("hdrlavih", 8));
  const size_t avih = 32;
  EXPECT_EQ(le32(b, avih), 40000u);    // microseconds a frame at 25 fps
  EXPECT_EQ(le32(b, avih + 16), 3u);   // frames
  EXPECT_EQ(le32(b, avih + 32), 16u);  // width
  EXPECT_EQ(le32(b, avih + 36), 8u);   // height
  const size_t hdrl_end = 20 + le32(b, 16);
  // movi: the frames, each a JPEG, then idx1 pointing at each.
  ASSERT_EQ(b.substr(hdrl_end, 4), "LIST");
  const size_t movi = hdrl_end + 8;
  EXPECT_EQ(b.substr(movi, 4), "movi");
  const size_t movi_end = movi + le32(b, hdrl_end + 4);
  ASSERT_EQ(b.substr(movi_end, 4), "idx1");
  ASSERT_EQ(le32(b, movi_end + 4), 16u * frames);
  EXPECT_EQ(movi_end + 8 + 16 * frames, b.size());
  size_t chunk = movi + 4;
  for (int f = 0; f < frames; ++f) {
    const size_t e = movi_end + 8 + 16 * f;
    EXPECT_EQ(b.substr(e, 4), "00dc");
    EXPECT_EQ(le32(b, e + 4), 0x10u);  // key frame
    EXPECT_EQ(movi + le32(b, e + 8), chunk) << "frame " << f;
    ASSERT_EQ(b.substr(chunk, 4), "00dc");
    const uint32_t size = le32(b, chunk + 4);
    EXPECT_EQ(le32(b, e + 12), size);
    EXPECT_EQ(static_cast<unsigned char>(b[chunk + 8]), 0xFF);  // a JPEG's start-of-image marker
    EXPECT_EQ(static_cast<unsigned char>(b[chunk + 9]), 0xD8);
    chunk += 8 + size + (size % 2);
  }
  EXPECT_EQ(chunk, movi_end);
  fs::remove_all(path.parent_path());
}

TEST(AviWriter, AFullVideoKeepsItsFirstFramesAndStaysReadable) {
  const fs::path path = scratch("limit.avi");
  {
    MjpegAviWriter avi(path.string(), 32, 24, 25, 95, 4096);
    for (int f = 0; f < 40; ++f) avi.write_rgb(frame(32, 24, f, 40));
    EXPECT_GT(avi.frames(), 1);
    EXPECT_EQ(avi.frames() + avi.dropped(), 40);
    EXPECT_GT(avi.dropped(), 0);
    avi.close();
    EXPECT_LE(static_cast<int64_t>(fs::file_size(path)), 4096);
    cv::VideoCapture video(path.string(), cv::CAP_OPENCV_MJPEG);
    ASSERT_TRUE(video.isOpened());
    EXPECT_EQ(video.get(cv::CAP_PROP_FRAME_COUNT), avi.frames());
    cv::Mat bgr;
    int read = 0;
    while (video.read(bgr)) ++read;
    EXPECT_EQ(read, avi.frames());
  }
  fs::remove_all(path.parent_path());
}

TEST(AviWriter, BadArgumentsAndPathsAreRefusedByName) {
  const fs::path path = scratch("bad.avi");
  auto message = [](auto&& make) {
    try {
      make();
    } catch (const std::exception& e) {
      return std::string(e.what());
    }
    return std::string("(nothing thrown)");
  };
  EXPECT_NE(message([&] { MjpegAviWriter(path.string(), 0, 8, 25); }).find("sides must be"), std::string::npos);
  EXPECT_NE(message([&] { MjpegAviWriter(path.string(), 8, 8, 0); }).find("frames a second"), std::string::npos);
  EXPECT_NE(message([&] { MjpegAviWriter(path.string(), 8, 8, NAN); }).find("frames a second"), std::string::npos);
  EXPECT_NE(message([&] { MjpegAviWriter(path.string(), 8, 8, 25, 0); }).find("quality"), std::string::npos);
  EXPECT_NE(message([&] { MjpegAviWriter(path.string(), 8, 8, 25, 95, 10); }).find("size limit"), std::string::npos);
  const std::string no_dir = (path.parent_path() / "no_such_dir" / "x.avi").string();
  EXPECT_NE(message([&] { MjpegAviWriter(no_dir, 8, 8, 25); }).find(no_dir), std::string::npos);
  MjpegAviWriter avi(path.string(), 8, 8, 25);
  EXPECT_NE(message([&] { avi.write_rgb(std::vector<float>(10)); }).find("8x8x3"), std::string::npos);
  EXPECT_NE(message([&] { avi.write_jpeg({1, 2, 3, 4}); }).find("not a JPEG"), std::string::npos);
  avi.close();
  EXPECT_NE(message([&] { avi.write_rgb(frame(8, 8, 0, 1)); }).find("after close"), std::string::npos);
  fs::remove_all(path.parent_path());
}

}  // namespace
}  // namespace ag2gs
