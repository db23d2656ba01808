// Tests for the .npy reader/writer (host/io/npy_io.h) and the COLMAP model
// writer (host/io/colmap_writer.h), plus regression cases found by the fuzzers
// in fuzz/ for every parser they cover (npy, PLY, COLMAP binary and text).
#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <functional>
#include <limits>
#include <map>
#include <random>
#include <sstream>
#include <string>
#include <vector>

#ifndef _WIN32
#include <sys/resource.h>
#include <sys/wait.h>
#include <unistd.h>

#include <csignal>
#endif

#include "host/io/colmap_reader.h"
#include "host/io/colmap_writer.h"
#include "host/io/npy_io.h"
#include "host/io/ply_io.h"
#include "tests/io_test_util.h"

namespace fs = std::filesystem;
using namespace ag2gs;

namespace {

using TempDir = ag2gs::test::ScratchDir;
using ag2gs::test::expect_error_with;
using ag2gs::test::read_bytes;
using ag2gs::test::write_bytes;

std::string source_dir() {
  return ag2gs::test::source_path("");
}

bool same_bits(const std::vector<float>& a, const std::vector<float>& b) {
  return a.size() == b.size() && (a.empty() || std::memcmp(a.data(), b.data(), a.size() * 4) == 0);
}

// ---------------------------------------------------------------- npy bytes

// The header dict exactly as numpy.save formats it.
std::string numpy_dict(const std::string& descr, bool fortran, const std::string& shape) {
  return "{'descr': '" + descr + "', 'fortran_order': " + (fortran ? "True" : "False") + ", 'shape': " + shape + ", }";
}

// A .npy file as numpy writes it: magic, version, header length (uint16 for
// 1.0, uint32 for 2.0 and 3.0), the dict padded with spaces so that the data
// starts at a multiple of `align` bytes (64; 16 before numpy 1.14), '\n', data.
std::string npy_file(const std::string& dict, const std::string& data, int major = 1, size_t align = 64) {
  const size_t len_bytes = major == 1 ? 2 : 4;
  std::string header = dict;
  const size_t unpadded = 8 + len_bytes + header.size() + 1;
  header.append((align - unpadded % align) % align, ' ');
  header += '\n';
  std::string out("\x93NUMPY", 6);
  out += static_cast<char>(major);
  out += '\0';
  for (size_t b = 0; b < len_bytes; ++b) out += static_cast<char>((header.size() >> (8 * b)) & 0xff);
  return out + header + data;
}

// `n` bytes of `bits`, little- or big-endian.
std::string encode(uint64_t bits, int n, bool big_endian) {
  std::string s;
  for (int b = 0; b < n; ++b) {
    const int shift = 8 * (big_endian ? n - 1 - b : b);
    s += static_cast<char>((bits >> shift) & 0xff);
  }
  return s;
}
uint64_t bits_of(float f) {
  uint32_t u;
  std::memcpy(&u, &f, 4);
  return u;
}
uint64_t bits_of(double d) {
  uint64_t u;
  std::memcpy(&u, &d, 8);
  return u;
}

bool host_is_little_endian() {
  const uint16_t probe = 1;
  unsigned char first;
  std::memcpy(&first, &probe, 1);
  return first == 1;
}

// Values of one dtype: their bits and the float32 read_npy must return.
struct TypedValues {
  char kind;  // numpy type code: b i u f
  int bytes;
  std::vector<uint64_t> bits;
  std::vector<float> expected;
};

std::vector<TypedValues> every_dtype() {
  const float inf = std::numeric_limits<float>::infinity();
  std::vector<TypedValues> all;
  all.push_back({'b', 1, {0, 1, 2, 255}, {0, 1, 1, 1}});
  all.push_back({'i', 1, {0x80, 0xff, 0, 0x7f}, {-128, -1, 0, 127}});
  all.push_back({'u', 1, {0, 1, 0x80, 0xff}, {0, 1, 128, 255}});
  all.push_back({'i', 2, {0x8000, 0xfffe, 0x7fff, 0x0102}, {-32768, -2, 32767, 258}});
  all.push_back({'u', 2, {0xffff, 0x8000, 0, 0x0102}, {65535, 32768, 0, 258}});
  all.push_back({'i',
                 4,
                 {0x80000000u, static_cast<uint32_t>(-123456), 0x7fffffffu, 0x01020304u},
                 {-2147483648.f, -123456.f, 2147483648.f, 16909060.f}});
  all.push_back({'u', 4, {0xffffffffu, 7, 0x80000000u, 0x01020304u}, {4294967296.f, 7, 2147483648.f, 16909060.f}});
  all.push_back({'i',
                 8,
                 {0x8000000000000000ull, ~uint64_t(0), (uint64_t(1) << 53) + 1, 0x0102030405060708ull},
                 {-9223372036854775808.f, -1, 9007199254740992.f, static_cast<float>(0x0102030405060708ll)}});
  all.push_back({'u',
                 8,
                 {~uint64_t(0), 0, 42, 0x0102030405060708ull},
                 {18446744073709551616.f, 0, 42, static_cast<float>(0x0102030405060708ull)}});
  // float16: 1, -2, the largest half, the smallest subnormal, the largest
  // subnormal, +-inf, -0, 1/3 rounded to half.
  all.push_back(
      {'f',
       2,
       {0x3c00, 0xc000, 0x7bff, 0x0001, 0x03ff, 0x7c00, 0xfc00, 0x8000, 0x3555},
       {1.f, -2.f, 65504.f, std::ldexp(1.f, -24), 1023 * std::ldexp(1.f, -24), inf, -inf, -0.f, 0.333251953125f}});
  all.push_back({'f',
                 4,
                 {bits_of(1.5f), bits_of(-0.f), bits_of(inf), bits_of(3.4e38f), bits_of(1e-45f)},
                 {1.5f, -0.f, inf, 3.4e38f, 1e-45f}});
  all.push_back({'f',
                 8,
                 {bits_of(0.1), bits_of(-1e300), bits_of(1e-50), bits_of(123456789.125)},
                 {0.1f, -inf, 0.f, static_cast<float>(123456789.125)}});
  return all;
}

}  // namespace

// ---------------------------------------------------------------- npy

