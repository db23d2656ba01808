// Tests for the I/O layer: GaussianSet/Camera checks, the 3DGS PLY reader and
// atomic writer, the COLMAP model reader and the camera helpers.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <functional>
#include <random>
#include <sstream>
#include <string>
#include <vector>

#ifndef _WIN32
#include <sys/resource.h>
#include <unistd.h>

#include <csignal>
#endif

#include "host/core/gaussians.h"
#include "host/io/colmap_reader.h"
#include "host/io/json_input.h"
#include "host/io/ply_io.h"
#include "tests/io_test_util.h"

namespace fs = std::filesystem;
using namespace ag2gs;

namespace {

using TempDir = ag2gs::test::ScratchDir;
using ag2gs::test::expect_error_with;
using ag2gs::test::read_bytes;
using ag2gs::test::write_bytes;

std::string sample_path(const std::string& rel) {
  return ag2gs::test::source_path("data_samples/" + rel);
}

GaussianSet random_set(int degree, size_t n, unsigned seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<float> u(-2.f, 2.f), op(0.01f, 0.99f), sc(1e-3f, 2.f);
  GaussianSet gs;
  gs.sh_degree = degree;
  gs.resize(n);
  for (float& v : gs.means) v = u(rng);
  for (float& v : gs.scales) v = sc(rng);
  for (float& v : gs.quats) v = u(rng);  // deliberately not normalised
  for (float& v : gs.opacities) v = op(rng);
  for (float& v : gs.sh) v = u(rng);
  for (float& v : gs.features) v = u(rng);
  return gs;
}

// What the reader makes of what the writer stores (host/io/ply_io.h).
float opacity_through_file(float o) {
  const double c = std::clamp(static_cast<double>(o), 1e-7, 1.0 - 1e-7);
  const float logit = static_cast<float>(std::log(c / (1.0 - c)));
  return static_cast<float>(1.0 / (1.0 + std::exp(-static_cast<double>(logit))));
}
float scale_through_file(float s) {
  const float log_s = static_cast<float>(std::log(std::max(static_cast<double>(s), 1e-30)));
  return static_cast<float>(std::exp(static_cast<double>(log_s)));
}

bool same_bits(const std::vector<float>& a, const std::vector<float>& b) {
  return a.size() == b.size() && (a.empty() || std::memcmp(a.data(), b.data(), a.size() * 4) == 0);
}

// A PLY header for the standard layout, with hooks to drop or rename properties.
std::string ply_header(const std::string& format, const std::string& count, int n_rest, const std::string& drop = "",
                       const std::string& type = "float") {
  std::vector<std::string> names = {"x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"};
  for (int i = 0; i < n_rest; ++i) names.push_back("f_rest_" + std::to_string(i));
  for (const char* s : {"opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"}) {
    names.push_back(s);
  }
  std::string h = "ply\nformat " + format + " 1.0\nelement vertex " + count + "\n";
  for (const std::string& n : names) {
    if (n != drop) h += "property " + type + " " + n + "\n";
  }
  return h + "end_header\n";
}
constexpr int kStdProps = 17;  // properties of ply_header with n_rest = 0

}  // namespace

// ---------------------------------------------------------------- types

TEST(GaussianSet, ResizeGivesConsistentShapes) {
  GaussianSet gs;
  gs.sh_degree = 2;
  gs.resize(5);
  EXPECT_EQ(gs.size(), 5u);
  EXPECT_EQ(gs.means.size(), 15u);
  EXPECT_EQ(gs.quats.size(), 20u);
  EXPECT_EQ(gs.sh.size(), 5u * 9 * 3);
  EXPECT_EQ(gs.features.size(), 15u);
  EXPECT_NO_THROW(gs.validate());
  EXPECT_TRUE(std::all_of(gs.sh.begin(), gs.sh.end(), [](float v) { return v == 0.f; }));
}

TEST(GaussianSet, ValidateNamesTheWrongArray) {
  GaussianSet gs;
  gs.sh_degree = 1;
  gs.resize(4);
  gs.sh.pop_back();
  expect_error_with<std::invalid_argument>([&] { gs.validate(); }, {"'sh'", "47", "48"});
  gs.resize(4);
  gs.sh.resize(48);
  gs.quats.resize(12);
  expect_error_with<std::invalid_argument>([&] { gs.validate(); }, {"'quats'", "12", "16"});
  gs.quats.resize(16);
  gs.sh_degree = 4;
  expect_error_with<std::invalid_argument>([&] { gs.validate(); }, {"sh_degree", "4"});
}

