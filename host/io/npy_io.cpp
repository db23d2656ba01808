// NumPy .npy reader (versions 1.0, 2.0, 3.0) and atomic float32 writer.
// Layout: magic "\x93NUMPY", major and minor version bytes, the header length
// (uint16 LE for 1.0, uint32 LE for 2.0/3.0), then the header: a Python dict
// literal {'descr': ..., 'fortran_order': ..., 'shape': (...), } padded with
// spaces and a final '\n', then the raw array data.
#include "host/io/npy_io.h"

#include <algorithm>
#include <cctype>
#include <cerrno>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <limits>
#include <stdexcept>
#include <string>
#include <vector>

#include "host/io/atomic_file.h"

namespace ag2gs {
namespace {

namespace fs = std::filesystem;

constexpr char kMagic[] = "\x93NUMPY";
constexpr size_t kMagicLen = 6;
constexpr const char* kSaveHint = "save it with numpy.save(path, array.astype(numpy.float32))";

[[noreturn]] void fail(const std::string& path, const std::string& what) {
  throw std::runtime_error(path + ": " + what);
}

// ---------------------------------------------------------------- header dict

// The subset of Python literals a .npy header uses: a dict of strings,
// booleans, integers and tuples (lists and None are parsed so that their
// presence can be reported, not silently misread).
struct PyValue {
  enum class Kind { Str, Bool, Int, Tuple, List, Dict, None } kind = Kind::None;
  std::string str;       // Str
  bool boolean = false;  // Bool
  // Int: the magnitude saturates at `int_overflow`; the sign is kept apart so
  // that a negative dimension and an overflowing one get different messages.
  bool negative = false;
  bool int_overflow = false;
  int64_t integer = 0;
  std::vector<PyValue> items;                            // Tuple, List
  std::vector<std::pair<std::string, PyValue>> entries;  // Dict (string keys)
};

class HeaderParser {
 public:
  HeaderParser(const std::string& path, const std::string& text) : path_(path), text_(text) {}

  PyValue parse() {
    skip_space();
    PyValue v = value(0);
    skip_space();
    if (pos_ != text_.size()) bad("unexpected text after the closing '}'");
    if (v.kind != PyValue::Kind::Dict) bad("the header is not a dict");
    return v;
  }

 private:
  static constexpr int kMaxDepth = 8;  // a .npy header nests at most dict -> tuple

  [[noreturn]] void bad(const std::string& what) const {
    std::string shown = text_.substr(0, 200);
    for (char& c : shown) {
      if (static_cast<unsigned char>(c) < 0x20 || static_cast<unsigned char>(c) >= 0x7f) c = '?';
    }
    fail(path_, "malformed .npy header (" + what + " at character " + std::to_string(pos_) + " of \"" + shown +
                    (text_.size() > 200 ? "...\"" : "\"") + "); the file is corrupt or not written by numpy.save");
  }

  void skip_space() {
    while (pos_ < text_.size() && (text_[pos_] == ' ' || text_[pos_] == '\t' || text_[pos_] == '\n' ||
                                   text_[pos_] == '\r' || text_[pos_] == '\f' || text_[pos_] == '\v')) {
      ++pos_;
    }
  }
  bool peek(char c) {
    skip_space();
    return pos_ < text_.size() && text_[pos_] == c;
  }
  void expect(char c) {
    if (!peek(c)) bad(std::string("expected '") + c + "'");
    ++pos_;
  }
  bool word(const char* w) {
    const size_t n = std::strlen(w);
    if (text_.compare(pos_, n, w) != 0) return false;
    // Not a prefix of a longer identifier ("Truex").
    if (pos_ + n < text_.size()) {
      const char next = text_[pos_ + n];
      if (std::isalnum(static_cast<unsigned char>(next)) || next == '_') return false;
    }
    pos_ += n;
    return true;
  }

