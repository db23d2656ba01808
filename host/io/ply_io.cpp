// 3DGS point_cloud.ply reader and atomic writer (layout: host/io/ply_io.h).
#include "host/io/ply_io.h"

#include <algorithm>
#include <cctype>
#include <cerrno>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <set>
#include <sstream>
#include <stdexcept>
#include <string>
#include <vector>

#include "host/io/atomic_file.h"

namespace ag2gs {
namespace {

constexpr const char* kExpected = "expected a 3D Gaussian Splatting point_cloud.ply";
constexpr size_t kMaxHeaderBytes = size_t(1) << 20;
constexpr size_t kChunkVertices = size_t(1) << 16;

[[noreturn]] void fail(const std::string& path, const std::string& what) {
  throw std::runtime_error(path + ": " + what);
}

// ---------------------------------------------------------------- header

enum class PlyType { Int8, UInt8, Int16, UInt16, Int32, UInt32, Float32, Float64 };

bool parse_type(const std::string& s, PlyType* type, int* bytes) {
  struct Entry {
    const char* name;
    PlyType type;
    int bytes;
  };
  static const Entry kTypes[] = {
      {"char", PlyType::Int8, 1},       {"int8", PlyType::Int8, 1},       {"uchar", PlyType::UInt8, 1},
      {"uint8", PlyType::UInt8, 1},     {"short", PlyType::Int16, 2},     {"int16", PlyType::Int16, 2},
      {"ushort", PlyType::UInt16, 2},   {"uint16", PlyType::UInt16, 2},   {"int", PlyType::Int32, 4},
      {"int32", PlyType::Int32, 4},     {"uint", PlyType::UInt32, 4},     {"uint32", PlyType::UInt32, 4},
      {"float", PlyType::Float32, 4},   {"float32", PlyType::Float32, 4}, {"double", PlyType::Float64, 8},
      {"float64", PlyType::Float64, 8},
  };
  for (const Entry& e : kTypes) {
    if (s == e.name) {
      *type = e.type;
      *bytes = e.bytes;
      return true;
    }
  }
  return false;
}

struct PlyProperty {
  std::string name;
  PlyType type = PlyType::Float32;
  int bytes = 4;
  bool is_list = false;
  PlyType count_type = PlyType::UInt8;
  int count_bytes = 1;
};

struct PlyElement {
  std::string name;
  uint64_t count = 0;
  std::vector<PlyProperty> props;