TEST(Camera, ValidateRejectsUnusableCameras) {
  Camera cam;
  cam.name = "a.png";
  cam.width = 10;
  cam.height = 8;
  cam.fx = cam.fy = 12;
  cam.cx = 5;
  cam.cy = 4;
  EXPECT_NO_THROW(cam.validate());
  Camera bad = cam;
  bad.width = 0;
  expect_error_with<std::invalid_argument>([&] { bad.validate(); }, {"a.png", "0x8"});
  bad = cam;
  bad.fy = std::nan("");
  expect_error_with<std::invalid_argument>([&] { bad.validate(); }, {"fy"});
  bad = cam;
  bad.R(0, 0) = 1.01;
  expect_error_with<std::invalid_argument>([&] { bad.validate(); }, {"not a rotation"});
  bad = cam;
  bad.R(2, 2) = -1;  // a reflection: orthonormal, det -1
  expect_error_with<std::invalid_argument>([&] { bad.validate(); }, {"det"});
}

// ---------------------------------------------------------------- PLY

TEST(Ply, RoundTripAllDegreesWithAndWithoutFeatures) {
  TempDir dir;
  for (int degree = 0; degree <= 3; ++degree) {
    for (bool with_features : {true, false}) {
      SCOPED_TRACE("degree " + std::to_string(degree) + (with_features ? " with" : " without") + " features");
      const GaussianSet gs = random_set(degree, 37, 100u + degree);
      const std::string path = dir.file("rt.ply");
      write_ply(path, gs, with_features);
      const GaussianSet back = read_ply(path);
      ASSERT_EQ(back.sh_degree, degree);
      ASSERT_EQ(back.size(), gs.size());
      EXPECT_NO_THROW(back.validate());
      EXPECT_TRUE(same_bits(back.means, gs.means));
      EXPECT_TRUE(same_bits(back.quats, gs.quats));
      EXPECT_TRUE(same_bits(back.sh, gs.sh));
      if (with_features) {
        EXPECT_TRUE(same_bits(back.features, gs.features));
      } else {
        EXPECT_TRUE(std::all_of(back.features.begin(), back.features.end(), [](float v) { return v == 0.f; }));
      }
      for (size_t i = 0; i < gs.opacities.size(); ++i) {
        EXPECT_EQ(back.opacities[i], opacity_through_file(gs.opacities[i])) << i;
        EXPECT_NEAR(back.opacities[i], gs.opacities[i], 1e-6f * gs.opacities[i]) << i;
      }
      for (size_t i = 0; i < gs.scales.size(); ++i) {
        EXPECT_EQ(back.scales[i], scale_through_file(gs.scales[i])) << i;
        EXPECT_NEAR(back.scales[i], gs.scales[i], 1e-6f * gs.scales[i]) << i;
      }
    }
  }
  EXPECT_EQ(dir.entries(), std::vector<std::string>{"rt.ply"});
}

TEST(Ply, WriterUsesStandardLayoutAndInverseActivations) {
  GaussianSet gs;
  gs.sh_degree = 1;
  gs.resize(2);
  for (size_t i = 0; i < gs.sh.size(); ++i) gs.sh[i] = static_cast<float>(i);  // sh[(n*4+k)*3+c]
  gs.opacities = {0.f, 1.f};                                                   // clamped to 1e-7, 1 - 1e-7
  gs.scales = {0.f, 1.f, std::exp(2.f), 1.f, 1.f, 1.f};                        // 0 -> log(1e-30)
  TempDir dir;
  const std::string path = dir.file("layout.ply");
  write_ply(path, gs);
  const std::string bytes = read_bytes(path);
  const size_t data = bytes.find("end_header\n") + 11;
  ASSERT_NE(bytes.find("format binary_little_endian 1.0\nelement vertex 2\nproperty float x\n"), std::string::npos);
  ASSERT_NE(bytes.find("property float rot_3\nproperty float feat_0\nproperty float feat_1\n"
                       "property float feat_2\nend_header\n"),
            std::string::npos);
  const int stride = 3 + 3 + 3 + 9 + 1 + 3 + 4 + 3;
  ASSERT_EQ(bytes.size() - data, 2u * stride * 4);
  auto value = [&](int vertex, int prop) {
    float f;
    std::memcpy(&f, bytes.data() + data + (vertex * stride + prop) * 4, 4);
    return f;
  };
  for (int n = 0; n < 2; ++n) {
    for (int c = 0; c < 3; ++c) EXPECT_EQ(value(n, 6 + c), gs.sh[(n * 4) * 3 + c]);  // f_dc_c
    for (int c = 0; c < 3; ++c) {
      for (int k = 1; k < 4; ++k) {  // f_rest_{c*(K-1)+(k-1)} = sh[n,k,c]
        EXPECT_EQ(value(n, 9 + c * 3 + (k - 1)), gs.sh[(n * 4 + k) * 3 + c]) << n << " " << c << " " << k;
      }
    }
  }
  EXPECT_NEAR(value(0, 18), std::log(1e-7), 1e-4);   // opacity logit
  EXPECT_NEAR(value(1, 18), -std::log(1e-7), 1e-2);  // float spacing near 1 limits this one
  EXPECT_NEAR(value(0, 19), std::log(1e-30), 1e-4);  // scale_0
  EXPECT_EQ(value(0, 20), 0.f);
  EXPECT_NEAR(value(0, 21), 2.f, 1e-6);
}