  PyValue value(int depth) {
    if (depth > kMaxDepth) bad("nesting too deep");
    skip_space();
    if (pos_ >= text_.size()) bad("unexpected end of the header");
    const char c = text_[pos_];
    PyValue v;
    if (c == '\'' || c == '"') {
      v.kind = PyValue::Kind::Str;
      v.str = string_literal();
    } else if (c == '{') {
      v.kind = PyValue::Kind::Dict;
      ++pos_;
      while (!peek('}')) {
        PyValue key = value(depth + 1);
        if (key.kind != PyValue::Kind::Str) bad("a dict key is not a string");
        expect(':');
        PyValue item = value(depth + 1);
        v.entries.emplace_back(key.str, std::move(item));
        if (!peek(',')) break;
        ++pos_;
      }
      expect('}');
    } else if (c == '(' || c == '[') {
      const char close = c == '(' ? ')' : ']';
      v.kind = c == '(' ? PyValue::Kind::Tuple : PyValue::Kind::List;
      ++pos_;
      bool had_comma = false;
      while (!peek(close)) {
        v.items.push_back(value(depth + 1));
        had_comma = peek(',');
        if (!had_comma) break;
        ++pos_;
      }
      expect(close);
      // "(3)" is a parenthesised integer in Python, not a tuple.
      if (v.kind == PyValue::Kind::Tuple && v.items.size() == 1 && !had_comma) {
        PyValue inner = std::move(v.items[0]);
        return inner;
      }
    } else if (c == '-' || c == '+' || (c >= '0' && c <= '9')) {
      v.kind = PyValue::Kind::Int;
      integer_literal(&v);
    } else if (word("True")) {
      v.kind = PyValue::Kind::Bool;
      v.boolean = true;
    } else if (word("False")) {
      v.kind = PyValue::Kind::Bool;
    } else if (word("None")) {
      v.kind = PyValue::Kind::None;
    } else {
      bad(std::string("unexpected character '") + (std::isprint(static_cast<unsigned char>(c)) ? c : '?') + "'");
    }
    return v;
  }

  std::string string_literal() {
    const char quote = text_[pos_++];
    std::string s;
    while (true) {
      if (pos_ >= text_.size()) bad("unterminated string");
      const char c = text_[pos_++];
      if (c == quote) break;
      if (c == '\n') bad("line break inside a string");
      if (c == '\\') {
        if (pos_ >= text_.size()) bad("unterminated string");
        s += text_[pos_++];  // enough for \' \" \\; descr strings hold no other escapes
      } else {
        s += c;
      }
    }
    return s;
  }

  void integer_literal(PyValue* v) {
    if (text_[pos_] == '-' || text_[pos_] == '+') {
      v->negative = text_[pos_] == '-';
      ++pos_;
      skip_space();
    }
    const size_t start = pos_;
    uint64_t magnitude = 0;
    while (pos_ < text_.size() && text_[pos_] >= '0' && text_[pos_] <= '9') {
      const uint64_t digit = static_cast<uint64_t>(text_[pos_] - '0');
      if (magnitude > (uint64_t(std::numeric_limits<int64_t>::max()) - digit) / 10) {
        v->int_overflow = true;
      } else {
        magnitude = magnitude * 10 + digit;
      }
      ++pos_;
    }
    if (pos_ == start) bad("expected digits");
    // Python 2 wrote long integers as "3L".
    if (pos_ < text_.size() && (text_[pos_] == 'L' || text_[pos_] == 'l')) ++pos_;
    if (pos_ < text_.size() && (std::isalnum(static_cast<unsigned char>(text_[pos_])) || text_[pos_] == '.')) {
      bad("not an integer");
    }
    v->integer = static_cast<int64_t>(magnitude);
  }

