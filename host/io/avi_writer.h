// Motion-JPEG AVI files (RIFF AVI 1.0 with an idx1 index), written frame by
// frame: what `ag2gs simulate` writes beside its PNG frames. Our own
// container (the frames are JPEG-encoded by OpenCV's imgcodecs) instead of
// OpenCV's video module, whose dependencies (FFmpeg, GStreamer and about a
// hundred more libraries) every run of the program would load for this one
// writer.
#pragma once

#include <cstdint>
#include <fstream>
#include <string>
#include <vector>

namespace ag2gs {

class MjpegAviWriter {
 public:
  // Creates `path` for frames of width x height at `fps` frames a second.
  // Throws std::runtime_error naming the file when it cannot be written,
  // std::invalid_argument for a size or rate out of range.
  // Frames that would take the file past max_bytes are left out.
  MjpegAviWriter(const std::string& path, int width, int height, double fps, int jpeg_quality = 95,
                 int64_t max_bytes = int64_t{1} << 30);
  ~MjpegAviWriter();  // closes (finishes the headers) if close() was not called; never throws
  MjpegAviWriter(const MjpegAviWriter&) = delete;
  MjpegAviWriter& operator=(const MjpegAviWriter&) = delete;

  // [H,W,3] floats in [0,1] (clamped), rows top to bottom: JPEG-encoded at
  // the writer's quality and appended.
  void write_rgb(const std::vector<float>& rgb);
  // A frame already encoded as one JPEG image of the writer's size. Frames
  // that would take the file past max_bytes are left out (a warning, once).
  void write_jpeg(const std::vector<unsigned char>& jpeg);
  // Writes the index and the final sizes and frame count; the file is
  // complete afterwards. Throws naming the file on an I/O error.
  void close();

  int frames() const { return static_cast<int>(index_.size()); }  // in the file
  int dropped() const { return dropped_; }                        // left out at the size limit

 private:
  struct Entry {
    uint32_t offset, size;  // the chunk's offset from the 'movi' fourcc, its data's size
  };
  void put32(uint32_t v);
  void put16(uint16_t v);
  void fourcc(const char* c);
  void patch32(std::streamoff at, uint32_t v);

  std::string path_;
  std::ofstream out_;
  int width_, height_, quality_;
  int64_t max_bytes_;
  uint32_t rate_, scale_;
  std::streamoff riff_size_at_ = 0, frames_at_ = 0, length_at_ = 0, movi_size_at_ = 0, movi_at_ = 0;
  std::streamoff suggested_at_[2] = {0, 0};
  uint32_t largest_ = 0;
  std::vector<Entry> index_;
  bool closed_ = false;
  int dropped_ = 0;  // frames left out at the size limit; the file is full once one is
};

}  // namespace ag2gs
