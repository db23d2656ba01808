// Image output: PNGs written atomically (temp file + rename).
#pragma once

#include <opencv2/core.hpp>
#include <string>
#include <vector>

namespace ag2gs {

// [H,W,3] floats in [0,1] -> 8-bit BGR (OpenCV's order): clamped, rounded,
// non-finite values 0. What write_rgb_png writes and the videos encode.
cv::Mat rgb_to_bgr8(const std::vector<float>& rgb, int width, int height);
// [H,W,3] floats in [0,1] -> 8-bit sRGB-as-is PNG (values clamped).
void write_rgb_png(const std::string& path, const std::vector<float>& rgb, int width, int height);
// [H,W] floats times `scale`, clamped to [0, 65535] -> 16-bit grey PNG.
void write_gray16_png(const std::string& path, const std::vector<float>& img, int width, int height, float scale);
// Reads any image OpenCV can decode as [H,W,3] floats in [0,1]. Throws naming the file.
std::vector<float> read_rgb(const std::string& path, int& width, int& height);

// Whether `bytes` are a JPEG (FF D8 ...) whose image data stops before its
// end-of-image marker (FF D9): a file cut short by a failed copy or
// download, which decoders accept with grey or missing rows. The markers
// are walked from the start, so a thumbnail's own markers inside APP1 do
// not count; data after the end marker (motion photos) is allowed.
bool jpeg_is_truncated(const std::vector<unsigned char>& bytes);

}  // namespace ag2gs