TEST(Npy, RoundTripIsBitExact) {
  TempDir dir;
  std::mt19937 rng(7);
  std::uniform_int_distribution<uint32_t> any_bits;
  const std::vector<std::vector<int64_t>> shapes = {{4, 12, 16}, {5}, {}, {0, 512}, {2, 0, 3}, {3, 1, 1, 2}, {70000}};
  for (const auto& shape : shapes) {
    size_t n = 1;
    for (int64_t d : shape) n *= static_cast<size_t>(d);
    std::vector<float> data(n);
    // Every bit pattern: NaNs with payloads, infinities, -0, subnormals.
    for (float& v : data) {
      const uint32_t u = any_bits(rng);
      std::memcpy(&v, &u, 4);
    }
    const std::string path = dir.file("a.npy");
    write_npy(path, data, shape);
    const NpyArray back = read_npy(path);
    EXPECT_EQ(back.shape, shape);
    EXPECT_TRUE(same_bits(back.data, data)) << "shape of " << shape.size() << " dims";
    EXPECT_EQ(back.size(), n);
  }
}

TEST(Npy, WriterMatchesNumpyByteForByte) {
  TempDir dir;
  const std::string path = dir.file("a.npy");
  const std::vector<float> data = {0, 1, 2, 3, 4, 5};
  write_npy(path, data, {2, 3});
  std::string raw;
  for (float v : data) raw += encode(bits_of(v), 4, false);
  // numpy.save(path, numpy.arange(6, dtype='<f4').reshape(2, 3)) writes exactly this.
  const std::string expected = npy_file("{'descr': '<f4', 'fortran_order': False, 'shape': (2, 3), }", raw);
  EXPECT_EQ(read_bytes(path), expected);
  EXPECT_EQ(expected.size(), 128u + 24u);

  write_npy(path, {2.5f}, {1});
  EXPECT_NE(read_bytes(path).find("'shape': (1,), }"), std::string::npos);
  write_npy(path, {2.5f}, {});
  EXPECT_NE(read_bytes(path).find("'shape': (), }"), std::string::npos);
  const NpyArray scalar = read_npy(path);
  EXPECT_TRUE(scalar.shape.empty());
  EXPECT_EQ(scalar.data, std::vector<float>{2.5f});
}

TEST(Npy, ReadsEveryDtypeInBothByteOrders) {
  TempDir dir;
  const std::string path = dir.file("typed.npy");
  for (const TypedValues& t : every_dtype()) {
    std::vector<std::string> orders = {"<", ">", "="};
    if (t.bytes == 1) orders = {"|", "<", ">"};
    for (const std::string& order : orders) {
      const std::string descr = order + t.kind + std::to_string(t.bytes);
      SCOPED_TRACE(descr);
      const bool big = order == ">" || (order == "=" && !host_is_little_endian());
      std::string data;
      for (uint64_t b : t.bits) data += encode(b, t.bytes, big);
      write_bytes(path, npy_file(numpy_dict(descr, false, "(" + std::to_string(t.bits.size()) + ",)"), data));
      const NpyArray a = read_npy(path);
      ASSERT_EQ(a.shape, std::vector<int64_t>{static_cast<int64_t>(t.bits.size())});
      EXPECT_TRUE(same_bits(a.data, t.expected)) << "first value " << a.data[0] << " vs " << t.expected[0];
    }
  }
  // Half NaN stays NaN.
  write_bytes(path, npy_file(numpy_dict("<f2", false, "(1,)"), encode(0x7e00, 2, false)));
  EXPECT_TRUE(std::isnan(read_npy(path).data[0]));
}

TEST(Npy, FortranOrderIsTransposedIntoCOrder) {
  TempDir dir;
  const std::string path = dir.file("f.npy");
  // Element (i, j, k) of a [2,3,4] array holds 100 i + 10 j + k; Fortran
  // order stores it at i + 2 j + 6 k.
  std::vector<double> fortran(24);
  for (int i = 0; i < 2; ++i)
    for (int j = 0; j < 3; ++j)
      for (int k = 0; k < 4; ++k) fortran[i + 2 * j + 6 * k] = 100 * i + 10 * j + k;
  std::string data;
  for (double v : fortran) data += encode(bits_of(v), 8, true);
  write_bytes(path, npy_file(numpy_dict(">f8", true, "(2, 3, 4)"), data));
  const NpyArray a = read_npy(path);
  ASSERT_EQ(a.shape, (std::vector<int64_t>{2, 3, 4}));
  for (int i = 0; i < 2; ++i)
    for (int j = 0; j < 3; ++j)
      for (int k = 0; k < 4; ++k) EXPECT_EQ(a.data[(i * 3 + j) * 4 + k], 100 * i + 10 * j + k);

  // 2-D, 1-D, a unit and an empty dimension.
  data.clear();
  for (int v : {1, 4, 2, 5, 3, 6}) data += encode(static_cast<uint64_t>(v), 2, false);  // [[1,2,3],[4,5,6]]
  write_bytes(path, npy_file(numpy_dict("<i2", true, "(2, 3)"), data));
  EXPECT_EQ(read_npy(path).data, (std::vector<float>{1, 2, 3, 4, 5, 6}));
  write_bytes(path, npy_file(numpy_dict("<i2", true, "(6,)"), data));
  EXPECT_EQ(read_npy(path).data, (std::vector<float>{1, 4, 2, 5, 3, 6}));
  write_bytes(path, npy_file(numpy_dict("<i2", true, "(1, 6, 1)"), data));
  EXPECT_EQ(read_npy(path).data, (std::vector<float>{1, 4, 2, 5, 3, 6}));
  write_bytes(path, npy_file(numpy_dict("<i2", true, "(2, 1, 3, 1)"), data));
  EXPECT_EQ(read_npy(path).data, (std::vector<float>{1, 2, 3, 4, 5, 6}));
  write_bytes(path, npy_file(numpy_dict("<i2", true, "(3, 0, 2)"), ""));
  const NpyArray empty = read_npy(path);
  EXPECT_EQ(empty.shape, (std::vector<int64_t>{3, 0, 2}));
  EXPECT_TRUE(empty.data.empty());
}