TEST(Ply, ReadsTheSampleScene) {
  const GaussianSet gs = read_ply(sample_path("tiny_scene/gaussians.ply"));
  ASSERT_EQ(gs.size(), 300u);
  EXPECT_EQ(gs.sh_degree, 1);
  EXPECT_NO_THROW(gs.validate());
  for (size_t i = 0; i < gs.size(); ++i) {
    EXPECT_GT(gs.opacities[i], 0.5f);
    EXPECT_LT(gs.opacities[i], 0.96f);
    const Eigen::Map<const Eigen::Vector3f> mean(&gs.means[i * 3]);
    EXPECT_LT(mean.norm(), 1.5f);
    const Eigen::Map<const Eigen::Vector3f> feat(&gs.features[i * 3]);
    EXPECT_NEAR(feat.norm(), 1.f, 1e-6f);  // one unit vector per blob
    const Eigen::Map<const Eigen::Vector4f> q(&gs.quats[i * 4]);
    EXPECT_NEAR(q.norm(), 1.f, 1e-5f);
    for (int a = 0; a < 3; ++a) {
      EXPECT_GT(gs.scales[i * 3 + a], 0.005f);
      EXPECT_LT(gs.scales[i * 3 + a], 0.5f);
    }
  }
  // The first blob is red: f_dc maps back to colour 0.5 + C0 * f_dc.
  const float c0 = 0.28209479177387814f;
  EXPECT_GT(0.5f + c0 * gs.sh[0], 0.7f);
  EXPECT_LT(0.5f + c0 * gs.sh[1], 0.35f);
}

TEST(Ply, AcceptsAsciiDoublesExtraPropertiesAndNoFeatures) {
  TempDir dir;
  // ascii, double typed, no normals, an extra property, degree 0, no feat.
  std::string h = "ply\nformat ascii 1.0\ncomment made by hand\nelement vertex 2\n";
  for (const char* n : {"x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
                        "rot_0", "rot_1", "rot_2", "rot_3"}) {
    h += std::string("property double ") + n + "\n";
  }
  h += "property uchar red\nend_header\n";
  h += "1 2 3 0.1 0.2 0.3 0 0 -1 1 1 0 0 0 255\n";
  h += "-1 -2 -3 0.4 0.5 0.6 2.5 0.5 0.5 0.5 2 0 0 0 7\n";
  write_bytes(dir.file("a.ply"), h);
  const GaussianSet gs = read_ply(dir.file("a.ply"));
  ASSERT_EQ(gs.size(), 2u);
  EXPECT_EQ(gs.sh_degree, 0);
  EXPECT_EQ(gs.means, (std::vector<float>{1, 2, 3, -1, -2, -3}));
  EXPECT_EQ(gs.sh, (std::vector<float>{0.1f, 0.2f, 0.3f, 0.4f, 0.5f, 0.6f}));
  EXPECT_FLOAT_EQ(gs.opacities[0], 0.5f);
  EXPECT_FLOAT_EQ(gs.opacities[1], 1.f / (1.f + std::exp(-2.5f)));
  EXPECT_FLOAT_EQ(gs.scales[0], 1.f);
  EXPECT_FLOAT_EQ(gs.scales[1], std::exp(-1.f));
  EXPECT_FLOAT_EQ(gs.scales[3], std::exp(0.5f));
  EXPECT_EQ(gs.quats, (std::vector<float>{1, 0, 0, 0, 2, 0, 0, 0}));  // not normalised
  EXPECT_EQ(gs.features, std::vector<float>(6, 0.f));

  // Binary with double properties reads the same numbers.
  std::string b = ply_header("binary_little_endian", "1", 0, "", "double");
  const double row[kStdProps] = {1, 2, 3, 0, 0, 0, 0.1, 0.2, 0.3, 0, -1, 1, 1, 0.5, 0.5, 0.5, 0.5};
  b.append(reinterpret_cast<const char*>(row), sizeof(row));
  write_bytes(dir.file("d.ply"), b);
  const GaussianSet d = read_ply(dir.file("d.ply"));
  ASSERT_EQ(d.size(), 1u);
  EXPECT_EQ(d.means, (std::vector<float>{1, 2, 3}));
  EXPECT_FLOAT_EQ(d.opacities[0], 0.5f);
  EXPECT_FLOAT_EQ(d.scales[0], std::exp(-1.f));
  EXPECT_FLOAT_EQ(d.scales[1], std::exp(1.f));
  EXPECT_EQ(d.quats, (std::vector<float>{0.5f, 0.5f, 0.5f, 0.5f}));
}