  const std::string& path_;
  const std::string& text_;
  size_t pos_ = 0;
};

// ---------------------------------------------------------------- dtype

enum class Kind { Bool, Int, UInt, Float };

struct DType {
  Kind kind = Kind::Float;
  int bytes = 4;
  bool big_endian = false;
};

bool host_is_big_endian() {
  const uint16_t probe = 1;
  unsigned char first;
  std::memcpy(&first, &probe, 1);
  return first == 0;
}

[[noreturn]] void unsupported_dtype(const std::string& path, const std::string& descr, const std::string& why) {
  fail(path, "unsupported dtype '" + descr + "' (" + why +
                 "); ag2gs reads bool, integer and float16/32/64 arrays: " + kSaveHint);
}

DType parse_descr(const std::string& path, const std::string& descr) {
  if (descr.size() < 2) unsupported_dtype(path, descr, "not a numpy type string");
  const char order = descr[0];
  const char type = descr[1];
  const std::string size_text = descr.substr(2);
  if (order != '<' && order != '>' && order != '|' && order != '=') {
    unsupported_dtype(path, descr, "unknown byte order");
  }
  switch (type) {
    case 'b':
    case 'i':
    case 'u':
    case 'f':
      break;
    case 'O':
      unsupported_dtype(path, descr, "object arrays hold Python objects, not numbers");
    case 'c':
      unsupported_dtype(path, descr, "complex numbers");
    case 'U':
    case 'S':
    case 'a':
      unsupported_dtype(path, descr, "strings");
    case 'V':
      unsupported_dtype(path, descr, "raw bytes or records");
    case 'M':
    case 'm':
      unsupported_dtype(path, descr, "dates and time deltas");
    default:
      unsupported_dtype(path, descr, "unknown type code");
  }
  DType dt;
  dt.bytes = size_text.size() == 1 && size_text[0] >= '1' && size_text[0] <= '8' ? size_text[0] - '0' : 0;
  const bool power_of_two = dt.bytes == 1 || dt.bytes == 2 || dt.bytes == 4 || dt.bytes == 8;
  if (type == 'b') {
    if (dt.bytes != 1) unsupported_dtype(path, descr, "bool must have 1 byte");
    dt.kind = Kind::Bool;
  } else if (type == 'i' || type == 'u') {
    if (!power_of_two) unsupported_dtype(path, descr, "integers have 1, 2, 4 or 8 bytes");
    dt.kind = type == 'i' ? Kind::Int : Kind::UInt;
  } else {
    if (!power_of_two || dt.bytes == 1) {
      unsupported_dtype(path, descr,
                        size_text == "16" || size_text == "12" ? "long double" : "floats have 2, 4 or 8 bytes");
    }
    dt.kind = Kind::Float;
  }
  if (order == '|' && dt.bytes > 1) {
    unsupported_dtype(path, descr, "'|' (no byte order) is only valid for 1-byte types");
  }
  dt.big_endian = order == '>' || (order == '=' && host_is_big_endian());
  return dt;
}

// IEEE half -> float, exact for every half value.
float half_to_float(uint16_t h) {
  const uint32_t sign = uint32_t(h >> 15) << 31;
  const uint32_t exp = (h >> 10) & 0x1f;
  uint32_t mant = h & 0x3ff;
  uint32_t bits;
  if (exp == 0x1f) {
    bits = sign | 0x7f800000u | (mant << 13);  // inf / nan (payload kept)
  } else if (exp != 0) {
    bits = sign | ((exp + 112) << 23) | (mant << 13);
  } else if (mant == 0) {
    bits = sign;  // +-0
  } else {
    // Subnormal half: normalise into a float.
    int e = -1;
    do {
      ++e;
      mant <<= 1;
    } while ((mant & 0x400) == 0);
    bits = sign | (uint32_t(112 - e) << 23) | ((mant & 0x3ff) << 13);
  }
  float f;
  std::memcpy(&f, &bits, 4);
  return f;
}

// Raw bytes of `count` elements (in file order) -> float32.
void convert(const unsigned char* src, size_t count, const DType& dt, float* dst) {
  const size_t n = static_cast<size_t>(dt.bytes);
  for (size_t i = 0; i < count; ++i) {
    const unsigned char* p = src + i * n;
    uint64_t u = 0;
    if (dt.big_endian) {
      for (size_t b = 0; b < n; ++b) u = (u << 8) | p[b];
    } else {
      for (size_t b = n; b-- > 0;) u = (u << 8) | p[b];
    }
    float v = 0.f;
    switch (dt.kind) {
      case Kind::Bool:
        v = u != 0 ? 1.f : 0.f;
        break;
      case Kind::UInt:
        v = static_cast<float>(u);
        break;
      case Kind::Int: {
        // Sign-extend from n bytes.
        const unsigned shift = static_cast<unsigned>(64 - 8 * n);
        const int64_t s = static_cast<int64_t>(u << shift) >> shift;
        v = static_cast<float>(s);
        break;
      }
      case Kind::Float:
        if (n == 2) {
          v = half_to_float(static_cast<uint16_t>(u));
        } else if (n == 4) {
          const uint32_t w = static_cast<uint32_t>(u);
          std::memcpy(&v, &w, 4);
        } else {
          double d;
          std::memcpy(&d, &u, 8);
          v = static_cast<float>(d);
        }
        break;
    }
    dst[i] = v;
  }
}

// Fortran order (first index fastest) -> C order (last index fastest).
std::vector<float> fortran_to_c(const std::vector<float>& f, const std::vector<int64_t>& full_shape) {
  // Unit dimensions do not change the layout. Without them every dimension is
  // at least 2, so there are at most 64 and the index carry below costs O(1)
  // per element on average; with them, a header of 300k ones made it O(ndim).
  std::vector<int64_t> shape;
  for (int64_t d : full_shape) {
    if (d != 1) shape.push_back(d);
  }
  const size_t ndim = shape.size();
  if (f.empty() || ndim <= 1) return f;
  std::vector<float> c(f.size());
  std::vector<size_t> stride(ndim);  // Fortran strides, in elements
  size_t s = 1;
  for (size_t d = 0; d < ndim; ++d) {
    stride[d] = s;
    s *= static_cast<size_t>(shape[d]);
  }
  std::vector<size_t> index(ndim, 0);
  size_t src = 0;
  for (size_t out = 0; out < c.size(); ++out) {
    c[out] = f[src];
    // Advance the C-order multi-index (last dimension fastest), tracking the Fortran offset.
    for (size_t d = ndim; d-- > 0;) {
      if (++index[d] < static_cast<size_t>(shape[d])) {
        src += stride[d];
        break;
      }
      src -= stride[d] * (index[d] - 1);
      index[d] = 0;
    }
  }
  return c;
}

std::string shape_text(const std::vector<int64_t>& shape) {
  std::string s = "(";
  for (size_t i = 0; i < shape.size(); ++i) s += (i ? ", " : "") + std::to_string(shape[i]);
  return s + (shape.size() == 1 ? ",)" : ")");
}

// ---------------------------------------------------------------- writing

}  // namespace

NpyArray read_npy(const std::string& path) {
  std::error_code ec;
  if (fs::is_directory(path, ec)) fail(path, "is a directory, not a .npy file");
  std::ifstream in(path, std::ios::binary);
  if (!in) fail(path, std::string("cannot open: ") + std::strerror(errno));
  in.seekg(0, std::ios::end);
  const std::streamoff end = in.tellg();
  if (end < 0) fail(path, "cannot determine the file size (not a regular file?)");
  const uint64_t file_size = static_cast<uint64_t>(end);
  in.seekg(0);

  auto read_exact = [&](void* dst, uint64_t bytes, const char* what) {
    in.read(static_cast<char*>(dst), static_cast<std::streamsize>(bytes));
    if (static_cast<uint64_t>(in.gcount()) != bytes) {
      fail(path, std::string("read error in ") + what + " (the file changed while reading?)");
    }
  };

  // Magic and version.
  unsigned char prefix[12];
  if (file_size == 0) fail(path, "not a .npy file: the file is empty (0 bytes)");
  const size_t head = static_cast<size_t>(std::min<uint64_t>(file_size, 8));
  read_exact(prefix, head, "the preamble");
  if (std::memcmp(prefix, kMagic, std::min(head, kMagicLen)) != 0) {
    fail(path, "not a .npy file (missing the \\x93NUMPY magic); expected an array written by numpy.save");
  }
  if (head < 8) fail(path, "truncated .npy header: the file ends after " + std::to_string(head) + " bytes");
  const int major = prefix[6], minor = prefix[7];
  if (!((major == 1 || major == 2 || major == 3) && minor == 0)) {
    fail(path, "unsupported .npy format version " + std::to_string(major) + "." + std::to_string(minor) +
                   " (ag2gs reads 1.0, 2.0 and 3.0); re-save the array with numpy.save");
  }
  const size_t len_bytes = major == 1 ? 2 : 4;
  if (file_size < 8 + len_bytes) fail(path, "truncated .npy header: the file ends inside the header length");
  read_exact(prefix + 8, len_bytes, "the header length");
  uint64_t header_len = uint64_t(prefix[8]) | uint64_t(prefix[9]) << 8;
  if (len_bytes == 4) header_len |= uint64_t(prefix[10]) << 16 | uint64_t(prefix[11]) << 24;
  const uint64_t data_offset = 8 + len_bytes + header_len;
  if (data_offset > file_size) {
    fail(path, "truncated .npy header: it claims " + std::to_string(header_len) + " bytes but the file has only " +
                   std::to_string(file_size - 8 - len_bytes) + " after the preamble");
  }
  std::string header(static_cast<size_t>(header_len), '\0');
  if (header_len > 0) read_exact(&header[0], header_len, "the header");

  // The header dict.
  const PyValue dict = HeaderParser(path, header).parse();
  const PyValue* descr = nullptr;
  const PyValue* fortran = nullptr;
  const PyValue* shape_v = nullptr;
  for (const auto& [key, v] : dict.entries) {
    const PyValue** slot = key == "descr"           ? &descr
                           : key == "fortran_order" ? &fortran
                           : key == "shape"         ? &shape_v
                                                    : nullptr;
    if (!slot) fail(path, "malformed .npy header: unexpected key '" + key + "'");
    if (*slot) fail(path, "malformed .npy header: key '" + key + "' appears twice");
    *slot = &v;
  }
  for (const auto& [ptr, name] : {std::pair{descr, "descr"}, {fortran, "fortran_order"}, {shape_v, "shape"}}) {
    if (!ptr) fail(path, std::string("malformed .npy header: no '") + name + "' key");
  }
  if (descr->kind == PyValue::Kind::List) {
    fail(path, std::string("unsupported dtype: a structured array (record fields); ") + kSaveHint);
  }
  if (descr->kind != PyValue::Kind::Str) fail(path, "malformed .npy header: 'descr' is not a string");
  const DType dtype = parse_descr(path, descr->str);
  if (fortran->kind != PyValue::Kind::Bool) {
    fail(path, "malformed .npy header: 'fortran_order' is not True or False");
  }
  if (shape_v->kind != PyValue::Kind::Tuple) {
    fail(path, "malformed .npy header: 'shape' is not a tuple of integers");
  }

  // Shape and element count, without overflow.
  NpyArray array;
  uint64_t count = 1;
  bool overflow = false;
  for (const PyValue& d : shape_v->items) {
    if (d.kind != PyValue::Kind::Int) fail(path, "malformed .npy header: 'shape' holds a non-integer");
    if (d.negative && (d.integer != 0 || d.int_overflow)) {
      fail(path, "malformed .npy header: negative dimension in 'shape'; the file is corrupt");
    }
    if (d.int_overflow) {
      fail(path, "malformed .npy header: a dimension in 'shape' exceeds 2^63 - 1; the file is corrupt");
    }
    array.shape.push_back(d.integer);
    const uint64_t dim = static_cast<uint64_t>(d.integer);
    if (dim != 0 && count > std::numeric_limits<uint64_t>::max() / dim) {
      overflow = true;
    } else {
      count *= dim;
    }
  }
  const bool has_zero = std::find(array.shape.begin(), array.shape.end(), 0) != array.shape.end();
  if (has_zero) {
    count = 0;
  } else if (overflow || count > std::numeric_limits<uint64_t>::max() / static_cast<uint64_t>(dtype.bytes)) {
    fail(path, "malformed .npy header: shape " + shape_text(array.shape) +
                   " has more elements than any file can hold (the element count overflows); the file is corrupt");
  }
  const uint64_t data_bytes = file_size - data_offset;
  const uint64_t need = count * static_cast<uint64_t>(dtype.bytes);
  if (need != data_bytes) {
    const std::string detail = "shape " + shape_text(array.shape) + " of '" + descr->str + "' needs " +
                               std::to_string(need) + " data bytes but the file holds " + std::to_string(data_bytes);
    if (need > data_bytes) {
      fail(path, "truncated data: " + detail + "; the file is incomplete (re-copy or re-save it)");
    }
    fail(path, "trailing bytes: " + detail +
                   "; the header is corrupt or the file holds more than one array (save one array per file)");
  }
  if (count > std::numeric_limits<size_t>::max() / 4) fail(path, "the array is too large for this machine");

  // Data, converted in chunks so that the raw bytes never need a second full copy.
  array.data.resize(static_cast<size_t>(count));
  constexpr size_t kChunk = size_t(1) << 16;
  std::vector<unsigned char> raw;
  for (size_t start = 0; start < array.data.size(); start += kChunk) {
    const size_t n = std::min(kChunk, array.data.size() - start);
    raw.resize(n * static_cast<size_t>(dtype.bytes));
    read_exact(raw.data(), raw.size(), "the array data");
    convert(raw.data(), n, dtype, array.data.data() + start);
  }
  if (fortran->boolean && array.shape.size() > 1) array.data = fortran_to_c(array.data, array.shape);
  return array;
}

void write_npy(const std::string& path, const std::vector<float>& data, const std::vector<int64_t>& shape) {
  uint64_t count = 1;
  for (int64_t d : shape) {
    if (d < 0) throw std::invalid_argument("write_npy(" + path + "): negative dimension in shape " + shape_text(shape));
    if (d != 0 && count > std::numeric_limits<uint64_t>::max() / static_cast<uint64_t>(d)) {
      count = std::numeric_limits<uint64_t>::max();  // cannot match any data size
      break;
    }
    count *= static_cast<uint64_t>(d);
  }
  if (std::find(shape.begin(), shape.end(), 0) != shape.end()) count = 0;
  if (count != data.size()) {
    throw std::invalid_argument(
        "write_npy(" + path + "): " + std::to_string(data.size()) + " values do not fill shape " + shape_text(shape) +
        " (" + (count == std::numeric_limits<uint64_t>::max() ? std::string("overflowing") : std::to_string(count)) +
        " elements)");
  }

  // The header as numpy.save writes it: keys sorted, padded with spaces so
  // that the data starts at a multiple of 64 bytes, ending in '\n'.
  // Version 1.0 unless the header outgrows its uint16 length (thousands of dimensions).
  const std::string literal = "{'descr': '<f4', 'fortran_order': False, 'shape': " + shape_text(shape) + ", }";
  auto padded = [&](size_t len_bytes) {
    const size_t unpadded = kMagicLen + 2 + len_bytes + literal.size() + 1;
    return literal + std::string((64 - unpadded % 64) % 64, ' ') + '\n';
  };
  std::string dict = padded(2);
  const size_t len_bytes = dict.size() <= 65535 ? 2 : 4;
  if (len_bytes == 4) dict = padded(4);
  std::string preamble(kMagic, kMagicLen);
  preamble += static_cast<char>(len_bytes == 2 ? 1 : 2);
  preamble += '\0';
  for (size_t b = 0; b < len_bytes; ++b) preamble += static_cast<char>((dict.size() >> (8 * b)) & 0xff);

  AtomicFile out(path);
  auto put = [&](const void* bytes, size_t n) { out.write(bytes, n); };
  put(preamble.data(), preamble.size());
  put(dict.data(), dict.size());

  constexpr size_t kChunk = size_t(1) << 16;
  std::vector<unsigned char> bytes;
  for (size_t start = 0; start < data.size(); start += kChunk) {
    const size_t n = std::min(kChunk, data.size() - start);
    bytes.resize(n * 4);
    for (size_t i = 0; i < n; ++i) {
      uint32_t u;
      std::memcpy(&u, &data[start + i], 4);
      for (int b = 0; b < 4; ++b) bytes[i * 4 + b] = static_cast<unsigned char>(u >> (8 * b));
    }
    put(bytes.data(), bytes.size());
  }

  out.commit();
}

}  // namespace ag2gs