TEST(Npy, ReadsVersion2And3AndOtherHeaderSpellings) {
  TempDir dir;
  const std::string path = dir.file("v.npy");
  std::string data;
  for (float v : {1.f, 2.f, 3.f, 4.f, 5.f, 6.f}) data += encode(bits_of(v), 4, false);
  const std::vector<float> expected = {1, 2, 3, 4, 5, 6};
  const std::vector<int64_t> shape = {3, 2};

  for (int major : {2, 3}) {
    SCOPED_TRACE(major);
    write_bytes(path, npy_file(numpy_dict("<f4", false, "(3, 2)"), data, major));
    const NpyArray a = read_npy(path);
    EXPECT_EQ(a.shape, shape);
    EXPECT_EQ(a.data, expected);
  }
  // Version 2.0 as numpy writes it for a header over 64 KiB (long padding).
  write_bytes(path, npy_file(numpy_dict("<f4", false, "(3, 2)") + std::string(70000, ' '), data, 2));
  EXPECT_EQ(read_npy(path).data, expected);

  const std::vector<std::string> spellings = {
      "{'descr': '<f4', 'fortran_order': False, 'shape': (3L, 2L), }",     // Python 2 longs
      "{'shape': (3, 2), 'fortran_order': False, 'descr': '<f4'}",         // any key order, no trailing comma
      "{\"descr\": \"<f4\", \"fortran_order\": False, \"shape\": (3,2)}",  // double quotes, no spaces
      "{ 'descr' : '<f4' ,\t'fortran_order' : False , 'shape' : ( 3 , 2 , ) , }",
      // numpy >= 1.23 leaves room after the dict to grow the first axis in place.
      "{'descr': '<f4', 'fortran_order': False, 'shape': (3, 2), }                    ",
  };
  for (const std::string& dict : spellings) {
    SCOPED_TRACE(dict);
    write_bytes(path, npy_file(dict, data));
    const NpyArray a = read_npy(path);
    EXPECT_EQ(a.shape, shape);
    EXPECT_EQ(a.data, expected);
  }
  // numpy < 1.14 aligned the data to 16 bytes only.
  write_bytes(path, npy_file(numpy_dict("<f4", false, "(3, 2)"), data, 1, 16));
  EXPECT_EQ(read_npy(path).data, expected);
}

TEST(Npy, CorruptFilesGiveErrorsNamingTheFile) {
  TempDir dir;
  const std::string path = dir.file("bad.npy");
  const std::string good_data = encode(bits_of(1.f), 4, false) + encode(bits_of(2.f), 4, false);
  const std::string good = npy_file(numpy_dict("<f4", false, "(2,)"), good_data);
  ASSERT_NO_THROW(write_bytes(path, good); read_npy(path));

  struct Case {
    const char* what;
    std::string bytes;
    std::vector<std::string> needles;
  };
  std::string bad_magic = good;
  bad_magic[1] = 'M';
  std::string version_4 = good, version_1_1 = good;
  version_4[6] = 4;
  version_1_1[7] = 1;
  std::string long_header = good;
  long_header[8] = '\xff', long_header[9] = '\x7f';
  const std::vector<Case> cases = {
      {"empty", "", {"not a .npy file", "0 bytes"}},
      {"bad magic", bad_magic, {"not a .npy file", "magic"}},
      {"a PNG", std::string("\x89PNG\r\n\x1a\n\0\0\0\rIHDR", 16), {"not a .npy file"}},
      {"version 4.0", version_4, {"version 4.0"}},
      {"version 1.1", version_1_1, {"version 1.1"}},
      {"magic cut", good.substr(0, 3), {"truncated .npy header", "after 3 bytes"}},
      {"version cut", good.substr(0, 7), {"truncated .npy header", "after 7 bytes"}},
      {"header length cut", good.substr(0, 9), {"truncated .npy header"}},
      {"v2 header length cut",
       npy_file(numpy_dict("<f4", false, "(2,)"), good_data, 2).substr(0, 11),
       {"truncated .npy header"}},
      {"header cut", good.substr(0, 40), {"truncated .npy header", "claims 118 bytes"}},
      {"header length too big", long_header, {"truncated .npy header"}},
      {"data cut", good.substr(0, good.size() - 1), {"truncated data", "needs 8 data bytes", "holds 7"}},
      {"no data", good.substr(0, good.size() - 8), {"truncated data"}},
      {"trailing bytes", good + "x", {"trailing bytes", "more than one array"}},
      {"empty header", npy_file("", ""), {"malformed .npy header", "unexpected end"}},
      {"not a dict", npy_file("('<f4', False, (2,))", good_data), {"malformed .npy header", "not a dict"}},
      {"missing key", npy_file("{'descr': '<f4', 'shape': (2,), }", good_data), {"no 'fortran_order' key"}},
      {"extra key",
       npy_file("{'descr': '<f4', 'fortran_order': False, 'shape': (2,), 'x': 1}", good_data),
       {"unexpected key 'x'"}},
      {"duplicate key",
       npy_file("{'descr': '<f4', 'descr': '<f4', 'fortran_order': False, 'shape': (2,)}", good_data),
       {"'descr' appears twice"}},
      {"unterminated string",
       npy_file("{'descr: '<f4', 'fortran_order': False, 'shape': (2,), }", good_data),
       {"malformed .npy header"}},
      {"no colon",
       npy_file("{'descr' '<f4', 'fortran_order': False, 'shape': (2,), }", good_data),
       {"malformed .npy header", "expected ':'"}},
      {"unclosed dict",
       npy_file("{'descr': '<f4', 'fortran_order': False, 'shape': (2,), ", good_data),
       {"malformed .npy header"}},
      {"text after dict",
       npy_file(numpy_dict("<f4", false, "(2,)") + " 7", good_data),
       {"malformed .npy header", "after the closing"}},
      {"shape a list", npy_file(numpy_dict("<f4", false, "[2]"), good_data), {"'shape' is not a tuple"}},
      {"shape an int", npy_file(numpy_dict("<f4", false, "2"), good_data), {"'shape' is not a tuple"}},
      {"shape (2)", npy_file(numpy_dict("<f4", false, "(2)"), good_data), {"'shape' is not a tuple"}},
      {"shape of strings", npy_file(numpy_dict("<f4", false, "('2',)"), good_data), {"non-integer"}},
      {"shape of floats", npy_file(numpy_dict("<f4", false, "(2.0,)"), good_data), {"malformed .npy header"}},
      {"fortran_order 0",
       npy_file("{'descr': '<f4', 'fortran_order': 0, 'shape': (2,), }", good_data),
       {"'fortran_order' is not True or False"}},
      {"descr not a string",
       npy_file("{'descr': 4, 'fortran_order': False, 'shape': (2,), }", good_data),
       {"'descr' is not a string"}},
      {"negative shape", npy_file(numpy_dict("<f4", false, "(-2,)"), good_data), {"negative dimension"}},
      {"negative in 3-D", npy_file(numpy_dict("<f4", false, "(2, -1, -2)"), good_data), {"negative dimension"}},
      {"dimension over 2^63",
       npy_file(numpy_dict("<f4", false, "(9223372036854775808,)"), good_data),
       {"exceeds 2^63 - 1"}},
      {"huge dimension",
       npy_file(numpy_dict("<f4", false, "(99999999999999999999999999,)"), good_data),
       {"exceeds 2^63 - 1"}},
      {"count overflows", npy_file(numpy_dict("<f4", false, "(4294967296, 4294967296, 16)"), good_data), {"overflows"}},
      {"bytes overflow", npy_file(numpy_dict("<f8", false, "(9223372036854775807,)"), good_data), {"overflows"}},
      {"count wraps to 8", npy_file(numpy_dict("<u1", false, "(4294967296, 4294967296, 8)"), good_data), {"overflows"}},
      {"big but finite", npy_file(numpy_dict("<f4", false, "(1000000, 1000000)"), good_data), {"truncated data"}},
      {"object dtype", npy_file(numpy_dict("|O", false, "(2,)"), good_data), {"unsupported dtype '|O'", "object"}},
      {"structured dtype",
       npy_file("{'descr': [('a', '<f4')], 'fortran_order': False, 'shape': (2,), }", good_data),
       {"structured"}},
      {"complex", npy_file(numpy_dict("<c8", false, "(1,)"), good_data), {"unsupported dtype '<c8'", "complex"}},
      {"unicode", npy_file(numpy_dict("<U2", false, "(1,)"), good_data), {"unsupported dtype '<U2'", "strings"}},
      {"long double", npy_file(numpy_dict("<f16", false, "(1,)"), good_data + good_data), {"long double"}},
      {"datetime", npy_file(numpy_dict("<M8", false, "(1,)"), good_data), {"dates"}},
      {"no byte order", npy_file(numpy_dict("f4", false, "(2,)"), good_data), {"unsupported dtype 'f4'"}},
      {"| on f4", npy_file(numpy_dict("|f4", false, "(2,)"), good_data), {"'|'"}},
      {"3-byte int", npy_file(numpy_dict("<i3", false, "(2,)"), good_data), {"unsupported dtype '<i3'"}},
      {"2-byte bool", npy_file(numpy_dict("<b2", false, "(2,)"), good_data), {"unsupported dtype '<b2'"}},
      {"deep nesting", npy_file(std::string(1000, '('), good_data), {"malformed .npy header", "nesting"}},
  };
  for (const Case& c : cases) {
    SCOPED_TRACE(c.what);
    write_bytes(path, c.bytes);
    std::vector<std::string> needles = c.needles;
    needles.insert(needles.begin(), path);
    expect_error_with<std::runtime_error>([&] { read_npy(path); }, needles);
  }

  expect_error_with<std::runtime_error>([&] { read_npy(dir.file("missing.npy")); },
                                        {dir.file("missing.npy"), "cannot open"});
  expect_error_with<std::runtime_error>([&] { read_npy(dir.path().string()); }, {dir.path().string(), "directory"});
}