TEST(Ply, MalformedFilesGiveErrorsNamingTheFile) {
  TempDir dir;
  auto expect_bad = [&](const std::string& name, const std::string& bytes, const std::vector<std::string>& needles) {
    SCOPED_TRACE(name);
    const std::string path = dir.file(name);
    write_bytes(path, bytes);
    std::vector<std::string> all = needles;
    all.push_back(path);
    expect_error_with<std::runtime_error>([&] { read_ply(path); }, all);
  };
  const std::string one_vertex(kStdProps * 4, '\0');

  expect_bad("empty.ply", "", {"empty file"});
  expect_bad("magic.ply", "plx\nformat binary_little_endian 1.0\n", {"not a PLY file", "'ply' magic"});
  expect_bad("obj.ply", "# an OBJ file\nv 0 0 0\n", {"not a PLY file"});
  expect_bad("truncated.ply",
             ply_header("binary_little_endian", "1000", 0) + std::string(312 * kStdProps * 4 + 5, '\0'),
             {"truncated", "header says 1000 vertices but data holds 312"});
  expect_bad("missing.ply", ply_header("binary_little_endian", "1", 0, "scale_1") + one_vertex,
             {"missing property 'scale_1'", "3D Gaussian Splatting"});
  expect_bad("absurd.ply", ply_header("binary_little_endian", "4000000000000000000", 0) + one_vertex,
             {"header says 4000000000000000000 vertices but data holds 1"});
  expect_bad("absurd_ascii.ply", ply_header("ascii", "900000000000", 0) + "1 2 3\n", {"truncated"});
  expect_bad("big.ply", ply_header("binary_big_endian", "1", 0) + one_vertex,
             {"binary_big_endian", "binary_little_endian"});
  expect_bad("rest.ply", ply_header("binary_little_endian", "1", 5) + std::string((kStdProps + 5) * 4, '\0'),
             {"5 f_rest_* properties", "0, 9, 24 or 45"});
  expect_bad("noend.ply", "ply\nformat binary_little_endian 1.0\nelement vertex 1\n", {"end_header"});
  expect_bad("noformat.ply", "ply\nelement vertex 0\nproperty float x\nend_header\n", {"format"});
  expect_bad("count.ply", "ply\nformat ascii 1.0\nelement vertex -3\nend_header\n", {"element"});
  expect_bad("novertex.ply", "ply\nformat ascii 1.0\nelement face 0\nend_header\n", {"element vertex"});
  expect_bad("ascii_short.ply",
             ply_header("ascii", "2", 0) + "1 2 3 4 5 6 7 8 9 10 11 12 13 14 15 16 17\n1 2 3 4 5 6 7 8 9\n",
             {"header says 2 vertices but data holds 1"});
  expect_bad("ascii_nan.ply", ply_header("ascii", "1", 0) + "1 2 x3 4 5 6 7 8 9 10 11 12 13 14 15 16 17\n",
             {"bad number 'x3'"});
  expect_error_with<std::runtime_error>([&] { read_ply(dir.file("does_not_exist.ply")); },
                                        {"does_not_exist.ply", "cannot open"});
}

TEST(Ply, ZeroGaussiansRoundTrip) {
  TempDir dir;
  GaussianSet gs;
  gs.sh_degree = 3;
  write_ply(dir.file("empty.ply"), gs);
  const GaussianSet back = read_ply(dir.file("empty.ply"));
  EXPECT_EQ(back.size(), 0u);
  EXPECT_EQ(back.sh_degree, 3);
}

// One validation policy at load: non-finite numbers, zero rotations and
// (activated values) scales <= 0 or opacities outside [0, 1] are refused
// naming the file, the count and the first one, or dropped on request.
TEST(Ply, InvalidNumbersAreRefusedNamingTheFirstOrDropped) {
  TempDir dir;
  struct Case {
    const char* name;
    std::function<void(GaussianSet&, size_t)> spoil;
    const char* needle;
  };
  const std::vector<Case> cases = {
      {"nan_position", [](GaussianSet& g, size_t i) { g.means[3 * i + 1] = NAN; }, "position_1 = nan"},
      {"inf_scale", [](GaussianSet& g, size_t i) { g.scales[3 * i + 2] = INFINITY; }, "scale_2 = inf"},
      {"zero_rotation", [](GaussianSet& g, size_t i) { std::fill_n(&g.quats[4 * i], 4, 0.f); },
       "rotation (0, 0, 0, 0)"},
      {"nan_opacity", [](GaussianSet& g, size_t i) { g.opacities[i] = NAN; }, "opacity = nan"},
      {"nan_sh", [](GaussianSet& g, size_t i) { g.sh[i * 16 * 3 + 7] = NAN; }, "sh_7 = nan"},
  };
  for (const Case& c : cases) {
    GaussianSet gs = random_set(3, 10, 4);
    for (size_t i : {3u, 7u}) c.spoil(gs, i);
    const std::string path = dir.file(std::string(c.name) + ".ply");
    write_ply(path, gs, true, PlyValues::stored);
    expect_error_with<std::runtime_error>([&] { read_ply(path, PlyValues::stored); },
                                          {path, "2 of 10 Gaussians", "vertex 3", c.needle, "--drop-invalid"});
    size_t dropped = 0;
    const GaussianSet kept = read_ply(path, PlyValues::stored, InvalidGaussians::drop, &dropped);
    EXPECT_EQ(dropped, 2u) << c.name;
    ASSERT_EQ(kept.size(), 8u) << c.name;
    EXPECT_EQ(kept.means[3 * 3], gs.means[3 * 4]) << c.name << ": the Gaussian after the first dropped one moved up";
    EXPECT_EQ(find_invalid_gaussians(kept, PlyValues::stored).count, 0u) << c.name;
  }
  // Activated values: a scale of 0 or an opacity above 1 are invalid too;
  // the file's own logits are not checked for range.
  GaussianSet gs = random_set(0, 4, 5);
  gs.opacities[2] = 1.5f;
  EXPECT_EQ(find_invalid_gaussians(gs).count, 1u);
  EXPECT_NE(find_invalid_gaussians(gs).what.find("opacity = 1.5"), std::string::npos);
  EXPECT_EQ(find_invalid_gaussians(gs, PlyValues::stored).count, 0u);
  gs.opacities[2] = 0.5f;
  gs.scales[1] = 0.f;
  EXPECT_EQ(find_invalid_gaussians(gs).first, 0u);
}