  bool has_list() const {
    return std::any_of(props.begin(), props.end(), [](const PlyProperty& p) { return p.is_list; });
  }
  size_t stride() const {  // bytes per item, scalar properties only
    size_t s = 0;
    for (const PlyProperty& p : props) s += static_cast<size_t>(p.bytes);
    return s;
  }
};

enum class PlyFormat { Ascii, BinaryLittleEndian };

struct PlyHeader {
  PlyFormat format = PlyFormat::BinaryLittleEndian;
  std::vector<PlyElement> elements;
  uint64_t data_offset = 0;  // first byte after "end_header\n"
};

bool parse_count(const std::string& s, uint64_t* out) {
  if (s.empty() || s.size() > 19) return false;
  uint64_t v = 0;
  for (char ch : s) {
    if (ch < '0' || ch > '9') return false;
    v = v * 10 + static_cast<uint64_t>(ch - '0');
  }
  *out = v;
  return true;
}

PlyHeader parse_header(const std::string& path, std::ifstream& in, uint64_t file_size) {
  if (file_size == 0) fail(path, std::string("empty file (0 bytes); ") + kExpected);
  std::string head(static_cast<size_t>(std::min<uint64_t>(file_size, kMaxHeaderBytes)), '\0');
  in.seekg(0);
  in.read(&head[0], static_cast<std::streamsize>(head.size()));
  if (static_cast<size_t>(in.gcount()) != head.size()) fail(path, "read error in the header");

  if (head.compare(0, 4, "ply\n") != 0 && head.compare(0, 5, "ply\r\n") != 0) {
    fail(path, std::string("not a PLY file (missing 'ply' magic on the first line); ") + kExpected);
  }

  PlyHeader header;
  bool have_format = false;
  size_t pos = 0;
  int line_no = 0;
  while (true) {
    const size_t eol = head.find('\n', pos);
    if (eol == std::string::npos) {
      if (head.size() < file_size) {
        fail(path, "no 'end_header' within the first 1 MiB; the header is corrupt");
      }
      fail(path, "the header ends without 'end_header'; the file is truncated or not a PLY");
    }
    std::string line = head.substr(pos, eol - pos);
    pos = eol + 1;
    ++line_no;
    if (!line.empty() && line.back() == '\r') line.pop_back();
    if (line_no == 1) continue;  // "ply"

    std::istringstream ss(line);
    std::string key;
    ss >> key;
    auto bad_line = [&](const std::string& why) {
      fail(path, "header line " + std::to_string(line_no) + " '" + line + "': " + why);
    };
    if (key.empty() || key == "comment" || key == "obj_info") continue;
    if (key == "end_header") break;
    if (key == "format") {
      std::string fmt, version;
      ss >> fmt >> version;
      if (fmt == "ascii") {
        header.format = PlyFormat::Ascii;
      } else if (fmt == "binary_little_endian") {
        header.format = PlyFormat::BinaryLittleEndian;
      } else if (fmt == "binary_big_endian") {
        fail(path,
             "binary_big_endian PLY is not supported; convert it to binary_little_endian "
             "(re-export it, or load and save it with a PLY tool such as Python plyfile)");
      } else {
        bad_line("unknown format '" + fmt + "'; expected binary_little_endian or ascii");
      }
      have_format = true;
    } else if (key == "element") {
      PlyElement e;
      std::string count;
      ss >> e.name >> count;
      if (e.name.empty() || !parse_count(count, &e.count)) {
        bad_line("expected 'element <name> <count>' with a non-negative count");
      }
      header.elements.push_back(e);
    } else if (key == "property") {
      if (header.elements.empty()) bad_line("property before any element");
      PlyProperty p;
      std::string type;
      ss >> type;
      if (type == "list") {
        std::string count_type, item_type;
        ss >> count_type >> item_type >> p.name;
        p.is_list = true;
        if (!parse_type(count_type, &p.count_type, &p.count_bytes) || !parse_type(item_type, &p.type, &p.bytes) ||
            p.name.empty()) {
          bad_line("expected 'property list <count type> <item type> <name>'");
        }
      } else {
        ss >> p.name;
        if (!parse_type(type, &p.type, &p.bytes) || p.name.empty()) {
          bad_line("expected 'property <type> <name>' with a PLY scalar type");
        }
      }
      header.elements.back().props.push_back(p);
    } else {
      bad_line("unknown keyword '" + key + "'");
    }
  }
  if (!have_format) fail(path, "the header has no 'format' line");
  header.data_offset = pos;
  return header;
}

// ---------------------------------------------------------------- values

// Little-endian loads, independent of the host's byte order.
inline uint32_t load_u32(const unsigned char* p) {
  return uint32_t(p[0]) | uint32_t(p[1]) << 8 | uint32_t(p[2]) << 16 | uint32_t(p[3]) << 24;
}
inline uint64_t load_u64(const unsigned char* p) {
  return uint64_t(load_u32(p)) | uint64_t(load_u32(p + 4)) << 32;
}

float load_value(PlyType type, const unsigned char* p) {
  switch (type) {
    case PlyType::Int8:
      return static_cast<float>(static_cast<int8_t>(p[0]));
    case PlyType::UInt8:
      return static_cast<float>(p[0]);
    case PlyType::Int16:
      return static_cast<float>(static_cast<int16_t>(uint16_t(p[0] | p[1] << 8)));
    case PlyType::UInt16:
      return static_cast<float>(uint16_t(p[0] | p[1] << 8));
    case PlyType::Int32:
      return static_cast<float>(static_cast<int32_t>(load_u32(p)));
    case PlyType::UInt32:
      return static_cast<float>(load_u32(p));
    case PlyType::Float32: {
      const uint32_t u = load_u32(p);
      float f;
      std::memcpy(&f, &u, 4);
      return f;
    }
    case PlyType::Float64: {
      const uint64_t u = load_u64(p);
      double d;
      std::memcpy(&d, &u, 8);
      return static_cast<float>(d);
    }
  }
  return 0.f;
}

inline void store_f32(unsigned char* p, float f) {
  uint32_t u;
  std::memcpy(&u, &f, 4);
  p[0] = u & 0xff;
  p[1] = (u >> 8) & 0xff;
  p[2] = (u >> 16) & 0xff;
  p[3] = (u >> 24) & 0xff;
}

// Slots of one vertex's raw (pre-activation) values.
constexpr int kSlotXyz = 0;
constexpr int kSlotDc = 3;
constexpr int kSlotRest = 6;  // up to 45
constexpr int kSlotOpacity = 51;
constexpr int kSlotScale = 52;
constexpr int kSlotRot = 55;
constexpr int kSlotFeat = 59;
constexpr int kSlotCount = 62;

struct VertexLayout {
  int sh_degree = 0;
  std::vector<int> slot;       // per vertex property: raw slot, -1 = ignored
  std::vector<size_t> offset;  // per vertex property: byte offset (binary)
};

bool rest_index(const std::string& name, int* index) {
  static const std::string prefix = "f_rest_";
  if (name.compare(0, prefix.size(), prefix) != 0 || name.size() == prefix.size() || name.size() > prefix.size() + 6) {
    return false;
  }
  int v = 0;
  for (size_t i = prefix.size(); i < name.size(); ++i) {
    if (name[i] < '0' || name[i] > '9') return false;
    v = v * 10 + (name[i] - '0');
  }
  *index = v;
  return true;
}

VertexLayout map_vertex(const std::string& path, const PlyElement& vertex) {
  struct Named {
    const char* name;
    int slot;
  };
  static const Named kRequired[] = {
      {"x", kSlotXyz},
      {"y", kSlotXyz + 1},
      {"z", kSlotXyz + 2},
      {"f_dc_0", kSlotDc},
      {"f_dc_1", kSlotDc + 1},
      {"f_dc_2", kSlotDc + 2},
      {"opacity", kSlotOpacity},
      {"scale_0", kSlotScale},
      {"scale_1", kSlotScale + 1},
      {"scale_2", kSlotScale + 2},
      {"rot_0", kSlotRot},
      {"rot_1", kSlotRot + 1},
      {"rot_2", kSlotRot + 2},
      {"rot_3", kSlotRot + 3},
  };
  static const Named kOptional[] = {{"feat_0", kSlotFeat}, {"feat_1", kSlotFeat + 1}, {"feat_2", kSlotFeat + 2}};

  VertexLayout layout;
  layout.slot.assign(vertex.props.size(), -1);
  layout.offset.assign(vertex.props.size(), 0);
  std::vector<int> rest_prop(45, -1);
  int rest_count = 0;
  int rest_out_of_range = -1;
  size_t offset = 0;
  std::set<std::string> seen;  // not a pairwise check: a 1 MiB header declares ~50k properties
  for (size_t i = 0; i < vertex.props.size(); ++i) {
    const PlyProperty& p = vertex.props[i];
    if (p.is_list) {
      fail(path, "vertex property '" + p.name + "' is a list; " + kExpected);
    }
    if (!seen.insert(p.name).second) fail(path, "vertex property '" + p.name + "' appears twice");
    layout.offset[i] = offset;
    offset += static_cast<size_t>(p.bytes);
    for (const Named& r : kRequired) {
      if (p.name == r.name) layout.slot[i] = r.slot;
    }
    for (const Named& r : kOptional) {
      if (p.name == r.name) layout.slot[i] = r.slot;
    }
    int index = 0;
    if (rest_index(p.name, &index)) {
      ++rest_count;
      if (index < 45) {
        rest_prop[static_cast<size_t>(index)] = static_cast<int>(i);
      } else {
        rest_out_of_range = index;
      }
    }
  }

  std::vector<std::string> missing;
  for (const Named& r : kRequired) {
    if (std::find(layout.slot.begin(), layout.slot.end(), r.slot) == layout.slot.end()) {
      missing.push_back(r.name);
    }
  }
  if (!missing.empty()) {
    std::string list;
    for (size_t i = 0; i < missing.size(); ++i) list += (i ? ", '" : "'") + missing[i] + "'";
    fail(path,
         std::string(missing.size() == 1 ? "missing property " : "missing properties ") + list + "; " + kExpected);
  }

  int degree = -1;
  for (int d = 0; d <= 3; ++d) {
    if (rest_count == 3 * (sh_coeffs_for_degree(d) - 1)) degree = d;
  }
  if (degree < 0) {
    fail(path, "has " + std::to_string(rest_count) + " f_rest_* properties; expected 0, 9, 24 or 45 (SH degree 0..3)");
  }
  if (rest_out_of_range >= 0) {
    fail(path, "property 'f_rest_" + std::to_string(rest_out_of_range) + "' is out of range for " +
                   std::to_string(rest_count) + " f_rest_* properties");
  }
  for (int k = 0; k < rest_count; ++k) {
    if (rest_prop[static_cast<size_t>(k)] < 0) {
      fail(path, "missing property 'f_rest_" + std::to_string(k) + "' among " + std::to_string(rest_count) +
                     " f_rest_* properties");
    }
    layout.slot[static_cast<size_t>(rest_prop[static_cast<size_t>(k)])] = kSlotRest + k;
  }
  layout.sh_degree = degree;
  return layout;
}

// Applies the activations to one vertex's raw values.
void store_vertex(const float* raw, size_t n, GaussianSet& gs, PlyValues values) {
  const size_t k_count = static_cast<size_t>(gs.sh_coeffs());
  for (int i = 0; i < 3; ++i) gs.means[n * 3 + i] = raw[kSlotXyz + i];
  for (int c = 0; c < 3; ++c) gs.sh[(n * k_count) * 3 + c] = raw[kSlotDc + c];
  for (size_t c = 0; c < 3; ++c) {
    for (size_t k = 1; k < k_count; ++k) {
      gs.sh[(n * k_count + k) * 3 + c] = raw[kSlotRest + c * (k_count - 1) + (k - 1)];
    }
  }
  if (values == PlyValues::stored) {
    gs.opacities[n] = raw[kSlotOpacity];
    for (int i = 0; i < 3; ++i) gs.scales[n * 3 + i] = raw[kSlotScale + i];
  } else {
    gs.opacities[n] = static_cast<float>(1.0 / (1.0 + std::exp(-static_cast<double>(raw[kSlotOpacity]))));
    for (int i = 0; i < 3; ++i) {
      gs.scales[n * 3 + i] = static_cast<float>(std::exp(static_cast<double>(raw[kSlotScale + i])));
    }
  }
  for (int i = 0; i < 4; ++i) gs.quats[n * 4 + i] = raw[kSlotRot + i];
  for (int i = 0; i < 3; ++i) gs.features[n * 3 + i] = raw[kSlotFeat + i];
}

std::string truncated_message(uint64_t expected, uint64_t holds, const std::string& what) {
  return "truncated: header says " + std::to_string(expected) + " vertices but data holds " + std::to_string(holds) +
         what + "; the file is incomplete or its header is corrupt (re-export or re-copy it)";
}

void read_binary(const std::string& path, std::ifstream& in, uint64_t file_size, const PlyHeader& header,
                 size_t vertex_index, const VertexLayout& layout, GaussianSet& gs, PlyValues values) {
  uint64_t offset = header.data_offset;
  for (size_t e = 0; e < vertex_index; ++e) {
    const PlyElement& el = header.elements[e];
    if (el.has_list()) {
      fail(path,
           "element '" + el.name + "' before 'vertex' has list properties; this layout is not supported, " + kExpected);
    }
    const uint64_t stride = el.stride();
    const uint64_t left = file_size - std::min(file_size, offset);
    if (stride > 0 && el.count > left / stride) {
      fail(path, "truncated: element '" + el.name + "' needs more bytes than the file holds");
    }
    offset += el.count * stride;
  }
  const PlyElement& vertex = header.elements[vertex_index];
  const uint64_t stride = vertex.stride();
  const uint64_t left = file_size - std::min(file_size, offset);
  const uint64_t holds = left / stride;
  if (vertex.count > holds) {
    fail(path, truncated_message(vertex.count, holds, " (" + std::to_string(stride) + " bytes per vertex)"));
  }

  gs.resize(static_cast<size_t>(vertex.count));
  in.clear();
  in.seekg(static_cast<std::streamoff>(offset));
  std::vector<unsigned char> chunk;
  float raw[kSlotCount] = {};
  const size_t n_props = vertex.props.size();
  for (size_t start = 0; start < vertex.count; start += kChunkVertices) {
    const size_t n = static_cast<size_t>(std::min<uint64_t>(kChunkVertices, vertex.count - start));
    chunk.resize(n * stride);
    in.read(reinterpret_cast<char*>(chunk.data()), static_cast<std::streamsize>(chunk.size()));
    if (static_cast<size_t>(in.gcount()) != chunk.size()) {
      fail(path, truncated_message(vertex.count, start + static_cast<size_t>(in.gcount()) / stride, " (read failed)"));
    }
    for (size_t v = 0; v < n; ++v) {
      const unsigned char* base = chunk.data() + v * stride;
      for (size_t p = 0; p < n_props; ++p) {
        const int s = layout.slot[p];
        if (s >= 0) raw[s] = load_value(vertex.props[p].type, base + layout.offset[p]);
      }
      store_vertex(raw, start + v, gs, values);
    }
  }
}

void read_ascii(const std::string& path, std::ifstream& in, uint64_t file_size, const PlyHeader& header,
                size_t vertex_index, const VertexLayout& layout, GaussianSet& gs, PlyValues values) {
  const uint64_t left = file_size - std::min(file_size, header.data_offset);
  std::string text(static_cast<size_t>(left), '\0');
  in.clear();
  in.seekg(static_cast<std::streamoff>(header.data_offset));
  in.read(&text[0], static_cast<std::streamsize>(text.size()));
  const char* cur = text.c_str();
  const char* end = cur + text.size();

  // Returns false at the end of the data; throws on a malformed token.
  auto next = [&](double* value, const std::string& where) {
    while (cur < end && std::isspace(static_cast<unsigned char>(*cur))) ++cur;
    if (cur >= end) return false;
    char* after = nullptr;
    *value = std::strtod(cur, &after);
    if (after == cur || (after < end && !std::isspace(static_cast<unsigned char>(*after)))) {
      const char* tok_end = cur;
      while (tok_end < end && !std::isspace(static_cast<unsigned char>(*tok_end))) ++tok_end;
      fail(path, "bad number '" + std::string(cur, tok_end) + "' in " + where);
    }
    cur = after;
    return true;
  };

  double value = 0;
  for (size_t e = 0; e < vertex_index; ++e) {
    const PlyElement& el = header.elements[e];
    const std::string where = "element '" + el.name + "'";
    if (el.props.empty()) continue;  // no values to skip, however large its count (fuzz: a hang)
    for (uint64_t i = 0; i < el.count; ++i) {
      for (const PlyProperty& p : el.props) {
        if (!next(&value, where)) fail(path, "truncated: data ends inside " + where);
        if (p.is_list) {
          if (!(value >= 0 && value < 1e9)) fail(path, "bad list length in " + where);
          for (long j = 0; j < static_cast<long>(value); ++j) {
            double item = 0;
            if (!next(&item, where)) fail(path, "truncated: data ends inside " + where);
          }
        }
      }
    }
  }

  const PlyElement& vertex = header.elements[vertex_index];
  const uint64_t n_props = vertex.props.size();
  // Every value takes at least one character and one separator.
  const uint64_t remaining = static_cast<uint64_t>(end - cur);
  if (vertex.count > (remaining + 1) / (2 * n_props)) {
    fail(path, truncated_message(vertex.count, (remaining + 1) / (2 * n_props), " at most (ascii data too short)"));
  }
  gs.resize(static_cast<size_t>(vertex.count));
  float raw[kSlotCount] = {};
  for (uint64_t v = 0; v < vertex.count; ++v) {
    for (size_t p = 0; p < n_props; ++p) {
      if (!next(&value, "vertex " + std::to_string(v))) {
        fail(path, truncated_message(vertex.count, v, ""));
      }
      const int s = layout.slot[p];
      if (s >= 0) raw[s] = static_cast<float>(value);
    }
    store_vertex(raw, static_cast<size_t>(v), gs, values);
  }
}

// Removes the temporary file unless the write was committed.

}  // namespace

namespace {

// The file as it is, numbers unchecked.
GaussianSet read_ply_unchecked(const std::string& path, PlyValues values) {
  if (std::filesystem::is_directory(path)) fail(path, std::string("is a folder, not a .ply file; ") + kExpected);
  std::ifstream in(path, std::ios::binary);
  if (!in) fail(path, std::string("cannot open: ") + std::strerror(errno));
  in.seekg(0, std::ios::end);
  const std::streamoff end = in.tellg();
  if (end < 0) fail(path, "cannot determine the file size (not a regular file?)");
  const uint64_t file_size = static_cast<uint64_t>(end);

  const PlyHeader header = parse_header(path, in, file_size);
  size_t vertex_index = header.elements.size();
  for (size_t e = 0; e < header.elements.size(); ++e) {
    if (header.elements[e].name == "vertex") {
      vertex_index = e;
      break;
    }
  }
  if (vertex_index == header.elements.size()) {
    fail(path, std::string("no 'element vertex' in the header; ") + kExpected);
  }
  const VertexLayout layout = map_vertex(path, header.elements[vertex_index]);

  GaussianSet gs;
  gs.sh_degree = layout.sh_degree;
  if (header.format == PlyFormat::BinaryLittleEndian) {
    read_binary(path, in, file_size, header, vertex_index, layout, gs, values);
  } else {
    read_ascii(path, in, file_size, header, vertex_index, layout, gs, values);
  }
  return gs;
}

// What is wrong with Gaussian g ("" when nothing).
std::string invalid_reason(const GaussianSet& gs, size_t g, PlyValues values) {
  auto bad = [](const char* name, int i, float v) {
    char buf[96];
    if (i < 0)
      std::snprintf(buf, sizeof buf, "%s = %g", name, static_cast<double>(v));
    else
      std::snprintf(buf, sizeof buf, "%s_%d = %g", name, i, static_cast<double>(v));
    return std::string(buf);
  };
  for (int i = 0; i < 3; ++i)
    if (!std::isfinite(gs.means[g * 3 + i])) return bad("position", i, gs.means[g * 3 + i]);
  for (int i = 0; i < 3; ++i) {
    const float v = gs.scales[g * 3 + i];
    if (!std::isfinite(v) || (values == PlyValues::activated && !(v > 0))) return bad("scale", i, v);
  }
  float q2 = 0;
  for (int i = 0; i < 4; ++i) {
    const float v = gs.quats[g * 4 + i];
    if (!std::isfinite(v)) return bad("rot", i, v);
    q2 += v * v;
  }
  if (!(q2 > 0)) return "rotation (0, 0, 0, 0), which is no rotation";
  const float o = gs.opacities[g];
  if (!std::isfinite(o) || (values == PlyValues::activated && !(o >= 0 && o <= 1))) return bad("opacity", -1, o);
  const size_t k = static_cast<size_t>(gs.sh_coeffs());
  for (size_t j = 0; j < k * 3; ++j)
    if (!std::isfinite(gs.sh[g * k * 3 + j])) return bad("sh", static_cast<int>(j), gs.sh[g * k * 3 + j]);
  for (int i = 0; i < 3; ++i)
    if (!std::isfinite(gs.features[g * 3 + i])) return bad("feat", i, gs.features[g * 3 + i]);
  return {};
}

}  // namespace

InvalidReport find_invalid_gaussians(const GaussianSet& gs, PlyValues values) {
  InvalidReport r;
  for (size_t g = 0; g < gs.size(); ++g) {
    std::string why = invalid_reason(gs, g, values);
    if (why.empty()) continue;
    if (r.count++ == 0) {
      r.first = g;
      r.what = std::move(why);
    }
  }
  return r;
}

GaussianSet read_ply(const std::string& path, PlyValues values, InvalidGaussians policy, size_t* dropped) {
  GaussianSet gs = read_ply_unchecked(path, values);
  if (dropped) *dropped = 0;
  if (policy == InvalidGaussians::keep) return gs;
  const InvalidReport bad = find_invalid_gaussians(gs, values);
  if (bad.count == 0) return gs;
  if (policy == InvalidGaussians::reject)
    fail(path, std::to_string(bad.count) + " of " + std::to_string(gs.size()) +
                   " Gaussians hold invalid numbers (the first: vertex " + std::to_string(bad.first) + ", " +
                   bad.what + "); the file is damaged or was written by a diverged run. Give --drop-invalid to "
                   "leave them out");
  GaussianSet kept;
  kept.sh_degree = gs.sh_degree;
  kept.resize(gs.size() - bad.count);
  const size_t k3 = static_cast<size_t>(gs.sh_coeffs()) * 3;
  size_t out = 0;
  for (size_t g = 0; g < gs.size(); ++g) {
    if (!invalid_reason(gs, g, values).empty()) continue;
    std::copy_n(&gs.means[g * 3], 3, &kept.means[out * 3]);
    std::copy_n(&gs.scales[g * 3], 3, &kept.scales[out * 3]);
    std::copy_n(&gs.quats[g * 4], 4, &kept.quats[out * 4]);
    kept.opacities[out] = gs.opacities[g];
    std::copy_n(&gs.sh[g * k3], k3, &kept.sh[out * k3]);
    std::copy_n(&gs.features[g * 3], 3, &kept.features[out * 3]);
    ++out;
  }
  if (dropped) *dropped = bad.count;
  return kept;
}

void write_ply(const std::string& path, const GaussianSet& gs, bool with_features, PlyValues values) {
  gs.validate();
  const size_t n = gs.size();
  const size_t k_count = static_cast<size_t>(gs.sh_coeffs());
  const size_t n_rest = 3 * (k_count - 1);

  std::vector<std::string> names = {"x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"};
  for (size_t i = 0; i < n_rest; ++i) names.push_back("f_rest_" + std::to_string(i));
  for (const char* s : {"opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"}) {
    names.push_back(s);
  }
  if (with_features) {
    for (const char* s : {"feat_0", "feat_1", "feat_2"}) names.push_back(s);
  }
  std::string header = "ply\nformat binary_little_endian 1.0\nelement vertex " + std::to_string(n) + "\n";
  for (const std::string& name : names) header += "property float " + name + "\n";
  header += "end_header\n";

  AtomicFile out(path);
  auto write_or_fail = [&](const void* data, size_t bytes) { out.write(data, bytes); };
  write_or_fail(header.data(), header.size());

  const size_t stride = names.size() * 4;
  std::vector<unsigned char> chunk;
  std::vector<float> row(names.size(), 0.f);
  for (size_t start = 0; start < n; start += kChunkVertices) {
    const size_t count = std::min(kChunkVertices, n - start);
    chunk.resize(count * stride);
    for (size_t v = 0; v < count; ++v) {
      const size_t g = start + v;
      size_t j = 0;
      for (int i = 0; i < 3; ++i) row[j++] = gs.means[g * 3 + i];
      for (int i = 0; i < 3; ++i) row[j++] = 0.f;  // normals: unused by 3DGS
      for (int c = 0; c < 3; ++c) row[j++] = gs.sh[(g * k_count) * 3 + c];
      for (size_t c = 0; c < 3; ++c) {
        for (size_t k = 1; k < k_count; ++k) row[j++] = gs.sh[(g * k_count + k) * 3 + c];
      }
      if (values == PlyValues::stored) {
        row[j++] = gs.opacities[g];
        for (int i = 0; i < 3; ++i) row[j++] = gs.scales[g * 3 + i];
      } else {
        const double o = std::clamp(static_cast<double>(gs.opacities[g]), 1e-7, 1.0 - 1e-7);
        row[j++] = static_cast<float>(std::log(o / (1.0 - o)));
        for (int i = 0; i < 3; ++i) {
          row[j++] = static_cast<float>(std::log(std::max(static_cast<double>(gs.scales[g * 3 + i]), 1e-30)));
        }
      }
      for (int i = 0; i < 4; ++i) row[j++] = gs.quats[g * 4 + i];
      if (with_features) {
        for (int i = 0; i < 3; ++i) row[j++] = gs.features[g * 3 + i];
      }
      unsigned char* out = chunk.data() + v * stride;
      for (size_t i = 0; i < row.size(); ++i) store_f32(out + i * 4, row[i]);
    }
    write_or_fail(chunk.data(), chunk.size());
  }

  out.commit();
}

}  // namespace ag2gs