TEST(Npy, WriteRejectsShapesThatDoNotMatch) {
  TempDir dir;
  const std::string path = dir.file("a.npy");
  expect_error_with<std::invalid_argument>([&] { write_npy(path, {1, 2, 3}, {2, 2}); }, {path, "3 values", "(2, 2)"});
  expect_error_with<std::invalid_argument>([&] { write_npy(path, {1, 2}, {-1, -2}); }, {path, "negative"});
  expect_error_with<std::invalid_argument>(
      [&] {
        write_npy(path, {1}, {int64_t(1) << 40, int64_t(1) << 40, int64_t(1) << 40});
      },
      {path, "overflowing"});
  expect_error_with<std::invalid_argument>([&] { write_npy(path, {}, {}); }, {path, "0 values", "()"});
  EXPECT_TRUE(dir.entries().empty());
  write_npy(path, {}, {0, 7});
  EXPECT_EQ(read_npy(path).shape, (std::vector<int64_t>{0, 7}));
}

TEST(Npy, FailedWriteKeepsTheOldFile) {
  TempDir dir;
  const std::string path = dir.file("feat.npy");
  write_npy(path, {1, 2, 3}, {3});
  const std::string old_bytes = read_bytes(path);

  // A shape mismatch is rejected before anything is touched.
  EXPECT_THROW(write_npy(path, {1, 2}, {3}), std::invalid_argument);
  EXPECT_EQ(read_bytes(path), old_bytes);

  // The temporary file cannot be created (something else sits at its name):
  // also fails for root, which ignores directory permissions.
  const std::string tmp_name = path + ".tmp." + std::to_string(static_cast<long>(::getpid()));
  fs::create_directories(tmp_name);
  expect_error_with<std::runtime_error>([&] { write_npy(path, {4, 5}, {2}); }, {path, "temporary file", "writable"});
  EXPECT_EQ(read_bytes(path), old_bytes);
  EXPECT_TRUE(fs::is_directory(tmp_name)) << "the writer removed what it did not create";
  fs::remove(tmp_name);

  // The target is a non-empty directory: the final rename fails, nothing is left behind.
  fs::create_directories(dir.path() / "a_dir" / "inside");
  expect_error_with<std::runtime_error>([&] { write_npy(dir.file("a_dir"), {1}, {1}); }, {"a_dir", "unchanged"});
  EXPECT_TRUE(fs::is_directory(dir.path() / "a_dir" / "inside"));

  const std::string nowhere = dir.file("no_such_dir/x.npy");
  expect_error_with<std::runtime_error>([&] { write_npy(nowhere, {1}, {1}); }, {nowhere, "directory exists"});
  EXPECT_EQ(dir.entries(), (std::vector<std::string>{"a_dir", "feat.npy"}));

#ifndef _WIN32
  // Fail in the middle of the data: a file size limit makes write() return EFBIG.
  struct rlimit old_limit;
  ASSERT_EQ(getrlimit(RLIMIT_FSIZE, &old_limit), 0);
  auto old_handler = std::signal(SIGXFSZ, SIG_IGN);
  struct rlimit small = old_limit;
  small.rlim_cur = 8192;
  ASSERT_EQ(setrlimit(RLIMIT_FSIZE, &small), 0);
  bool threw = false;
  std::string message;
  try {
    write_npy(path, std::vector<float>(100000, 1.f), {100000});
  } catch (const std::runtime_error& e) {
    threw = true;
    message = e.what();
  }
  setrlimit(RLIMIT_FSIZE, &old_limit);
  std::signal(SIGXFSZ, old_handler);
  EXPECT_TRUE(threw);
  EXPECT_NE(message.find(path), std::string::npos) << message;
  EXPECT_EQ(read_bytes(path), old_bytes);
  EXPECT_EQ(dir.entries(), (std::vector<std::string>{"a_dir", "feat.npy"}));

  // An unwritable folder (root ignores permissions, so only as a user).
  if (::geteuid() != 0) {
    fs::create_directories(dir.path() / "ro");
    write_npy(dir.file("ro/f.npy"), {7}, {1});
    const std::string ro_bytes = read_bytes(dir.file("ro/f.npy"));
    fs::permissions(dir.path() / "ro", fs::perms::owner_read | fs::perms::owner_exec);
    expect_error_with<std::runtime_error>(
        [&] {
          write_npy(dir.file("ro/f.npy"), {8, 9}, {2});
        },
        {"ro/f.npy", "writable"});
    fs::permissions(dir.path() / "ro", fs::perms::owner_all);
    EXPECT_EQ(read_bytes(dir.file("ro/f.npy")), ro_bytes);
    EXPECT_EQ(dir.entries("ro"), std::vector<std::string>{"f.npy"});
  }
#endif
}

