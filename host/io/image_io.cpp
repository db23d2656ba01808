#include "host/io/image_io.h"

#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <stdexcept>

#include "host/io/atomic_file.h"
#include "host/io/output_set.h"

namespace ag2gs {

namespace {

void write_atomic(const std::string& path, const cv::Mat& img) {
  namespace fs = std::filesystem;
  fs::path p(path);
  remove_stale_temp_files_once(p.parent_path().string());
  std::string tmp =
      (p.parent_path() / ("." + p.filename().string() + ".tmp." + std::to_string(::getpid()) + ".png")).string();
  bool ok = false;
  try {
    ok = cv::imwrite(tmp, img);
  } catch (const cv::Exception& e) {
    ok = false;
  }
  if (!ok) {
    std::error_code ec;
    fs::remove(tmp, ec);
    throw std::runtime_error(path + ": could not write the image (is the directory writable and the disk not full?)");
  }
  if (OutputSet::defer(tmp, path)) return;  // moves with the rest of its set (host/io/output_set.h)
  std::error_code ec;
  fs::rename(tmp, p, ec);
  if (ec) {
    fs::remove(tmp, ec);
    throw std::runtime_error(path + ": could not move the finished image into place: " + ec.message());
  }
}

}  // namespace

cv::Mat rgb_to_bgr8(const std::vector<float>& rgb, int width, int height) {
  cv::Mat img(height, width, CV_8UC3);
  for (int y = 0; y < height; ++y)
    for (int x = 0; x < width; ++x) {
      const float* p = &rgb[(static_cast<size_t>(y) * width + x) * 3];
      auto q = [](float v) {
        return static_cast<uint8_t>(std::lround(std::clamp(std::isfinite(v) ? v : 0.f, 0.f, 1.f) * 255.f));
      };
      img.at<cv::Vec3b>(y, x) = cv::Vec3b(q(p[2]), q(p[1]), q(p[0]));  // OpenCV is BGR
    }
  return img;
}

void write_rgb_png(const std::string& path, const std::vector<float>& rgb, int width, int height) {
  if (rgb.size() != static_cast<size_t>(width) * height * 3)
    throw std::invalid_argument(path + ": image buffer size does not match " + std::to_string(width) + "x" +
                                std::to_string(height) + "x3");
  write_atomic(path, rgb_to_bgr8(rgb, width, height));
}

void write_gray16_png(const std::string& path, const std::vector<float>& v, int width, int height, float scale) {
  if (v.size() != static_cast<size_t>(width) * height)
    throw std::invalid_argument(path + ": image buffer size does not match " + std::to_string(width) + "x" +
                                std::to_string(height));
  cv::Mat img(height, width, CV_16UC1);
  for (int y = 0; y < height; ++y)
    for (int x = 0; x < width; ++x) {
      float f = v[static_cast<size_t>(y) * width + x] * scale;
      img.at<uint16_t>(y, x) = static_cast<uint16_t>(std::lround(std::clamp(std::isfinite(f) ? f : 0.f, 0.f, 65535.f)));
    }
  write_atomic(path, img);
}

std::vector<float> read_rgb(const std::string& path, int& width, int& height) {
  cv::Mat img = cv::imread(path, cv::IMREAD_COLOR);
  if (img.empty())
    throw std::runtime_error(path + ": cannot read the image (missing, or a format OpenCV cannot decode)");
  width = img.cols;
  height = img.rows;
  std::vector<float> out(static_cast<size_t>(width) * height * 3);
  for (int y = 0; y < height; ++y)
    for (int x = 0; x < width; ++x) {
      cv::Vec3b c = img.at<cv::Vec3b>(y, x);
      float* p = &out[(static_cast<size_t>(y) * width + x) * 3];
      p[0] = c[2] / 255.f;
      p[1] = c[1] / 255.f;
      p[2] = c[0] / 255.f;
    }
  return out;
}

bool jpeg_is_truncated(const std::vector<unsigned char>& b) {
  const size_t n = b.size();
  if (n < 4 || b[0] != 0xFF || b[1] != 0xD8) return false;  // not a JPEG
  // Segments with a length up to the first start of scan (FF DA).
  size_t i = 2;
  while (true) {
    while (i < n && b[i] == 0xFF && i + 1 < n && b[i + 1] == 0xFF) ++i;  // fill bytes
    if (i + 4 > n || b[i] != 0xFF) return true;                          // cut inside the headers
    const unsigned char marker = b[i + 1];
    if (marker == 0xD9) return false;  // an image with no scan: not ours to judge
    const size_t len = (static_cast<size_t>(b[i + 2]) << 8) | b[i + 3];
    if (len < 2) return true;
    i += 2 + len;
    if (marker == 0xDA) break;
    if (i > n) return true;
  }
  // Entropy-coded data: FF is followed by 00 (stuffing), D0-D7 (restart) or
  // a marker; the image ends at the first FF D9.
  for (; i + 1 < n; ++i)
    if (b[i] == 0xFF && b[i + 1] == 0xD9) return false;
  return true;
}

}  // namespace ag2gs
