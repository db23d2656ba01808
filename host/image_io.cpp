#include "host/image_io.h"

#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <stdexcept>

namespace ag2gs {

namespace {

void write_atomic(const std::string& path, const cv::Mat& img) {
  namespace fs = std::filesystem;
  fs::path p(path);
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
  std::error_code ec;
  fs::rename(tmp, p, ec);
  if (ec) {
    fs::remove(tmp, ec);
    throw std::runtime_error(path + ": could not move the finished image into place: " + ec.message());
  }
}

}  // namespace

void write_rgb_png(const std::string& path, const std::vector<float>& rgb, int width, int height) {
  if (rgb.size() != static_cast<size_t>(width) * height * 3)
    throw std::invalid_argument(path + ": image buffer size does not match " + std::to_string(width) + "x" +
                                std::to_string(height) + "x3");
  cv::Mat img(height, width, CV_8UC3);
  for (int y = 0; y < height; ++y)
    for (int x = 0; x < width; ++x) {
      const float* p = &rgb[(static_cast<size_t>(y) * width + x) * 3];
      auto q = [](float v) {
        return static_cast<uint8_t>(std::lround(std::clamp(std::isfinite(v) ? v : 0.f, 0.f, 1.f) * 255.f));
      };
      img.at<cv::Vec3b>(y, x) = cv::Vec3b(q(p[2]), q(p[1]), q(p[0]));  // OpenCV is BGR
    }
  write_atomic(path, img);
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

}  // namespace ag2gs
