// The native model archive (versioned, checksummed, atomic) and the JSON
// readers of queries and evaluation (vocabulary, label frames, click lists).
#include <gtest/gtest.h>
#include <sys/stat.h>

#include <cmath>
#include <cstring>
#include <filesystem>
#include <limits>
#include <random>

#include "host/io/model_io.h"
#include "host/io/ply_io.h"
#include "host/io/semantic_io.h"
#include "tests/io_test_util.h"

namespace fs = std::filesystem;
using namespace ag2gs;
using ag2gs::test::expect_error_with;
using ag2gs::test::read_bytes;
using ag2gs::test::ScratchDir;
using ag2gs::test::write_bytes;

namespace {

ModelArchive sample_archive() {
  ModelArchive a;
  a.meta = {{"iteration", 1234}, {"seed", 7}, {"config", {{"lr", 0.001}, {"name", "x"}}}};
  a.put<float>("anchors", {1.f, 2.f, 3.f, -0.f, std::numeric_limits<float>::infinity(), 6.f}, {2, 3});
  a.put<double>("d", {1.0 / 3.0});
  a.put<int32_t>("layer", {0, 1, 2, -1});
  a.put<uint32_t>("u", {7u});
  a.put<int64_t>("edges", {1ll << 40, -5});
  a.put<uint64_t>("rng", {~0ull});
  a.put<uint8_t>("flags", {1, 0, 1});
  a.put<float>("empty", {}, {0, 3});
  return a;
}

}  // namespace

TEST(ModelArchive, RoundTripIsBitExactForEveryType) {
  ScratchDir dir("model");
  const ModelArchive a = sample_archive();
  write_model_archive(dir.file("model.ag2gs"), a);
  const ModelArchive b = read_model_archive(dir.file("model.ag2gs"));
  EXPECT_EQ(b.meta, a.meta);
  ASSERT_EQ(b.arrays().size(), a.arrays().size());
  for (const auto& [name, t] : a.arrays()) {
    const Tensor& u = b.tensor(name);
    EXPECT_EQ(u.dtype, t.dtype) << name;
    EXPECT_EQ(u.shape, t.shape) << name;
    EXPECT_EQ(u.bytes, t.bytes) << name;
  }
  EXPECT_EQ(b.get<float>("anchors", {-1, 3}).size(), 6u);
  EXPECT_EQ(b.get<int64_t>("edges")[0], 1ll << 40);
  // Writing what was read gives the same bytes (deterministic files).
  write_model_archive(dir.file("again.ag2gs"), b);
  EXPECT_EQ(read_bytes(dir.file("model.ag2gs")), read_bytes(dir.file("again.ag2gs")));
}

TEST(ModelArchive, WrongTypeShapeOrNameIsAClearError) {
  ScratchDir dir("model");
  write_model_archive(dir.file("m.ag2gs"), sample_archive());
  const ModelArchive b = read_model_archive(dir.file("m.ag2gs"));
  expect_error_with<std::runtime_error>([&] { b.get<int32_t>("anchors"); }, {"m.ag2gs", "'anchors' is f32"});
  expect_error_with<std::runtime_error>([&] { b.get<float>("anchors", {3, 2}); }, {"shape [2,3]", "expected [3,2]"});
  expect_error_with<std::runtime_error>([&] { b.get<float>("nope"); }, {"no array 'nope'"});
  ModelArchive c;
  EXPECT_THROW(c.put<float>("x", {1.f, 2.f}, {3}), std::invalid_argument);
}

TEST(ModelArchive, OtherVersionsAndForeignFilesAreRejected) {
  ScratchDir dir("model");
  write_model_archive(dir.file("m.ag2gs"), sample_archive());
  std::string bytes = read_bytes(dir.file("m.ag2gs"));
  std::string v2 = bytes;
  v2[8] = 2;
  write_bytes(dir.file("v2.ag2gs"), v2);
  expect_error_with<std::runtime_error>([&] { read_model_archive(dir.file("v2.ag2gs")); },
                                        {"v2.ag2gs", "format version 2", "reads version 1"});
  write_bytes(dir.file("ply.ag2gs"), "ply\nformat binary_little_endian 1.0\n");
  expect_error_with<std::runtime_error>([&] { read_model_archive(dir.file("ply.ag2gs")); }, {"not an ag2gs model"});
  expect_error_with<std::runtime_error>([&] { read_model_archive(dir.file("missing.ag2gs")); }, {"cannot open"});
}