TEST(Ply, AtomicWriteLeavesNoTemporaryFile) {
  TempDir dir;
  const std::string path = dir.file("model.ply");
  write_ply(path, random_set(1, 10, 1));
  write_ply(path, random_set(2, 20, 2));  // replaces the old file
  EXPECT_EQ(dir.entries(), std::vector<std::string>{"model.ply"});
  EXPECT_EQ(read_ply(path).size(), 20u);
}

TEST(Ply, FailedWriteKeepsTheOldFile) {
  TempDir dir;
  const std::string path = dir.file("model.ply");
  write_ply(path, random_set(0, 3, 3));
  const std::string old_bytes = read_bytes(path);

  // Inconsistent arrays: rejected before anything is written.
  GaussianSet bad = random_set(1, 5, 4);
  bad.means.pop_back();
  expect_error_with<std::invalid_argument>([&] { write_ply(path, bad); }, {"'means'"});
  EXPECT_EQ(read_bytes(path), old_bytes);

  // The target is a non-empty directory: the final rename fails.
  fs::create_directories(dir.path() / "a_dir" / "inside");
  expect_error_with<std::runtime_error>([&] { write_ply(dir.file("a_dir"), random_set(0, 3, 5)); },
                                        {"a_dir", "unchanged"});
  EXPECT_TRUE(fs::is_directory(dir.path() / "a_dir" / "inside"));

  // A folder that does not exist.
  const std::string nowhere = dir.file("no_such_dir/model.ply");
  expect_error_with<std::runtime_error>([&] { write_ply(nowhere, random_set(0, 3, 6)); },
                                        {nowhere, "directory exists and is writable"});
  EXPECT_EQ(dir.entries(), (std::vector<std::string>{"a_dir", "model.ply"}));

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
    write_ply(path, random_set(3, 2000, 7));  // about 1.9 MB
  } catch (const std::runtime_error& e) {
    threw = true;
    message = e.what();
  }
  setrlimit(RLIMIT_FSIZE, &old_limit);
  std::signal(SIGXFSZ, old_handler);
  EXPECT_TRUE(threw);
  EXPECT_NE(message.find(path), std::string::npos) << message;
  EXPECT_EQ(read_bytes(path), old_bytes);
  EXPECT_EQ(dir.entries(), (std::vector<std::string>{"a_dir", "model.ply"}));

  // An unwritable folder (root ignores permissions, so only as a user).
  if (::geteuid() != 0) {
    fs::create_directories(dir.path() / "ro");
    write_ply(dir.file("ro/model.ply"), random_set(0, 3, 8));
    const std::string ro_bytes = read_bytes(dir.file("ro/model.ply"));
    fs::permissions(dir.path() / "ro", fs::perms::owner_read | fs::perms::owner_exec);
    expect_error_with<std::runtime_error>([&] { write_ply(dir.file("ro/model.ply"), random_set(1, 3, 9)); },
                                          {"ro/model.ply", "writable"});
    fs::permissions(dir.path() / "ro", fs::perms::owner_all);
    EXPECT_EQ(read_bytes(dir.file("ro/model.ply")), ro_bytes);
  }
#endif
}

// ---------------------------------------------------------------- COLMAP

namespace {

void expect_same_camera(const Camera& a, const Camera& b) {
  EXPECT_EQ(a.name, b.name);
  EXPECT_EQ(a.width, b.width);
  EXPECT_EQ(a.height, b.height);
  EXPECT_EQ(a.fx, b.fx);
  EXPECT_EQ(a.fy, b.fy);
  EXPECT_EQ(a.cx, b.cx);
  EXPECT_EQ(a.cy, b.cy);
  EXPECT_TRUE(a.R == b.R) << a.R << "\n vs\n" << b.R;
  EXPECT_TRUE(a.t == b.t) << a.t.transpose() << " vs " << b.t.transpose();
}

// A text model in `dir` with one image on camera 1.
void write_text_model(const TempDir& dir, const std::string& camera_line) {
  write_bytes(dir.file("cameras.txt"), "# cameras\n" + camera_line + "\n");
  write_bytes(dir.file("images.txt"), "# images\n1 1 0 0 0 0 0 2 1 frame_001.jpg\n\n");
  write_bytes(dir.file("points3D.txt"), "# no points\n");
}

}  // namespace

