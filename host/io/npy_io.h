// NumPy .npy files (format versions 1.0, 2.0 and 3.0), the container of the
// LangSplat / OpenGaussian language features (docs/formats.md).
// Spec: https://numpy.org/doc/stable/reference/generated/numpy.lib.format.html
#pragma once

#include <cstdint>
#include <string>
#include <vector>

namespace ag2gs {

// A dense C-order array converted to float32.
struct NpyArray {
  std::vector<int64_t> shape;  // empty = a scalar (one element)
  std::vector<float> data;     // row-major, product(shape) elements

  int64_t dim(size_t i) const { return shape.at(i); }
  size_t size() const { return data.size(); }
};

// Reads `path`. Accepts little- and big-endian float16/float32/float64,
// signed and unsigned integers of 1, 2, 4 and 8 bytes and bool, converting to
// float32; Fortran order is transposed into C order. Throws
// std::runtime_error naming the file and what is wrong: not an npy file,
// unsupported version or dtype (e.g. object arrays), a malformed header, a
// shape whose element count overflows or disagrees with the file size
// (truncated data). Never reads past the file.
NpyArray read_npy(const std::string& path);

// Writes a float32 little-endian C-order array (format 1.0, header padded to
// 64 bytes). Atomic: written to "<path>.tmp.<pid>" and renamed over `path`
// only when complete; on failure the temporary file is removed, an existing
// `path` is left as it was, and std::runtime_error says why. Throws
// std::invalid_argument when data.size() != product(shape).
void write_npy(const std::string& path, const std::vector<float>& data, const std::vector<int64_t>& shape);

}  // namespace ag2gs