TEST(ModelArchive, EveryTruncationAndEveryFlippedByteIsDetected) {
  ScratchDir dir("model");
  write_model_archive(dir.file("m.ag2gs"), sample_archive());
  const std::string bytes = read_bytes(dir.file("m.ag2gs"));
  int detected = 0, cases = 0;
  for (size_t n = 0; n < bytes.size(); ++n) {
    write_bytes(dir.file("t.ag2gs"), bytes.substr(0, n));
    ++cases;
    try {
      read_model_archive(dir.file("t.ag2gs"));
    } catch (const std::runtime_error& e) {
      ++detected;
      EXPECT_NE(std::string(e.what()).find("t.ag2gs"), std::string::npos);
    }
  }
  // Flip one bit at every position except the padding (which no reader looks at).
  for (size_t i = 0; i < bytes.size(); ++i) {
    std::string c = bytes;
    c[i] = static_cast<char>(c[i] ^ 0x10);
    write_bytes(dir.file("f.ag2gs"), c);
    try {
      const ModelArchive m = read_model_archive(dir.file("f.ag2gs"));
      // Undetected flips must be in padding: the content is then unchanged.
      const ModelArchive ref = sample_archive();
      for (const auto& [name, t] : ref.arrays()) EXPECT_EQ(m.tensor(name).bytes, t.bytes) << "byte " << i;
      EXPECT_EQ(m.meta, ref.meta) << "byte " << i;
    } catch (const std::runtime_error&) {
      ++detected;
    }
    ++cases;
  }
  EXPECT_GE(detected, static_cast<int>(bytes.size()));  // at least every truncation
}

TEST(ModelArchive, FailedWriteLeavesTheOldFileUntouched) {
  ScratchDir dir("model");
  write_model_archive(dir.file("m.ag2gs"), sample_archive());
  const std::string before = read_bytes(dir.file("m.ag2gs"));
  if (::geteuid() != 0) {
    fs::permissions(dir.path(), fs::perms::owner_read | fs::perms::owner_exec);
    ModelArchive other;
    other.put<float>("x", {1.f});
    EXPECT_THROW(write_model_archive(dir.file("m.ag2gs"), other), std::runtime_error);
    fs::permissions(dir.path(), fs::perms::owner_all);
  }
  EXPECT_EQ(read_bytes(dir.file("m.ag2gs")), before);
  expect_error_with<std::runtime_error>([&] { write_model_archive(dir.file("no/such/dir/m.ag2gs"), sample_archive()); },
                                        {"does not exist"});
  for (const auto& e : fs::directory_iterator(dir.path())) {
    EXPECT_EQ(e.path().filename().string().find(".tmp."), std::string::npos) << "left a temp file";
  }
}

TEST(SemanticIo, VocabularyReadsAndValidates) {
  ScratchDir dir("json");
  write_bytes(dir.file("v.json"), R"({"red mug": [1, 0, 0.5], "ball": [0, 1, 0]})");
  const Vocabulary v = read_vocabulary(dir.file("v.json"));
  EXPECT_EQ(v.dim, 3);
  ASSERT_EQ(v.phrases.size(), 2u);
  EXPECT_FLOAT_EQ(v.phrases.at("red mug")[2], 0.5f);
  const std::vector<std::pair<std::string, std::string>> bad = {
      {R"({"a": [1, 2], "b": [1, 2, 3]})", "3 dimensions but earlier phrases have 2"},
      {R"({"a": [1, "x"]})", "element 1 is not a number"},
      {R"({"a": [0, 0]})", "all zeros"},
      {R"({"a": 5})", "list of numbers"},
      {R"([1, 2])", "JSON object"},
      {R"({"a": [1, 2)", "not valid JSON"},
      {"", "not valid JSON"},
  };
  for (const auto& [text, needle] : bad) {
    write_bytes(dir.file("bad.json"), text);
    expect_error_with<std::runtime_error>([&] { read_vocabulary(dir.file("bad.json")); }, {"bad.json", needle});
  }
  expect_error_with<std::runtime_error>([&] { read_vocabulary(dir.file("none.json")); }, {"none.json", "cannot open"});
}