TEST(Colmap, TextAndBinarySamplesGiveIdenticalModels) {
  const ColmapModel txt = read_colmap_model(sample_path("tiny_scene/sparse/0"));
  const ColmapModel bin = read_colmap_model(sample_path("tiny_scene_bin/sparse/0"));
  ASSERT_EQ(txt.cameras_for_images.size(), 4u);
  ASSERT_EQ(bin.cameras_for_images.size(), 4u);
  for (size_t i = 0; i < 4; ++i) {
    SCOPED_TRACE(i);
    expect_same_camera(txt.cameras_for_images[i], bin.cameras_for_images[i]);
  }
  ASSERT_EQ(txt.points.size(), 60u);
  ASSERT_EQ(bin.points.size(), 60u);
  EXPECT_EQ(txt.points, bin.points);
  EXPECT_EQ(txt.colors, bin.colors);

  // Sorted by name although the image ids are not; cameras looked up by id.
  const std::vector<std::string> names = {"view_000.png", "view_001.png", "view_002.png", "view_003.png"};
  for (size_t i = 0; i < 4; ++i) {
    const Camera& cam = txt.cameras_for_images[i];
    EXPECT_EQ(cam.name, names[i]);
    EXPECT_EQ(cam.width, 160);
    EXPECT_EQ(cam.height, 120);
    EXPECT_EQ(cam.fx, i < 2 ? 160.0 : 170.0);
    EXPECT_EQ(cam.cx, i < 2 ? 80.0 : 79.5);
    EXPECT_NO_THROW(cam.validate());
    // At distance 4 and looking at the origin, which projects to the principal point.
    EXPECT_NEAR(cam.center().norm(), 4.0, 1e-9);
    const Eigen::Vector3d origin_cam = cam.t;  // R * 0 + t
    EXPECT_NEAR(origin_cam.z(), 4.0, 1e-9);
    EXPECT_NEAR(cam.fx * origin_cam.x() / origin_cam.z() + cam.cx, cam.cx, 1e-9);
    EXPECT_NEAR(cam.fy * origin_cam.y() / origin_cam.z() + cam.cy, cam.cy, 1e-9);
  }
  // The sparse points are every 5th Gaussian centre of the sample PLY.
  const GaussianSet gs = read_ply(sample_path("tiny_scene/gaussians.ply"));
  for (size_t i = 0; i < txt.points.size(); ++i) {
    for (int a = 0; a < 3; ++a) EXPECT_EQ(txt.points[i][a], static_cast<double>(gs.means[i * 15 + a]));
  }
  EXPECT_EQ(txt.colors[0], (Eigen::Vector3<uint8_t>(230, 38, 26)));
}

TEST(Colmap, BinaryPreferredOverText) {
  TempDir dir;
  for (const char* f : {"cameras.bin", "images.bin", "points3D.bin"}) {
    fs::copy_file(sample_path(std::string("tiny_scene_bin/sparse/0/") + f), dir.file(f));
  }
  write_text_model(dir, "1 PINHOLE 10 10 999 999 5 5");
  const ColmapModel model = read_colmap_model(dir.path().string());
  ASSERT_EQ(model.cameras_for_images.size(), 4u);
  EXPECT_EQ(model.cameras_for_images[0].fx, 160.0);
}

TEST(Colmap, SimplePinholeAndRotation) {
  TempDir dir;
  write_text_model(dir, "1 SIMPLE_PINHOLE 640 480 500.5 320 240.25");
  // A 90 degree turn about y: q = (cos 45, 0, sin 45, 0), not normalised in the file.
  write_bytes(dir.file("images.txt"), "1 2 0 2 0 0.5 -1 3 1 frame_001.jpg\n\n");
  const ColmapModel model = read_colmap_model(dir.path().string());
  ASSERT_EQ(model.cameras_for_images.size(), 1u);
  const Camera& cam = model.cameras_for_images[0];
  EXPECT_EQ(cam.name, "frame_001.jpg");
  EXPECT_EQ(cam.width, 640);
  EXPECT_EQ(cam.height, 480);
  EXPECT_EQ(cam.fx, 500.5);
  EXPECT_EQ(cam.fy, 500.5);
  EXPECT_EQ(cam.cx, 320.0);
  EXPECT_EQ(cam.cy, 240.25);
  Eigen::Matrix3d expected;
  expected << 0, 0, 1, 0, 1, 0, -1, 0, 0;
  EXPECT_TRUE(cam.R.isApprox(expected, 1e-12)) << cam.R;
  EXPECT_EQ(cam.t, Eigen::Vector3d(0.5, -1, 3));
  EXPECT_TRUE(model.points.empty());
}