// ---------------------------------------------------------------- COLMAP writer

namespace {

struct Scene {
  std::vector<Camera> cameras;
  std::vector<Eigen::Vector3d> points;
  std::vector<Eigen::Vector3<uint8_t>> colors;
};

Scene random_scene(unsigned seed, size_t n_cameras, size_t n_points) {
  std::mt19937 rng(seed);
  std::normal_distribution<double> nrm(0, 1);
  std::uniform_real_distribution<double> u(0, 1);
  std::uniform_int_distribution<int> byte(0, 255), size(1, 4000);
  Scene s;
  for (size_t i = 0; i < n_cameras; ++i) {
    Camera c;
    // Names in folders and out of id order: the reader sorts by name.
    c.name = (i % 3 == 0 ? "sub/dir/" : "") + std::string("frame_") + std::to_string(1000 - i) + ".png";
    c.width = size(rng);
    c.height = size(rng);
    c.fx = 50 + 2000 * u(rng);
    c.fy = 50 + 2000 * u(rng);
    c.cx = c.width * u(rng);
    c.cy = c.height * u(rng);
    Eigen::Quaterniond q(nrm(rng), nrm(rng), nrm(rng), nrm(rng));  // w < 0 about half the time
    c.R = q.normalized().toRotationMatrix();
    c.t = Eigen::Vector3d(nrm(rng), nrm(rng), nrm(rng)) * std::pow(10.0, 4 * u(rng) - 2);
    s.cameras.push_back(c);
  }
  for (size_t i = 0; i < n_points; ++i) {
    s.points.emplace_back(nrm(rng) * 1e-7, nrm(rng) * 1e5, nrm(rng) / 3);
    s.colors.emplace_back(byte(rng), byte(rng), byte(rng));
  }
  return s;
}

// Compares a model read back with the scene written, cameras matched by name.
void expect_same_model(const ColmapModel& model, const Scene& s, double tol) {
  ASSERT_EQ(model.cameras_for_images.size(), s.cameras.size());
  std::map<std::string, const Camera*> by_name;
  for (const Camera& c : s.cameras) by_name[c.name] = &c;
  for (const Camera& got : model.cameras_for_images) {
    SCOPED_TRACE(got.name);
    ASSERT_TRUE(by_name.count(got.name));
    const Camera& want = *by_name[got.name];
    EXPECT_EQ(got.width, want.width);
    EXPECT_EQ(got.height, want.height);
    EXPECT_NEAR(got.fx, want.fx, tol);
    EXPECT_NEAR(got.fy, want.fy, tol);
    EXPECT_NEAR(got.cx, want.cx, tol);
    EXPECT_NEAR(got.cy, want.cy, tol);
    EXPECT_LE((got.R - want.R).cwiseAbs().maxCoeff(), tol) << got.R << "\nvs\n" << want.R;
    EXPECT_LE((got.t - want.t).cwiseAbs().maxCoeff(), tol) << got.t.transpose() << " vs " << want.t.transpose();
  }
  ASSERT_EQ(model.points.size(), s.points.size());
  for (size_t i = 0; i < s.points.size(); ++i) {
    EXPECT_LE((model.points[i] - s.points[i]).cwiseAbs().maxCoeff(), tol) << "point " << i;
  }
  if (s.colors.empty()) {
    for (const auto& c : model.colors) EXPECT_EQ(c, (Eigen::Vector3<uint8_t>(128, 128, 128)));
  } else {
    EXPECT_EQ(model.colors, s.colors);
  }
}

double load_f64(const std::string& bytes, size_t at) {
  uint64_t u = 0;
  for (int b = 0; b < 8; ++b) u |= uint64_t(static_cast<unsigned char>(bytes[at + b])) << (8 * b);
  double d;
  std::memcpy(&d, &u, 8);
  return d;
}
uint64_t load_u64(const std::string& bytes, size_t at) {
  uint64_t u = 0;
  for (int b = 0; b < 8; ++b) u |= uint64_t(static_cast<unsigned char>(bytes[at + b])) << (8 * b);
  return u;
}

bool have_colmap() {
  return std::system("command -v colmap > /dev/null 2>&1") == 0;
}

// Runs `colmap model_converter` from `in` into `out` (created), returning its log on failure.
bool colmap_convert(const std::string& in, const std::string& out, const std::string& type, std::string* log) {
  fs::create_directories(out);
  const std::string log_file = out + "/../colmap_" + type + ".log";
  const std::string cmd = "colmap model_converter --input_path '" + in + "' --output_path '" + out +
                          "' --output_type " + type + " > '" + log_file + "' 2>&1";
  const int rc = std::system(cmd.c_str());
  *log = cmd + "\n" + read_bytes(log_file);
  return rc == 0;
}

}  // namespace