TEST(SemanticIo, LabelFramePolygonsBecomeMasks) {
  ScratchDir dir("json");
  write_bytes(dir.file("f.json"), R"({"info": {"width": 10, "height": 8, "name": "frame_1.jpg"},
    "objects": [{"category": "cup", "segmentation": [[2, 2], [5, 2], [5, 5], [2, 5]], "bbox": [2, 2, 5, 5]},
                {"category": "cup", "segmentation": [[8, 6], [9, 6], [9, 7]]},
                {"category": "plate", "segmentation": [[0, 0], [1, 0], [1, 1], [0, 1]]}]})");
  const LabelFrame f = read_label_frame(dir.file("f.json"));
  EXPECT_EQ(f.width, 10);
  EXPECT_EQ(f.height, 8);
  EXPECT_EQ(f.name, "frame_1.jpg");
  EXPECT_EQ(f.categories(), (std::vector<std::string>{"cup", "plate"}));
  const auto cup = f.mask("cup");
  ASSERT_EQ(cup.size(), 80u);
  EXPECT_EQ(cup[3 * 10 + 3], 1);
  EXPECT_EQ(cup[0], 0);
  EXPECT_EQ(cup[7 * 10 + 9], 1);
  int area = 0;
  for (auto c : f.mask("plate")) area += c;
  EXPECT_EQ(area, 4);
  const std::vector<std::pair<std::string, std::string>> bad = {
      {R"({"info": {"width": 0, "height": 8}, "objects": []})", "positive integers"},
      {R"({"info": {"width": 4, "height": 4}, "objects": [{"segmentation": [[0,0],[1,0],[1,1]]}]})", "category"},
      {R"({"info": {"width": 4, "height": 4}, "objects": [{"category": "a", "segmentation": [[0,0],[1,0]]}]})",
       "fewer than 3"},
      {R"({"info": {"width": 4, "height": 4}, "objects": [{"category": "a", "segmentation": [[0,0],[1],[1,1]]}]})",
       "not [x, y]"},
      {R"({"objects": []})", "LERF-OVS"},
      {R"({"info": {"width": 4, "height": 4}, "objects": [{"category": "a", "segmentation": [[10,0],[12,0],[12,3]]}]})",
       "('a') lies outside the 4x4 image"},
      {R"({"info": {"width": 4, "height": 4}, "objects": [{"category": "a", "segmentation": [[0,0],[1e300,0],[1,1]]}]})",
       "far outside the 4x4 image"},
  };
  for (const auto& [text, needle] : bad) {
    write_bytes(dir.file("bad.json"), text);
    expect_error_with<std::runtime_error>([&] { read_label_frame(dir.file("bad.json")); }, {"bad.json", needle});
  }
}

TEST(SemanticIo, ClickListsReadAndValidate) {
  ScratchDir dir("json");
  write_bytes(dir.file("c.json"), R"([{"frame": "view_000", "x": 10.5, "y": 3, "category": "mug"},
                                      {"frame": "view_008", "x": 1, "y": 2}])");
  const auto clicks = read_clicks(dir.file("c.json"));
  ASSERT_EQ(clicks.size(), 2u);
  EXPECT_EQ(clicks[0].frame, "view_000");
  EXPECT_DOUBLE_EQ(clicks[0].x, 10.5);
  EXPECT_EQ(clicks[0].category, "mug");
  EXPECT_TRUE(clicks[1].category.empty());
  write_bytes(dir.file("bad.json"), R"([{"frame": "a", "x": 1}])");
  expect_error_with<std::runtime_error>([&] { read_clicks(dir.file("bad.json")); }, {"bad.json", "click 0"});
  write_bytes(dir.file("bad.json"), R"({"frame": "a"})");
  expect_error_with<std::runtime_error>([&] { read_clicks(dir.file("bad.json")); }, {"JSON array"});
}

TEST(PlyExport, StoredValuesRoundTripBitExact) {
  ScratchDir dir("ply");
  for (int degree = 0; degree <= 3; ++degree) {
    GaussianSet gs;
    gs.sh_degree = degree;
    gs.resize(1000);
    std::mt19937 rng(degree);
    std::uniform_int_distribution<uint32_t> bits;
    // Any float bit pattern: logits, log scales, denormals, infinities, signed zeros, NaN payloads.
    for (auto* arr : {&gs.means, &gs.scales, &gs.quats, &gs.opacities, &gs.sh, &gs.features}) {
      for (float& v : *arr) {
        const uint32_t b = bits(rng);
        std::memcpy(&v, &b, 4);
      }
    }
    for (bool features : {true, false}) {
      write_ply(dir.file("p.ply"), gs, features, PlyValues::stored);
      // Random bits hold NaNs and infinities: read them as they are.
      const GaussianSet back = read_ply(dir.file("p.ply"), PlyValues::stored, InvalidGaussians::keep);
      ASSERT_EQ(back.sh_degree, degree);
      auto same_bits = [](const std::vector<float>& a, const std::vector<float>& b) {
        return a.size() == b.size() && std::memcmp(a.data(), b.data(), a.size() * 4) == 0;
      };
      EXPECT_TRUE(same_bits(back.means, gs.means));
      EXPECT_TRUE(same_bits(back.scales, gs.scales));
      EXPECT_TRUE(same_bits(back.quats, gs.quats));
      EXPECT_TRUE(same_bits(back.opacities, gs.opacities));
      EXPECT_TRUE(same_bits(back.sh, gs.sh));
      if (features) EXPECT_TRUE(same_bits(back.features, gs.features));
      // The activated reading of the same file is the standard 3DGS meaning.
      const GaussianSet act = read_ply(dir.file("p.ply"), PlyValues::activated, InvalidGaussians::keep);
      for (size_t i = 0; i < 50; ++i) {
        const double o = 1.0 / (1.0 + std::exp(-static_cast<double>(gs.opacities[i])));
        if (std::isfinite(o)) EXPECT_EQ(act.opacities[i], static_cast<float>(o));
      }
    }
  }
}