TEST(Colmap, DistortedModelsSayHowToUndistort) {
  TempDir dir;
  write_text_model(dir, "1 SIMPLE_RADIAL 640 480 500 320 240 0.01");
  expect_error_with<std::runtime_error>([&] { read_colmap_model(dir.path().string()); },
                                        {dir.file("cameras.txt"), "camera 1", "SIMPLE_RADIAL",
                                         "colmap image_undistorter --image_path IMAGES --input_path SPARSE "
                                         "--output_path OUT --output_type COLMAP"});

  // Binary: camera 1 OPENCV (model id 4, 8 parameters), camera 2 PINHOLE.
  TempDir bin;
  for (const char* f : {"images.bin", "points3D.bin"}) {
    fs::copy_file(sample_path(std::string("tiny_scene_bin/sparse/0/") + f), bin.file(f));
  }
  std::string cams;
  auto put = [&](const void* p, size_t n) { cams.append(static_cast<const char*>(p), n); };
  const uint64_t count = 2;
  put(&count, 8);
  const int32_t head1[2] = {1, 4}, head2[2] = {2, 1};
  const uint64_t size[2] = {160, 120};
  const double opencv[8] = {160, 160, 80, 60, 0.1, 0, 0, 0}, pinhole[4] = {170, 170, 80, 60};
  put(head1, 8), put(size, 16), put(opencv, 64);
  put(head2, 8), put(size, 16), put(pinhole, 32);
  write_bytes(bin.file("cameras.bin"), cams);
  expect_error_with<std::runtime_error>([&] { read_colmap_model(bin.path().string()); },
                                        {bin.file("cameras.bin"), "camera 1", "OPENCV", "image_undistorter"});
}

TEST(Colmap, TruncatedAndInconsistentModelsAreRejected) {
  const std::string src = sample_path("tiny_scene_bin/sparse/0/");
  for (const char* name : {"cameras.bin", "images.bin", "points3D.bin"}) {
    SCOPED_TRACE(name);
    TempDir dir;
    for (const char* f : {"cameras.bin", "images.bin", "points3D.bin"}) {
      fs::copy_file(src + f, dir.file(f));
    }
    std::string bytes = read_bytes(dir.file(name));
    write_bytes(dir.file(name), bytes.substr(0, bytes.size() * 2 / 3));
    expect_error_with<std::runtime_error>([&] { read_colmap_model(dir.path().string()); },
                                          {dir.file(name), "truncated"});
    // An absurd count is caught before anything is allocated.
    const uint64_t huge = uint64_t(1) << 50;
    std::memcpy(&bytes[0], &huge, 8);
    write_bytes(dir.file(name), bytes);
    expect_error_with<std::runtime_error>([&] { read_colmap_model(dir.path().string()); },
                                          {dir.file(name), "truncated"});
  }

  TempDir dir;
  expect_error_with<std::runtime_error>([&] { read_colmap_model(dir.path().string()); },
                                        {"no cameras.bin or cameras.txt"});
  expect_error_with<std::runtime_error>([&] { read_colmap_model(dir.file("nope")); }, {"nope", "not a directory"});
  write_text_model(dir, "7 PINHOLE 640 480 500 500 320 240");
  expect_error_with<std::runtime_error>([&] { read_colmap_model(dir.path().string()); },
                                        {dir.file("images.txt"), "frame_001.jpg", "camera 1"});
  write_text_model(dir, "1 PINHOLE 640 480 500 500 320");
  expect_error_with<std::runtime_error>([&] { read_colmap_model(dir.path().string()); },
                                        {dir.file("cameras.txt"), "expected 4"});
  write_text_model(dir, "1 PINHOLE 640 480 500 abc 320 240");
  expect_error_with<std::runtime_error>([&] { read_colmap_model(dir.path().string()); },
                                        {dir.file("cameras.txt") + ":2", "'abc'"});
}

// ---------------------------------------------------------------- camera helpers