TEST(ColmapWriter, BinaryRoundTrip) {
  TempDir dir;
  const Scene s = random_scene(1, 7, 50);
  const std::string sparse = dir.file("scene/sparse/0");  // created by the writer
  write_colmap_model(sparse, s.cameras, s.points, s.colors, true);
  EXPECT_EQ(dir.entries("scene/sparse/0"), (std::vector<std::string>{"cameras.bin", "images.bin", "points3D.bin"}));
  expect_same_model(read_colmap_model(sparse), s, 1e-12);

  // Layout: sizes and the stored quaternions (unit, w >= 0).
  const std::string cams = read_bytes(sparse + "/cameras.bin");
  EXPECT_EQ(cams.size(), 8 + 7 * (4 + 4 + 8 + 8 + 4 * 8));
  EXPECT_EQ(load_u64(cams, 0), 7u);
  const std::string points = read_bytes(sparse + "/points3D.bin");
  EXPECT_EQ(points.size(), 8 + 50 * (8 + 24 + 3 + 8 + 8));
  EXPECT_EQ(load_u64(points, 8), 1u);  // ids 1..P
  const std::string images = read_bytes(sparse + "/images.bin");
  size_t at = 8, expected_size = 8;
  for (size_t i = 0; i < s.cameras.size(); ++i) {
    SCOPED_TRACE(i);
    const double w = load_f64(images, at + 4), x = load_f64(images, at + 12), y = load_f64(images, at + 20),
                 z = load_f64(images, at + 28);
    EXPECT_GE(w, 0.0);
    EXPECT_NEAR(w * w + x * x + y * y + z * z, 1.0, 1e-15);
    const size_t name_at = at + 4 + 56 + 4;
    EXPECT_EQ(images.substr(name_at, s.cameras[i].name.size()), s.cameras[i].name);
    EXPECT_EQ(load_u64(images, name_at + s.cameras[i].name.size() + 1), 0u);  // no 2D points
    at = name_at + s.cameras[i].name.size() + 1 + 8;
    expected_size += 4 + 56 + 4 + s.cameras[i].name.size() + 1 + 8;
  }
  EXPECT_EQ(images.size(), expected_size);
}

TEST(ColmapWriter, TextRoundTripWithColmapHeaders) {
  TempDir dir;
  Scene s = random_scene(2, 5, 30);
  write_colmap_model(dir.path().string(), s.cameras, s.points, s.colors, false);
  EXPECT_EQ(dir.entries(), (std::vector<std::string>{"cameras.txt", "images.txt", "points3D.txt"}));
  expect_same_model(read_colmap_model(dir.path().string()), s, 1e-12);

  const std::string cams = read_bytes(dir.file("cameras.txt"));
  EXPECT_EQ(cams.rfind("# Camera list with one line of data per camera:\n"
                       "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
                       "# Number of cameras: 5\n1 PINHOLE ",
                       0),
            0u)
      << cams;
  const std::string images = read_bytes(dir.file("images.txt"));
  EXPECT_EQ(images.rfind("# Image list with two lines of data per image:\n"
                         "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n"
                         "#   POINTS2D[] as (X, Y, POINT3D_ID)\n"
                         "# Number of images: 5, mean observations per image: 0\n1 ",
                         0),
            0u)
      << images;
  const std::string points = read_bytes(dir.file("points3D.txt"));
  EXPECT_EQ(points.rfind("# 3D point list with one line of data per point:\n"
                         "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n"
                         "# Number of points: 30, mean track length: 0\n1 ",
                         0),
            0u)
      << points;
  // Each image line is followed by its (empty) line of 2D points, and qw >= 0.
  std::istringstream lines(images);
  std::string line;
  int image_lines = 0;
  while (std::getline(lines, line)) {
    if (line.empty() || line[0] == '#') continue;
    ++image_lines;
    std::istringstream tok(line);
    int id;
    double qw, qx, qy, qz;
    tok >> id >> qw >> qx >> qy >> qz;
    EXPECT_GE(qw, 0.0) << line;
    EXPECT_NEAR(qw * qw + qx * qx + qy * qy + qz * qz, 1.0, 1e-15) << line;
    ASSERT_TRUE(std::getline(lines, line));
    EXPECT_EQ(line, "");
  }
  EXPECT_EQ(image_lines, 5);

  // A dropped line of 2D points (issue 42: the next image's header was read
  // as the points and that view silently lost) and a broken triple are errors
  // naming the file, its line and the image; points that are triples are read.
  {
    std::string one_less, with_points;
    std::istringstream in(images);
    bool dropped = false;
    for (std::string l; std::getline(in, l);) {
      if (!dropped && l.empty()) {
        dropped = true;
        with_points += "10.5 20.25 7 11 12 -1\n";
        continue;
      }
      one_less += l + "\n";
      with_points += l + "\n";
    }
    const std::string path = dir.file("images.txt");
    write_bytes(path, one_less);
    expect_error_with<std::runtime_error>(
        [&] { read_colmap_model(dir.path().string()); },
        {"images.txt:6", "2D points of image '" + s.cameras[0].name + "'", "two lines"});
    write_bytes(path, with_points);
    expect_same_model(read_colmap_model(dir.path().string()), s, 1e-12);
    write_bytes(path, with_points.replace(with_points.find(" -1\n"), 4, "\n"));
    expect_error_with<std::runtime_error>([&] { read_colmap_model(dir.path().string()); },
                                          {"images.txt:6", "hold 5 numbers"});
    write_bytes(path, images);
  }

  // No colours: grey. No cameras or points at all: valid, empty files.
  s.colors.clear();
  write_colmap_model(dir.path().string(), s.cameras, s.points, s.colors, false);
  expect_same_model(read_colmap_model(dir.path().string()), s, 1e-12);
  write_colmap_model(dir.file("empty"), {}, {}, {}, false);
  const ColmapModel empty = read_colmap_model(dir.file("empty"));
  EXPECT_TRUE(empty.cameras_for_images.empty());
  EXPECT_TRUE(empty.points.empty());
}

TEST(ColmapWriter, SwitchingFormatRemovesTheStaleFiles) {
  TempDir dir;
  const Scene a = random_scene(3, 2, 4), b = random_scene(4, 3, 5);
  write_colmap_model(dir.path().string(), a.cameras, a.points, a.colors, true);
  // The text model replaces the binary one, which readers would otherwise prefer.
  write_colmap_model(dir.path().string(), b.cameras, b.points, b.colors, false);
  EXPECT_EQ(dir.entries(), (std::vector<std::string>{"cameras.txt", "images.txt", "points3D.txt"}));
  expect_same_model(read_colmap_model(dir.path().string()), b, 1e-12);
  write_colmap_model(dir.path().string(), a.cameras, a.points, a.colors, true);
  EXPECT_EQ(dir.entries(), (std::vector<std::string>{"cameras.bin", "images.bin", "points3D.bin"}));
  expect_same_model(read_colmap_model(dir.path().string()), a, 1e-12);
}

