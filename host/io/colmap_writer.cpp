// COLMAP sparse model writer (binary and text). File formats:
// https://colmap.github.io/format.html; the binary layout is the one of
// COLMAP's scripts/python/read_write_model.py (little-endian throughout).
#include "host/io/colmap_writer.h"

#include <Eigen/Geometry>
#include <cerrno>
#include <charconv>
#include <climits>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <set>
#include <stdexcept>
#include <string>
#include <system_error>

#include "host/io/atomic_file.h"

namespace ag2gs {
namespace {

namespace fs = std::filesystem;

constexpr int kPinholeModelId = 1;  // COLMAP's id of the PINHOLE model (fx, fy, cx, cy)
const Eigen::Vector3<uint8_t> kGrey(128, 128, 128);

[[noreturn]] void fail(const std::string& path, const std::string& what) {
  throw std::runtime_error(path + ": " + what);
}

// ---------------------------------------------------------------- encoding

// Little-endian appends, independent of the host's byte order.
void put_u64(std::string& out, uint64_t v) {
  for (int b = 0; b < 8; ++b) out += static_cast<char>((v >> (8 * b)) & 0xff);
}
void put_i32(std::string& out, int32_t v) {
  const uint32_t u = static_cast<uint32_t>(v);
  for (int b = 0; b < 4; ++b) out += static_cast<char>((u >> (8 * b)) & 0xff);
}
void put_f64(std::string& out, double v) {
  uint64_t u;
  std::memcpy(&u, &v, 8);
  put_u64(out, u);
}

// The shortest decimal that reads back to the same double (locale independent).
std::string num(double v) {
  char buf[64];
  const auto r = std::to_chars(buf, buf + sizeof(buf), v);
  return std::string(buf, r.ptr);
}

// Unit quaternion (w, x, y, z) of a rotation matrix, w >= 0 (q and -q are the
// same rotation; COLMAP stores either, we pick one for reproducible files).
Eigen::Vector4d rotation_to_quaternion(const Eigen::Matrix3d& R) {
  Eigen::Quaterniond q(R);
  q.normalize();
  Eigen::Vector4d wxyz(q.w(), q.x(), q.y(), q.z());
  if (wxyz[0] < 0) wxyz = -wxyz;
  return wxyz;
}

// ---------------------------------------------------------------- the three files

std::string cameras_bin(const std::vector<Camera>& cameras) {
  std::string out;
  put_u64(out, cameras.size());
  for (size_t i = 0; i < cameras.size(); ++i) {
    const Camera& c = cameras[i];
    put_i32(out, static_cast<int32_t>(i + 1));
    put_i32(out, kPinholeModelId);
    put_u64(out, static_cast<uint64_t>(c.width));
    put_u64(out, static_cast<uint64_t>(c.height));
    for (double p : {c.fx, c.fy, c.cx, c.cy}) put_f64(out, p);
  }
  return out;
}

std::string images_bin(const std::vector<Camera>& cameras) {
  std::string out;
  put_u64(out, cameras.size());
  for (size_t i = 0; i < cameras.size(); ++i) {
    const Camera& c = cameras[i];
    const int32_t id = static_cast<int32_t>(i + 1);
    put_i32(out, id);
    const Eigen::Vector4d q = rotation_to_quaternion(c.R);
    for (int k = 0; k < 4; ++k) put_f64(out, q[k]);
    for (int k = 0; k < 3; ++k) put_f64(out, c.t[k]);
    put_i32(out, id);  // its own camera
    out += c.name;
    out += '\0';
    put_u64(out, 0);  // no 2D points
  }
  return out;
}

std::string points_bin(const std::vector<Eigen::Vector3d>& points, const std::vector<Eigen::Vector3<uint8_t>>& colors) {
  std::string out;
  out.reserve(8 + points.size() * 51);
  put_u64(out, points.size());
  for (size_t i = 0; i < points.size(); ++i) {
    put_u64(out, i + 1);
    for (int k = 0; k < 3; ++k) put_f64(out, points[i][k]);
    const Eigen::Vector3<uint8_t>& rgb = colors.empty() ? kGrey : colors[i];
    for (int k = 0; k < 3; ++k) out += static_cast<char>(rgb[k]);
    put_f64(out, 0.0);  // reprojection error
    put_u64(out, 0);    // empty track
  }
  return out;
}

std::string cameras_txt(const std::vector<Camera>& cameras) {
  std::string out =
      "# Camera list with one line of data per camera:\n"
      "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
      "# Number of cameras: " +
      std::to_string(cameras.size()) + "\n";
  for (size_t i = 0; i < cameras.size(); ++i) {
    const Camera& c = cameras[i];
    out += std::to_string(i + 1) + " PINHOLE " + std::to_string(c.width) + " " + std::to_string(c.height) + " " +
           num(c.fx) + " " + num(c.fy) + " " + num(c.cx) + " " + num(c.cy) + "\n";
  }
  return out;
}

std::string images_txt(const std::vector<Camera>& cameras) {
  std::string out =
      "# Image list with two lines of data per image:\n"
      "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n"
      "#   POINTS2D[] as (X, Y, POINT3D_ID)\n"
      "# Number of images: " +
      std::to_string(cameras.size()) + ", mean observations per image: 0\n";
  for (size_t i = 0; i < cameras.size(); ++i) {
    const Camera& c = cameras[i];
    const Eigen::Vector4d q = rotation_to_quaternion(c.R);
    const std::string id = std::to_string(i + 1);
    out += id;
    for (int k = 0; k < 4; ++k) out += " " + num(q[k]);
    for (int k = 0; k < 3; ++k) out += " " + num(c.t[k]);
    out += " " + id + " " + c.name + "\n";
    out += "\n";  // the (empty) line of 2D points
  }
  return out;
}

std::string points_txt(const std::vector<Eigen::Vector3d>& points, const std::vector<Eigen::Vector3<uint8_t>>& colors) {
  std::string out =
      "# 3D point list with one line of data per point:\n"
      "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n"
      "# Number of points: " +
      std::to_string(points.size()) + ", mean track length: 0\n";
  for (size_t i = 0; i < points.size(); ++i) {
    const Eigen::Vector3<uint8_t>& rgb = colors.empty() ? kGrey : colors[i];
    out += std::to_string(i + 1) + " " + num(points[i].x()) + " " + num(points[i].y()) + " " + num(points[i].z()) +
           " " + std::to_string(rgb[0]) + " " + std::to_string(rgb[1]) + " " + std::to_string(rgb[2]) + " 0\n";
  }
  return out;
}

// ---------------------------------------------------------------- atomic write

void write_atomic(const std::string& path, const std::string& bytes) {
  AtomicFile out(path);
  out.write(bytes.data(), bytes.size());
  out.commit();
}

void check_inputs(const std::vector<Camera>& cameras, const std::vector<Eigen::Vector3d>& points,
                  const std::vector<Eigen::Vector3<uint8_t>>& colors, bool binary) {
  auto bad = [](const std::string& what) { throw std::invalid_argument("write_colmap_model: " + what); };
  if (!colors.empty() && colors.size() != points.size()) {
    bad(std::to_string(colors.size()) + " colours for " + std::to_string(points.size()) +
        " points; pass one colour per point or none (grey)");
  }
  if (cameras.size() >= static_cast<size_t>(INT32_MAX)) bad("too many cameras for COLMAP's int32 ids");
  std::set<std::string> names;
  for (size_t i = 0; i < cameras.size(); ++i) {
    const Camera& c = cameras[i];
    const std::string who = "camera " + std::to_string(i) + " ('" + c.name + "')";
    c.validate();  // std::invalid_argument naming the camera
    if (c.name.empty()) bad("camera " + std::to_string(i) + " has no name; COLMAP needs an image name per camera");
    for (char ch : c.name) {
      const bool control = static_cast<unsigned char>(ch) < 0x20 || ch == 0x7f;
      if (control || (!binary && ch == ' ')) {
        bad(who + ": the image name holds " + (control ? "a control character" : "a space") + ", which COLMAP's " +
            (binary ? "" : "text ") + "format cannot store" + (binary ? "" : "; write the binary format instead"));
      }
    }
    if (!names.insert(c.name).second) bad(who + ": the image name appears twice; COLMAP needs unique names");
  }
}

}  // namespace

void write_colmap_model(const std::string& sparse_dir, const std::vector<Camera>& cameras,
                        const std::vector<Eigen::Vector3d>& points, const std::vector<Eigen::Vector3<uint8_t>>& colors,
                        bool binary) {
  check_inputs(cameras, points, colors, binary);

  std::error_code ec;
  fs::create_directories(sparse_dir, ec);
  if (ec || !fs::is_directory(sparse_dir)) {
    fail(sparse_dir, "cannot create the model folder: " + (ec ? ec.message() : std::string("not a directory")));
  }
  const fs::path dir(sparse_dir);
  const char* ext = binary ? ".bin" : ".txt";
  const char* other = binary ? ".txt" : ".bin";
  write_atomic((dir / (std::string("cameras") + ext)).string(), binary ? cameras_bin(cameras) : cameras_txt(cameras));
  write_atomic((dir / (std::string("images") + ext)).string(), binary ? images_bin(cameras) : images_txt(cameras));
  write_atomic((dir / (std::string("points3D") + ext)).string(),
               binary ? points_bin(points, colors) : points_txt(points, colors));

  // Readers (ours and COLMAP's) prefer .bin over .txt: a model of the other
  // format left in the folder would shadow or contradict the one just written.
  for (const char* stem : {"cameras", "images", "points3D"}) {
    const fs::path stale = dir / (std::string(stem) + other);
    if (fs::exists(stale, ec) && !fs::remove(stale, ec)) {
      fail(stale.string(), "cannot remove this stale file of the other format: " + ec.message() +
                               "; remove it by hand, it would shadow the model just written");
    }
  }
}

}  // namespace ag2gs
