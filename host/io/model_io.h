// The native model file: everything ag2gs needs to resume training and to run
// queries (anchors, children, features, graph, clusters, language features,
// optimiser state, configuration), as named typed arrays plus JSON metadata.
//
// Layout of MODEL_DIR/model.ag2gs (all integers little-endian):
//   8 bytes   magic "AG2GSMDL"
//   u32       format version (kModelFormatVersion)
//   u32       reserved, 0
//   u64       header length L
//   L bytes   JSON header: {"meta": {...}, "arrays": [{"name", "dtype",
//             "shape", "offset", "bytes", "fnv1a64"}, ...]}
//   u64       FNV-1a 64 of the header bytes
//   data      each array's bytes at header offset + its "offset", 8-aligned
// Every array carries a checksum, so a corrupt or truncated file is detected
// on load, never half-read into a model. Files are written atomically.
#pragma once

#include <cstdint>
#include <map>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

namespace ag2gs {

constexpr uint32_t kModelFormatVersion = 1;

enum class DType { f32, f64, i32, u32, i64, u64, u8 };
const char* dtype_name(DType t);
size_t dtype_size(DType t);

// One array: raw little-endian bytes of `dtype`, C order.
struct Tensor {
  DType dtype = DType::f32;
  std::vector<int64_t> shape;
  std::vector<uint8_t> bytes;

  int64_t elements() const;
};

class ModelArchive {
 public:
  nlohmann::json meta = nlohmann::json::object();

  // Store an array; `shape` must multiply to data.size() (std::invalid_argument).
  template <typename T>
  void put(const std::string& name, const std::vector<T>& data, std::vector<int64_t> shape = {});
  // The array `name` as T (the stored dtype must be T's); with a non-empty
  // `expect_shape` (-1 = any extent) the shape is checked. Throws
  // std::runtime_error naming the archive's source file otherwise.
  template <typename T>
  std::vector<T> get(const std::string& name, const std::vector<int64_t>& expect_shape = {}) const;

  bool has(const std::string& name) const { return arrays_.count(name) != 0; }
  const Tensor& tensor(const std::string& name) const;
  const std::map<std::string, Tensor>& arrays() const { return arrays_; }
  void put_tensor(const std::string& name, Tensor t);

  // Where the archive was read from (for error messages), empty when built in memory.
  std::string source;

 private:
  std::map<std::string, Tensor> arrays_;
};

// Writes `archive` to `path` atomically ("<path>.tmp.<pid>" + rename); on
// failure an existing `path` is untouched and std::runtime_error says why.
void write_model_archive(const std::string& path, const ModelArchive& archive);

// Reads and fully validates an archive (magic, version, header, sizes,
// checksums). Throws std::runtime_error naming the file and what is wrong:
// not an ag2gs model, a model of another format version (saying which version
// this build reads), a truncated or corrupt file.
ModelArchive read_model_archive(const std::string& path);

// Only the JSON metadata of an archive (magic, version and the header
// checksum checked; the arrays are not read): cheap on a large model.
nlohmann::json read_model_meta(const std::string& path);

// FNV-1a 64-bit hash (also used for the checksums).
uint64_t fnv1a64(const void* data, size_t size, uint64_t seed = 0xcbf29ce484222325ull);

}  // namespace ag2gs
