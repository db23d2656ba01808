#include "host/io/model_io.h"

#include <unistd.h>

#include <cerrno>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <limits>
#include <stdexcept>

#include "host/io/atomic_file.h"
#include "host/io/json_input.h"

namespace ag2gs {
namespace {

namespace fs = std::filesystem;

constexpr char kMagic[8] = {'A', 'G', '2', 'G', 'S', 'M', 'D', 'L'};
constexpr size_t kPrefix = 8 + 4 + 4 + 8;  // magic, version, reserved, header length

[[noreturn]] void fail(const std::string& path, const std::string& what) {
  throw std::runtime_error(path + ": " + what);
}

// The archive dtype of each element type put()/get() accept.
template <typename T>
struct DTypeOf;
#define AG2GS_DTYPE_OF(T, D)                 \
  template <>                                \
  struct DTypeOf<T> {                        \
    static constexpr DType value = DType::D; \
  };
AG2GS_DTYPE_OF(float, f32)
AG2GS_DTYPE_OF(double, f64)
AG2GS_DTYPE_OF(int32_t, i32)
AG2GS_DTYPE_OF(uint32_t, u32)
AG2GS_DTYPE_OF(int64_t, i64)
AG2GS_DTYPE_OF(uint64_t, u64)
AG2GS_DTYPE_OF(uint8_t, u8)
#undef AG2GS_DTYPE_OF

bool parse_dtype(const std::string& s, DType* t) {
  for (DType d : {DType::f32, DType::f64, DType::i32, DType::u32, DType::i64, DType::u64, DType::u8}) {
    if (s == dtype_name(d)) {
      *t = d;
      return true;
    }
  }
  return false;
}

void put_u32(std::string& out, uint32_t v) {
  for (int i = 0; i < 4; ++i) out.push_back(static_cast<char>((v >> (8 * i)) & 0xff));
}
void put_u64(std::string& out, uint64_t v) {
  for (int i = 0; i < 8; ++i) out.push_back(static_cast<char>((v >> (8 * i)) & 0xff));
}
uint64_t get_le(const unsigned char* p, int bytes) {
  uint64_t v = 0;
  for (int i = 0; i < bytes; ++i) v |= uint64_t(p[i]) << (8 * i);
  return v;
}

std::string shape_str(const std::vector<int64_t>& shape) {
  std::string s = "[";
  for (size_t i = 0; i < shape.size(); ++i) s += (i ? "," : "") + std::to_string(shape[i]);
  return s + "]";
}

// Element count of a shape, or -1 when an extent is negative or it overflows.
int64_t checked_elements(const std::vector<int64_t>& shape) {
  int64_t n = 1;
  for (int64_t d : shape) {
    if (d < 0) return -1;
    if (d != 0 && n > std::numeric_limits<int64_t>::max() / d) return -1;
    n *= d;
  }
  return n;
}

}  // namespace

const char* dtype_name(DType t) {
  switch (t) {
    case DType::f32:
      return "f32";
    case DType::f64:
      return "f64";
    case DType::i32:
      return "i32";
    case DType::u32:
      return "u32";
    case DType::i64:
      return "i64";
    case DType::u64:
      return "u64";
    case DType::u8:
      return "u8";
  }
  return "?";
}

size_t dtype_size(DType t) {
  switch (t) {
    case DType::f64:
    case DType::i64:
    case DType::u64:
      return 8;
    case DType::u8:
      return 1;
    default:
      return 4;
  }
}

int64_t Tensor::elements() const {
  return checked_elements(shape);
}

uint64_t fnv1a64(const void* data, size_t size, uint64_t seed) {
  const auto* p = static_cast<const unsigned char*>(data);
  uint64_t h = seed;
  for (size_t i = 0; i < size; ++i) {
    h ^= p[i];
    h *= 0x100000001b3ull;
  }
  return h;
}

void ModelArchive::put_tensor(const std::string& name, Tensor t) {
  if (name.empty()) throw std::invalid_argument("ModelArchive: an array needs a name");
  const int64_t n = t.elements();
  if (n < 0 || static_cast<uint64_t>(n) * dtype_size(t.dtype) != t.bytes.size()) {
    throw std::invalid_argument("ModelArchive: array '" + name + "' of shape " + shape_str(t.shape) + " holds " +
                                std::to_string(t.bytes.size()) + " bytes");
  }
  arrays_[name] = std::move(t);
}

const Tensor& ModelArchive::tensor(const std::string& name) const {
  auto it = arrays_.find(name);
  if (it == arrays_.end()) {
    fail(source.empty() ? "model" : source,
         "has no array '" + name + "'; it was written by an incompatible ag2gs or is incomplete");
  }
  return it->second;
}

template <typename T>
void ModelArchive::put(const std::string& name, const std::vector<T>& data, std::vector<int64_t> shape) {
  if (shape.empty()) shape = {static_cast<int64_t>(data.size())};
  Tensor t;
  t.dtype = DTypeOf<T>::value;
  t.shape = std::move(shape);
  t.bytes.resize(data.size() * sizeof(T));
  if (!data.empty()) std::memcpy(t.bytes.data(), data.data(), t.bytes.size());  // little-endian hosts only
  put_tensor(name, std::move(t));
}

template <typename T>
std::vector<T> ModelArchive::get(const std::string& name, const std::vector<int64_t>& expect_shape) const {
  const Tensor& t = tensor(name);
  const std::string where = source.empty() ? "model" : source;
  if (t.dtype != DTypeOf<T>::value) {
    fail(where, "array '" + name + "' is " + dtype_name(t.dtype) + ", expected " + dtype_name(DTypeOf<T>::value));
  }
  if (!expect_shape.empty()) {
    bool ok = expect_shape.size() == t.shape.size();
    for (size_t i = 0; ok && i < expect_shape.size(); ++i) ok = expect_shape[i] < 0 || expect_shape[i] == t.shape[i];
    if (!ok) {
      fail(where, "array '" + name + "' has shape " + shape_str(t.shape) + ", expected " + shape_str(expect_shape) +
                      " (-1 = any)");
    }
  }
  std::vector<T> out(t.bytes.size() / sizeof(T));
  if (!out.empty()) std::memcpy(out.data(), t.bytes.data(), t.bytes.size());
  return out;
}

#define AG2GS_INSTANTIATE(T)                                                                           \
  template void ModelArchive::put<T>(const std::string&, const std::vector<T>&, std::vector<int64_t>); \
  template std::vector<T> ModelArchive::get<T>(const std::string&, const std::vector<int64_t>&) const;
AG2GS_INSTANTIATE(float)
AG2GS_INSTANTIATE(double)
AG2GS_INSTANTIATE(int32_t)
AG2GS_INSTANTIATE(uint32_t)
AG2GS_INSTANTIATE(int64_t)
AG2GS_INSTANTIATE(uint64_t)
AG2GS_INSTANTIATE(uint8_t)
#undef AG2GS_INSTANTIATE

void write_model_archive(const std::string& path, const ModelArchive& archive) {
  nlohmann::json arrays = nlohmann::json::array();
  uint64_t offset = 0;
  for (const auto& [name, t] : archive.arrays()) {
    arrays.push_back({{"name", name},
                      {"dtype", dtype_name(t.dtype)},
                      {"shape", t.shape},
                      {"offset", offset},
                      {"bytes", t.bytes.size()},
                      {"fnv1a64", std::to_string(fnv1a64(t.bytes.data(), t.bytes.size()))}});
    offset += (t.bytes.size() + 7) / 8 * 8;
  }
  const nlohmann::json header = {{"meta", archive.meta}, {"arrays", arrays}};
  const std::string text = header.dump();

  std::string prefix(kMagic, 8);
  put_u32(prefix, kModelFormatVersion);
  put_u32(prefix, 0);
  put_u64(prefix, text.size());
  std::string suffix;
  put_u64(suffix, fnv1a64(text.data(), text.size()));

  const fs::path target(path);
  if (target.has_parent_path() && !fs::is_directory(target.parent_path())) {
    fail(path, "cannot write: the folder " + target.parent_path().string() + " does not exist");
  }
  AtomicFile out(path);
  out.write(prefix);
  out.write(text);
  out.write(suffix);
  // Pad so the data section starts 8-aligned.
  const size_t head = prefix.size() + text.size() + suffix.size();
  out.write(std::string((8 - head % 8) % 8, '\0'));
  for (const auto& [name, t] : archive.arrays()) {
    out.write(t.bytes.data(), t.bytes.size());
    out.write(std::string((8 - t.bytes.size() % 8) % 8, '\0'));
  }
  out.commit();
}

namespace {

// Opens `path`, checks magic, version and the header checksum, and returns
// the header text; `in` is left at the end of the header, `size` and
// `header_len` describe the file.
std::string read_header_text(const std::string& path, std::ifstream& in, uint64_t* size_out, uint64_t* header_len_out) {
  if (std::filesystem::is_directory(path))
    fail(path, "is a folder, not a model file; give the folder that holds model.ag2gs");
  in.open(path, std::ios::binary);
  if (!in) fail(path, std::string("cannot open: ") + std::strerror(errno));
  in.seekg(0, std::ios::end);
  const std::streamoff size_off = in.tellg();
  if (size_off < 0) fail(path, "cannot determine the file size");
  const uint64_t size = static_cast<uint64_t>(size_off);
  in.seekg(0);
  unsigned char prefix[kPrefix];
  if (size < kPrefix || !in.read(reinterpret_cast<char*>(prefix), kPrefix)) {
    fail(path, "too short to be an ag2gs model (" + std::to_string(size) + " bytes); it is truncated or not a model");
  }
  if (std::memcmp(prefix, kMagic, 8) != 0) {
    fail(path,
         "not an ag2gs model file (wrong magic bytes); a model folder holds model.ag2gs written by `ag2gs train`");
  }
  const uint32_t version = static_cast<uint32_t>(get_le(prefix + 8, 4));
  if (version != kModelFormatVersion) {
    fail(path, "is a model of format version " + std::to_string(version) + ", but this ag2gs reads version " +
                   std::to_string(kModelFormatVersion) + "; use the ag2gs release that wrote it" +
                   (version > kModelFormatVersion ? " (or a newer one)" : "") +
                   ", or export and retrain from point_cloud.ply");
  }
  const uint64_t header_len = get_le(prefix + 16, 8);
  if (header_len > size - kPrefix || size - kPrefix - header_len < 8) {
    fail(path, "truncated or corrupt: the header length " + std::to_string(header_len) + " exceeds the file");
  }
  std::string text(static_cast<size_t>(header_len), '\0');
  unsigned char sum[8];
  if (!in.read(text.data(), static_cast<std::streamsize>(header_len)) || !in.read(reinterpret_cast<char*>(sum), 8)) {
    fail(path, "read error in the header");
  }
  if (get_le(sum, 8) != fnv1a64(text.data(), text.size())) {
    fail(path, "corrupt: the header checksum does not match; the file was damaged after it was written");
  }
  *size_out = size;
  *header_len_out = header_len;
  return text;
}

}  // namespace

nlohmann::json read_model_meta(const std::string& path) {
  std::ifstream in;
  uint64_t size = 0, header_len = 0;
  const std::string text = read_header_text(path, in, &size, &header_len);
  try {
    return parse_json_input(text, path).at("meta");
  } catch (const std::exception& e) {
    fail(path, std::string("corrupt header: ") + e.what());
  }
}

ModelArchive read_model_archive(const std::string& path) {
  std::ifstream in;
  uint64_t size = 0, header_len = 0;
  const std::string text = read_header_text(path, in, &size, &header_len);
  const uint64_t head = kPrefix + header_len + 8;
  const uint64_t data_start = (head + 7) / 8 * 8;

  ModelArchive archive;
  archive.source = path;
  nlohmann::json header;
  try {
    header = parse_json_input(text, path);
    archive.meta = header.at("meta");
    const nlohmann::json& arrays = header.at("arrays");
    if (!arrays.is_array()) throw std::runtime_error("'arrays' is not a list");
    for (const nlohmann::json& a : arrays) {
      const std::string name = a.at("name").get<std::string>();
      Tensor t;
      if (!parse_dtype(a.at("dtype").get<std::string>(), &t.dtype)) {
        throw std::runtime_error("array '" + name + "' has unknown dtype");
      }
      t.shape = a.at("shape").get<std::vector<int64_t>>();
      const uint64_t offset = a.at("offset").get<uint64_t>();
      const uint64_t bytes = a.at("bytes").get<uint64_t>();
      const uint64_t expect = std::stoull(a.at("fnv1a64").get<std::string>());
      const int64_t n = t.elements();
      if (n < 0 || static_cast<uint64_t>(n) > std::numeric_limits<uint64_t>::max() / 8 ||
          static_cast<uint64_t>(n) * dtype_size(t.dtype) != bytes) {
        throw std::runtime_error("array '" + name + "' has shape " + shape_str(t.shape) + " but " +
                                 std::to_string(bytes) + " bytes");
      }
      if (offset > size || data_start > size - offset || bytes > size - data_start - offset) {
        fail(path, "truncated: array '" + name + "' lies beyond the end of the file (" + std::to_string(size) +
                       " bytes); the write was interrupted or the file was cut");
      }
      t.bytes.resize(static_cast<size_t>(bytes));
      in.seekg(static_cast<std::streamoff>(data_start + offset));
      if (bytes && !in.read(reinterpret_cast<char*>(t.bytes.data()), static_cast<std::streamsize>(bytes))) {
        fail(path, "read error in array '" + name + "'");
      }
      if (fnv1a64(t.bytes.data(), t.bytes.size()) != expect) {
        fail(path, "corrupt: the checksum of array '" + name + "' does not match");
      }
      if (archive.has(name)) throw std::runtime_error("array '" + name + "' appears twice");
      archive.put_tensor(name, std::move(t));
    }
  } catch (const std::runtime_error& e) {
    const std::string msg = e.what();
    if (msg.rfind(path + ":", 0) == 0) throw;
    fail(path, "corrupt header: " + msg);
  } catch (const std::exception& e) {
    fail(path, std::string("corrupt header: ") + e.what());
  }
  return archive;
}

}  // namespace ag2gs