TEST(ColmapWriter, RejectsBadInputBeforeWriting) {
  TempDir dir;
  const std::string sparse = dir.file("sparse");
  const Scene s = random_scene(5, 3, 4);
  auto write = [&](const Scene& scene, bool binary = true) {
    write_colmap_model(sparse, scene.cameras, scene.points, scene.colors, binary);
  };
  Scene bad = s;
  bad.colors.pop_back();
  expect_error_with<std::invalid_argument>([&] { write(bad); }, {"3 colours for 4 points"});
  bad = s;
  bad.cameras[1].fx = 0;
  expect_error_with<std::invalid_argument>([&] { write(bad); }, {bad.cameras[1].name, "fx"});
  // Finite but absurd numbers (issue 42: fx 1e300 and 1e-300, a translation
  // of 1e300 were accepted and overflowed later).
  for (double fx : {1e300, 1e-300}) {
    bad = s;
    bad.cameras[1].fx = fx;
    expect_error_with<std::invalid_argument>([&] { write(bad); }, {bad.cameras[1].name, "not those of a camera"});
  }
  bad = s;
  bad.cameras[1].cy = -1e300;
  expect_error_with<std::invalid_argument>([&] { write(bad); }, {bad.cameras[1].name, "principal point"});
  bad = s;
  bad.cameras[0].t.y() = 1e300;
  expect_error_with<std::invalid_argument>([&] { write(bad); }, {bad.cameras[0].name, "implausibly large"});
  bad = s;
  bad.cameras[0].t.y() = 6e6;  // a UTM northing is fine
  write(bad);
  fs::remove_all(sparse);
  bad = s;
  bad.cameras[2].R(0, 0) += 0.1;
  expect_error_with<std::invalid_argument>([&] { write(bad); }, {"not a rotation"});
  bad = s;
  bad.cameras[2].name = bad.cameras[0].name;
  expect_error_with<std::invalid_argument>([&] { write(bad); }, {bad.cameras[0].name, "twice"});
  bad = s;
  bad.cameras[1].name = "";
  expect_error_with<std::invalid_argument>([&] { write(bad); }, {"camera 1", "no name"});
  bad = s;
  bad.cameras[1].name = "a\nb.png";
  expect_error_with<std::invalid_argument>([&] { write(bad); }, {"control character"});
  bad = s;
  bad.cameras[1].name = "with space.png";
  expect_error_with<std::invalid_argument>([&] { write(bad, false); }, {"with space.png", "binary format instead"});
  EXPECT_FALSE(fs::exists(sparse));

  // Spaces are fine in the binary format.
  write(bad, true);
  expect_same_model(read_colmap_model(sparse), bad, 1e-12);
}

TEST(ColmapWriter, WriteFailuresNameTheFile) {
  TempDir dir;
  const Scene s = random_scene(6, 2, 3);
  write_bytes(dir.file("a_file"), "x");
  expect_error_with<std::runtime_error>([&] { write_colmap_model(dir.file("a_file"), s.cameras, s.points, s.colors); },
                                        {dir.file("a_file"), "cannot create the model folder"});

  // One file cannot be replaced: the error names it, the old file stays.
  write_colmap_model(dir.file("m"), s.cameras, s.points, s.colors);
  const std::string old_images = read_bytes(dir.file("m/images.bin"));
  const std::string blocker = dir.file("m/images.bin.tmp." + std::to_string(static_cast<long>(::getpid())));
  fs::create_directories(blocker);
  const Scene other = random_scene(7, 2, 3);
  expect_error_with<std::runtime_error>(
      [&] { write_colmap_model(dir.file("m"), other.cameras, other.points, other.colors); },
      {dir.file("m/images.bin"), "temporary file"});
  EXPECT_EQ(read_bytes(dir.file("m/images.bin")), old_images);
  EXPECT_TRUE(fs::is_directory(blocker));
}

TEST(ColmapWriter, ColmapItselfReadsTheModel) {
  if (!have_colmap()) GTEST_SKIP() << "the colmap program is not on PATH (scripts/install_deps.sh installs it)";
  TempDir dir;
  const Scene s = random_scene(8, 6, 40);
  std::string log;

  // Binary in, text out.
  write_colmap_model(dir.file("bin"), s.cameras, s.points, s.colors, true);
  ASSERT_TRUE(colmap_convert(dir.file("bin"), dir.file("bin_as_txt"), "TXT", &log)) << log;
  EXPECT_TRUE(fs::exists(dir.file("bin_as_txt/cameras.txt"))) << log;
  expect_same_model(read_colmap_model(dir.file("bin_as_txt")), s, 1e-12);

  // Text in, binary out.
  write_colmap_model(dir.file("txt"), s.cameras, s.points, s.colors, false);
  ASSERT_TRUE(colmap_convert(dir.file("txt"), dir.file("txt_as_bin"), "BIN", &log)) << log;
  EXPECT_TRUE(fs::exists(dir.file("txt_as_bin/cameras.bin"))) << log;
  expect_same_model(read_colmap_model(dir.file("txt_as_bin")), s, 1e-12);
}

// ---------------------------------------------------------------- fuzz regressions
//
// Inputs that made a parser crash, hang or report undefined behaviour under
// the fuzzers in fuzz/ (fuzz/README.md), replayed here: named cases as bytes,
// and every file under tests/data/fuzz/<parser>/ as the fuzzer saved it.