TEST(CameraHelpers, ScaleCameraRoundsLike3dgs) {
  Camera cam;
  cam.name = "a.png";
  cam.width = 160;
  cam.height = 120;
  cam.fx = 160;
  cam.fy = 150;
  cam.cx = 80;
  cam.cy = 60;
  const Camera same = scale_camera(cam, 1);
  EXPECT_EQ(same.width, 160);
  EXPECT_EQ(same.fx, 160.0);

  const Camera half = scale_camera(cam, 2);
  EXPECT_EQ(half.width, 80);
  EXPECT_EQ(half.height, 60);
  EXPECT_EQ(half.fx, 80.0);
  EXPECT_EQ(half.fy, 75.0);
  EXPECT_EQ(half.cx, 40.0);
  EXPECT_EQ(half.cy, 30.0);
  EXPECT_TRUE(half.R == cam.R);
  EXPECT_EQ(half.name, "a.png");

  const Camera third = scale_camera(cam, 3);  // 53.33 -> 53, 40
  EXPECT_EQ(third.width, 53);
  EXPECT_EQ(third.height, 40);
  EXPECT_DOUBLE_EQ(third.fx, 160.0 * 53 / 160);

  cam.width = 1297;  // 648.5 -> 648 (ties to even, Python's round)
  cam.height = 731;  // 365.5 -> 366
  const Camera odd = scale_camera(cam, 2);
  EXPECT_EQ(odd.width, 648);
  EXPECT_EQ(odd.height, 366);
  EXPECT_DOUBLE_EQ(odd.fx, 160.0 * 648 / 1297);
  EXPECT_DOUBLE_EQ(odd.cy, 60.0 * 366 / 731);

  expect_error_with<std::invalid_argument>([&] { scale_camera(cam, 0); }, {"factor"});
  expect_error_with<std::invalid_argument>([&] { scale_camera(cam, 5000); }, {"a.png", "vanishes"});
}

TEST(CameraHelpers, SelectViewsByNameAndStem) {
  const std::vector<Camera> cams = read_colmap_model(sample_path("tiny_scene/sparse/0")).cameras_for_images;
  auto names = [](const std::vector<Camera>& v) {
    std::vector<std::string> out;
    for (const Camera& c : v) out.push_back(c.name);
    return out;
  };
  EXPECT_EQ(names(select_views(cams, "view_001.png")), std::vector<std::string>{"view_001.png"});
  EXPECT_EQ(names(select_views(cams, "view_003, view_000.png")),
            (std::vector<std::string>{"view_003.png", "view_000.png"}));
  EXPECT_EQ(select_views(cams, "").size(), 4u);
  EXPECT_EQ(select_views(cams, "view_002")[0].fx, 170.0);
  expect_error_with<std::invalid_argument>([&] { select_views(cams, "view_000,view_9"); },
                                           {"unknown view 'view_9'", "view_000.png", "4 views"});

  std::vector<Camera> nested(3);
  nested[0].name = "left/frame_1.jpg";
  nested[1].name = "right/frame_1.jpg";
  nested[2].name = "left/frame_2.jpg";
  EXPECT_EQ(names(select_views(nested, "frame_2")), std::vector<std::string>{"left/frame_2.jpg"});
  EXPECT_EQ(names(select_views(nested, "right/frame_1")), std::vector<std::string>{"right/frame_1.jpg"});
  expect_error_with<std::invalid_argument>([&] { select_views(nested, "frame_1"); },
                                           {"ambiguous", "left/frame_1.jpg", "right/frame_1.jpg"});
}

TEST(Colmap, TextIntegersMustBePlainDigits) {
  for (const char* bad_id : {"1e3", "12.0", "-1", "0x10"}) {
    TempDir dir;
    write_bytes(dir.file("cameras.txt"), std::string(bad_id) + " PINHOLE 4 3 2 2 2 1.5\n");
    write_bytes(dir.file("images.txt"), "");
    write_bytes(dir.file("points3D.txt"), "");
    expect_error_with<std::runtime_error>(
        [&] { read_colmap_model(dir.path().string()); },
        {dir.file("cameras.txt") + ":1", std::string("'") + bad_id + "'", "non-negative integer"});
  }
}

// JSON from outside the program: nesting is measured outside strings and
// refused past 64 levels before the parser runs (a model header nested
// 200,000 deep crashed `info` and `query`), numbers past double's range and
// folders in place of files give one message naming the source.
TEST(JsonInput, DepthLimitAndClearErrors) {
  EXPECT_EQ(json_nesting_depth(R"({"a": [1, {"b": "[[[[{{{{"}]})"), 3);
  EXPECT_EQ(json_nesting_depth(R"("\"[[[")"), 0);
  EXPECT_EQ(parse_json_input(std::string(64, '[') + std::string(64, ']'), "x").dump().size(), 128u);
  const std::string deep = std::string(200000, '[') + std::string(200000, ']');
  EXPECT_EQ(json_nesting_depth(deep), kJsonMaxDepth + 1);  // stops counting early
  for (const auto& [text, message] :
       std::vector<std::pair<std::string, std::string>>{{deep, "model.ag2gs: JSON nested deeper than 64 levels"},
                                                        {std::string(65, '{'), "nested deeper"},
                                                        {R"({"a": 1e999})", "model.ag2gs: not valid JSON"},
                                                        {"{", "model.ag2gs: not valid JSON"}}) {
    try {
      parse_json_input(text, "model.ag2gs");
      ADD_FAILURE() << text.substr(0, 40) << " was accepted";
    } catch (const std::runtime_error& e) {
      EXPECT_NE(std::string(e.what()).find(message), std::string::npos) << e.what();
    }
  }
  try {
    read_json_file(testing::TempDir());
    ADD_FAILURE() << "a folder was read as JSON";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("is a folder"), std::string::npos) << e.what();
  }
}
