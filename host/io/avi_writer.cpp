#include "host/io/avi_writer.h"

#include <spdlog/spdlog.h>

#include <algorithm>
#include <cmath>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <stdexcept>

#include "host/io/image_io.h"

namespace ag2gs {

namespace {
constexpr uint32_t kHasIndex = 0x10;  // avih dwFlags: AVIF_HASINDEX
constexpr uint32_t kKeyFrame = 0x10;  // idx1 dwFlags: AVIIF_KEYFRAME (every JPEG is one)
}  // namespace

// The file, little-endian, with the sizes that depend on the frames
// written as placeholders until close():
//   RIFF 'AVI '
//     LIST 'hdrl'
//       avih  (56 bytes: frame period, flags, frames, streams, size)
//       LIST 'strl'
//         strh  (56 bytes: 'vids' 'MJPG', scale and rate, length)
//         strf  (40 bytes: BITMAPINFOHEADER, compression 'MJPG')
//     LIST 'movi'
//       00dc  (one JPEG per frame, padded to an even size)
//     idx1  (16 bytes a frame: '00dc', key frame, offset from 'movi', size)
MjpegAviWriter::MjpegAviWriter(const std::string& path, int width, int height, double fps, int jpeg_quality,
                               int64_t max_bytes)
    : path_(path), width_(width), height_(height), quality_(jpeg_quality), max_bytes_(max_bytes) {
  if (max_bytes < 1024 || max_bytes > (int64_t{1} << 31))
    throw std::invalid_argument("video " + path + ": a size limit of " + std::to_string(max_bytes) +
                                " bytes; give 1 KiB to 2 GiB");
  if (width < 1 || height < 1 || width > 65535 || height > 65535)
    throw std::invalid_argument("video " + path + ": frames of " + std::to_string(width) + "x" +
                                std::to_string(height) + " pixels; sides must be 1 to 65535");
  if (!(fps > 0) || !(fps <= 1e6))
    throw std::invalid_argument("video " + path + ": " + std::to_string(fps) +
                                " frames a second; give a rate in (0, 1e6]");
  if (jpeg_quality < 1 || jpeg_quality > 100)
    throw std::invalid_argument("video " + path + ": JPEG quality " + std::to_string(jpeg_quality) +
                                " is not in 1..100");
  // Rate / scale frames a second: whole rates exactly, others to 1/1000.
  if (std::abs(fps - std::round(fps)) < 1e-9) {
    rate_ = static_cast<uint32_t>(std::round(fps));
    scale_ = 1;
  } else {
    rate_ = static_cast<uint32_t>(std::max(1.0, std::round(fps * 1000)));
    scale_ = 1000;
  }
  out_.open(path, std::ios::binary | std::ios::trunc);
  if (!out_) throw std::runtime_error("video " + path + ": cannot be created");
  const uint32_t w = static_cast<uint32_t>(width), h = static_cast<uint32_t>(height);
  fourcc("RIFF");
  riff_size_at_ = out_.tellp();
  put32(0);
  fourcc("AVI ");
  fourcc("LIST");
  put32(4 + (8 + 56) + (8 + 4 + (8 + 56) + (8 + 40)));
  fourcc("hdrl");
  fourcc("avih");
  put32(56);
  put32(static_cast<uint32_t>(std::round(1e6 * scale_ / rate_)));  // microseconds a frame
  put32(0);                                                        // max bytes a second (unknown)
  put32(0);                                                        // padding granularity
  put32(kHasIndex);
  frames_at_ = out_.tellp();
  put32(0);  // total frames
  put32(0);  // initial frames
  put32(1);  // streams
  suggested_at_[0] = out_.tellp();
  put32(0);  // suggested buffer size: the largest frame
  put32(w);
  put32(h);
  for (int i = 0; i < 4; ++i) put32(0);
  fourcc("LIST");
  put32(4 + (8 + 56) + (8 + 40));
  fourcc("strl");
  fourcc("strh");
  put32(56);
  fourcc("vids");
  fourcc("MJPG");
  put32(0);  // flags
  put16(0);  // priority
  put16(0);  // language
  put32(0);  // initial frames
  put32(scale_);
  put32(rate_);
  put32(0);  // start
  length_at_ = out_.tellp();
  put32(0);  // length in frames
  suggested_at_[1] = out_.tellp();
  put32(0);            // suggested buffer size
  put32(0xFFFFFFFFu);  // quality: default
  put32(0);            // sample size: varies
  put16(0);
  put16(0);
  put16(static_cast<uint16_t>(w));
  put16(static_cast<uint16_t>(h));
  fourcc("strf");
  put32(40);
  put32(40);  // biSize
  put32(w);
  put32(h);
  put16(1);   // planes
  put16(24);  // bits a pixel once decoded
  fourcc("MJPG");
  put32(static_cast<uint32_t>(std::min<uint64_t>(uint64_t{w} * h * 3, 0xFFFFFFFFu)));  // decoded bytes
  for (int i = 0; i < 4; ++i) put32(0);  // resolution, colours used, important
  fourcc("LIST");
  movi_size_at_ = out_.tellp();
  put32(0);
  movi_at_ = out_.tellp();
  fourcc("movi");
  if (!out_) throw std::runtime_error("video " + path + ": write failed (disk full?)");
}

MjpegAviWriter::~MjpegAviWriter() {
  if (closed_) return;
  try {
    close();
  } catch (const std::exception& e) {
    spdlog::warn("{}", e.what());
  }
}

void MjpegAviWriter::put32(uint32_t v) {
  const char b[4] = {static_cast<char>(v & 0xFF), static_cast<char>((v >> 8) & 0xFF),
                     static_cast<char>((v >> 16) & 0xFF), static_cast<char>((v >> 24) & 0xFF)};
  out_.write(b, 4);
}

void MjpegAviWriter::put16(uint16_t v) {
  const char b[2] = {static_cast<char>(v & 0xFF), static_cast<char>((v >> 8) & 0xFF)};
  out_.write(b, 2);
}

void MjpegAviWriter::fourcc(const char* c) {
  out_.write(c, 4);
}

void MjpegAviWriter::patch32(std::streamoff at, uint32_t v) {
  out_.seekp(at);
  put32(v);
}

void MjpegAviWriter::write_rgb(const std::vector<float>& rgb) {
  const size_t want = static_cast<size_t>(width_) * height_ * 3;
  if (rgb.size() != want)
    throw std::invalid_argument("video " + path_ + ": a frame of " + std::to_string(rgb.size()) + " values, not " +
                                std::to_string(want) + " (" + std::to_string(width_) + "x" + std::to_string(height_) +
                                "x3)");
  std::vector<unsigned char> jpeg;  // the PNG frames' 8 bits, JPEG-encoded
  if (!cv::imencode(".jpg", rgb_to_bgr8(rgb, width_, height_), jpeg, {cv::IMWRITE_JPEG_QUALITY, quality_}))
    throw std::runtime_error("video " + path_ + ": a frame could not be encoded as JPEG");
  write_jpeg(jpeg);
}

void MjpegAviWriter::write_jpeg(const std::vector<unsigned char>& jpeg) {
  if (closed_) throw std::logic_error("video " + path_ + ": a frame after close()");
  if (jpeg.size() < 4 || jpeg[0] != 0xFF || jpeg[1] != 0xD8)
    throw std::invalid_argument("video " + path_ + ": a frame that is not a JPEG image");
  const std::streamoff at = out_.tellp();
  // RIFF sizes are 32-bit, and players read the first 1 GiB of an AVI 1.0
  // file reliably (the default limit): a longer run keeps its first frames
  // in the video (the PNGs beside it hold them all) rather than failing
  // after the work.
  const int64_t chunk = 8 + static_cast<int64_t>(jpeg.size() + jpeg.size() % 2);
  const int64_t index = 8 + 16 * static_cast<int64_t>(index_.size() + 1);  // idx1 with this frame
  if (dropped_ > 0 || static_cast<int64_t>(at) + chunk + index > max_bytes_) {
    if (dropped_ == 0)
      spdlog::warn(
          "video {}: its size limit ({}) reached after {} frames; the later frames are in the PNGs only", path_,
          max_bytes_ >= (1 << 20) ? std::to_string(max_bytes_ >> 20) + " MiB" : std::to_string(max_bytes_) + " bytes",
          index_.size());
    ++dropped_;
    return;
  }
  fourcc("00dc");
  put32(static_cast<uint32_t>(jpeg.size()));
  out_.write(reinterpret_cast<const char*>(jpeg.data()), static_cast<std::streamsize>(jpeg.size()));
  if (jpeg.size() % 2) out_.put('\0');
  if (!out_) throw std::runtime_error("video " + path_ + ": write failed (disk full?)");
  index_.push_back({static_cast<uint32_t>(at - movi_at_), static_cast<uint32_t>(jpeg.size())});
  largest_ = std::max(largest_, static_cast<uint32_t>(jpeg.size()));
}

void MjpegAviWriter::close() {
  if (closed_) return;
  closed_ = true;
  const std::streamoff movi_end = out_.tellp();
  fourcc("idx1");
  put32(static_cast<uint32_t>(16 * index_.size()));
  for (const Entry& e : index_) {
    fourcc("00dc");
    put32(kKeyFrame);
    put32(e.offset);
    put32(e.size);
  }
  const std::streamoff end = out_.tellp();
  const uint32_t n = static_cast<uint32_t>(index_.size());
  patch32(riff_size_at_, static_cast<uint32_t>(end - 8));
  patch32(frames_at_, n);
  patch32(length_at_, n);
  patch32(suggested_at_[0], largest_ + 8);
  patch32(suggested_at_[1], largest_ + 8);
  patch32(movi_size_at_, static_cast<uint32_t>(movi_end - movi_at_));
  out_.close();
  if (!out_) throw std::runtime_error("video " + path_ + ": write failed (disk full?)");
}

}  // namespace ag2gs