#ifndef _WIN32
namespace {

// Runs fn in a child process that must finish within `seconds` and may let
// only std::exception subclasses escape. Returns what went wrong, or "".
std::string run_isolated(const std::function<void()>& fn, unsigned seconds) {
  std::fflush(nullptr);
  const pid_t pid = ::fork();
  if (pid < 0) return std::string("fork failed: ") + std::strerror(errno);
  if (pid == 0) {
    ::alarm(seconds);
    try {
      fn();
    } catch (const std::exception&) {
    } catch (...) {
      std::_Exit(3);
    }
    std::_Exit(0);
  }
  int status = 0;
  if (::waitpid(pid, &status, 0) != pid) return "waitpid failed";
  if (WIFEXITED(status) && WEXITSTATUS(status) == 0) return "";
  if (WIFSIGNALED(status) && WTERMSIG(status) == SIGALRM) {
    return "did not finish within " + std::to_string(seconds) + " s (a hang)";
  }
  if (WIFSIGNALED(status)) return "crashed with signal " + std::to_string(WTERMSIG(status));
  return "exit status " + std::to_string(WEXITSTATUS(status)) + " (an exception not derived from std::exception?)";
}

// The COLMAP targets' input layout (fuzz/fuzz_common.h): two little-endian
// uint32 lengths, cameras, images, and the rest is points3D.
void write_three_files(const std::string& dir, const std::string& input, const std::string& ext) {
  auto u32 = [&](size_t at) {
    uint32_t v = 0;
    for (size_t b = 0; b < 4 && at + b < input.size(); ++b)
      v |= uint32_t(static_cast<unsigned char>(input[at + b])) << (8 * b);
    return size_t(v);
  };
  size_t at = std::min<size_t>(input.size(), 8);
  const size_t lens[2] = {u32(0), u32(4)};
  const char* stems[3] = {"cameras", "images", "points3D"};
  for (int i = 0; i < 3; ++i) {
    const size_t n = i < 2 ? std::min(lens[i], input.size() - at) : input.size() - at;
    write_bytes(dir + "/" + stems[i] + ext, input.substr(at, n));
    at += n;
  }
}

// Parses `input` the way fuzz target `parser` does.
void parse_like_fuzzer(const std::string& parser, const std::string& input, const TempDir& dir) {
  if (parser == "npy") {
    write_bytes(dir.file("input.npy"), input);
    read_npy(dir.file("input.npy"));
  } else if (parser == "ply") {
    write_bytes(dir.file("input.ply"), input);
    read_ply(dir.file("input.ply"));
  } else {
    write_three_files(dir.path().string(), input, parser == "colmap_bin" ? ".bin" : ".txt");
    read_colmap_model(dir.path().string());
  }
}

}  // namespace

TEST(FuzzRegression, SavedInputsParseOrFailCleanly) {
  const fs::path root = fs::path(source_dir()) / "tests" / "data" / "fuzz";
  ASSERT_TRUE(fs::is_directory(root)) << root << " missing; set AG2GS_SOURCE_DIR to the source tree";
  int replayed = 0;
  for (const char* parser : {"npy", "ply", "colmap_bin", "colmap_txt"}) {
    if (!fs::is_directory(root / parser)) continue;
    for (const auto& entry : fs::directory_iterator(root / parser)) {
      SCOPED_TRACE(entry.path().string());
      const std::string input = read_bytes(entry.path().string());
      TempDir dir;
      EXPECT_EQ(run_isolated([&] { parse_like_fuzzer(parser, input, dir); }, 60), "");
      ++replayed;
    }
  }
  EXPECT_GT(replayed, 0);
}

namespace {

std::string ply_header_lines(const std::string& format, const std::string& before_vertex, int vertices) {
  std::string h =
      "ply\nformat " + format + " 1.0\n" + before_vertex + "element vertex " + std::to_string(vertices) + "\n";
  for (const char* p : {"x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
                        "rot_0", "rot_1", "rot_2", "rot_3"}) {
    h += std::string("property float ") + p + "\n";
  }
  return h + "end_header\n";
}

}  // namespace

TEST(FuzzRegression, NpyFortranOrderWithManyUnitDimensions) {
  // Found reviewing the fuzz_npy coverage: the Fortran-to-C transposition
  // carried its index through every dimension, and a header may hold 300k
  // unit dimensions: 10^5 elements took 3 10^10 steps.
  TempDir dir;
  const std::string path = dir.file("a.npy");
  std::string shape = "(100000";
  for (int i = 0; i < 300000; ++i) shape += ", 1";
  shape += ")";
  std::string data(100000, '\0');
  for (size_t i = 0; i < data.size(); ++i) data[i] = static_cast<char>(i % 251);
  write_bytes(path, npy_file(numpy_dict("|u1", true, shape), data, 2));
  EXPECT_EQ(run_isolated([&] { read_npy(path); }, 20), "");
  const NpyArray a = read_npy(path);
  ASSERT_EQ(a.shape.size(), 300001u);
  ASSERT_EQ(a.size(), 100000u);
  EXPECT_EQ(a.data[99999], static_cast<float>(99999 % 251));
}

TEST(FuzzRegression, PlyAsciiElementWithoutPropertiesBeforeTheVertices) {
  // fuzz_ply timeout: the reader skipped the values of an element with no
  // properties once per declared item, 10^19 times.
  TempDir dir;
  const std::string path = dir.file("a.ply");
  write_bytes(path, ply_header_lines("ascii", "element face 9999999999999999999\n", 1) +
                        "1 2 3 0.5 0.5 0.5 0 -1 -1 -1 1 0 0 0\n");
  GaussianSet gs;
  EXPECT_EQ(run_isolated([&] { read_ply(path); }, 20), "");
  ASSERT_NO_THROW(gs = read_ply(path));
  ASSERT_EQ(gs.size(), 1u);
  EXPECT_EQ(gs.means[2], 3.f);
}

TEST(FuzzRegression, PlyHeaderWithFiftyThousandProperties) {
  // Found next to the one above: duplicate names were looked for pairwise, so
  // a 1 MiB header of distinct properties took about 20 s to reject.
  TempDir dir;
  const std::string path = dir.file("a.ply");
  std::string extra;
  for (int i = 0; i < 50000; ++i) extra += "property char p" + std::to_string(i) + "\n";
  std::string h = ply_header_lines("binary_little_endian", "", 0);
  h.insert(h.find("end_header"), extra);
  ASSERT_LT(h.size(), size_t(1) << 20);
  write_bytes(path, h);
  EXPECT_EQ(run_isolated([&] { read_ply(path); }, 20), "");
  const GaussianSet gs = read_ply(path);
  EXPECT_EQ(gs.size(), 0u);
  h.insert(h.find("end_header"), "property char p77\n");
  write_bytes(path, h);
  expect_error_with<std::runtime_error>([&] { read_ply(path); }, {path, "'p77' appears twice"});
}
#endif  // _WIN32
