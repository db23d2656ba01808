// The synthetic scene generator (synth/synth_scene.h): determinism, and every
// piece of ground truth checked against an independent re-computation: GT ids
// against a ray caster written here from synth.json alone, label polygons
// against the GT, the COLMAP model against the images, masks and features
// against their format and the designed similarity structure.
#include <gtest/gtest.h>
#include <spdlog/spdlog.h>
#include <sys/wait.h>
#include <unistd.h>

#include <Eigen/Core>
#include <algorithm>
#include <array>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <map>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <set>
#include <sstream>
#include <string>
#include <vector>

#include "host/io/colmap_reader.h"
#include "host/io/image_io.h"
#include "host/io/npy_io.h"
#include "host/io/semantic_io.h"
#include "synth/synth_scene.h"

namespace fs = std::filesystem;
using Json = nlohmann::json;
using Vec3 = Eigen::Vector3d;

namespace {

// Progress lines of the generator would drown the test output.
const bool kQuiet = [] {
  spdlog::set_level(spdlog::level::warn);
  return true;
}();

fs::path temp_dir(const std::string& name) {
  fs::path d = fs::path(testing::TempDir()) / ("ag2gs_synth_" + name + "_" + std::to_string(::getpid()));
  fs::remove_all(d);
  return d;
}

ag2gs::SynthOptions small_options(uint64_t seed, bool hard = false) {
  ag2gs::SynthOptions o;
  o.seed = seed;
  o.width = 64;
  o.height = 48;
  o.views = 8;
  o.points = 600;
  o.hard = hard;
  return o;
}

// Scenes generated once per process and shared by the tests.
const fs::path& scene(const std::string& which) {
  static std::map<std::string, fs::path> scenes;
  auto it = scenes.find(which);
  if (it != scenes.end()) return it->second;
  fs::path d = temp_dir(which);
  ag2gs::SynthOptions o;
  if (which == "small") {
    o = small_options(3);
  } else if (which == "hard") {
    o = small_options(2, true);
    o.width = 96;
    o.height = 72;
    o.views = 9;  // test views 0 and 8
  } else if (which == "background") {
    o = small_options(3);
    o.background_masks = true;
  } else if (which == "removal") {
    o = small_options(3);
    o.removal_gt = true;
  } else if (which == "half_masks") {
    o = small_options(5);
    o.mask_factor = 2;
    o.views = 3;
  } else {
    throw std::logic_error(which);
  }
  ag2gs::write_synth_scene(d.string(), o);
  return scenes[which] = d;
}

Json read_json(const fs::path& p) {
  std::ifstream f(p);
  return Json::parse(f);
}

std::string read_bytes(const fs::path& p) {
  std::ifstream f(p, std::ios::binary);
  std::stringstream ss;
  ss << f.rdbuf();
  return ss.str();
}

cv::Mat read16(const fs::path& p) {
  cv::Mat m = cv::imread(p.string(), cv::IMREAD_UNCHANGED);
  EXPECT_EQ(m.type(), CV_16UC1) << p;
  return m;
}

Vec3 vec(const Json& j) {
  return {j[0].get<double>(), j[1].get<double>(), j[2].get<double>()};
}

// ------------------------------------------------------------------ an independent ray caster
// Written from the conventions recorded in synth.json, not from the generator.
struct Cam {
  std::string name;
  bool test = false;
  int width = 0, height = 0;
  double fx = 0, fy = 0, cx = 0, cy = 0;
  Eigen::Matrix3d R;
  Vec3 t;
  Vec3 centre() const { return -R.transpose() * t; }
};

struct Obj {
  int id = 0;
  std::string category, primitive;
  Vec3 centre, size, colour;
  double yaw = 0;
};

struct Synth {
  Json json;
  std::vector<Cam> cams;
  std::vector<Obj> objs;
  double ground_radius = 0;
  bool backdrop = false;  // the closed textured cylinder around everything
  double backdrop_radius = 0, backdrop_height = 0;
};

Synth load(const fs::path& dir) {
  Synth s;
  s.json = read_json(dir / "synth.json");
  for (const auto& c : s.json["cameras"]) {
    Cam cam;
    cam.name = c["name"];
    cam.test = c["test"];
    cam.width = c["width"];
    cam.height = c["height"];
    cam.fx = c["fx"];
    cam.fy = c["fy"];
    cam.cx = c["cx"];
    cam.cy = c["cy"];
    for (int r = 0; r < 3; ++r)
      for (int k = 0; k < 3; ++k) cam.R(r, k) = c["R"][r][k];
    cam.t = vec(c["t"]);
    s.cams.push_back(cam);
  }
  for (const auto& o : s.json["objects"]) {
    Obj ob;
    ob.id = o["id"];
    ob.category = o["category"];
    ob.primitive = o["primitive"];
    ob.centre = vec(o["centre"]);
    ob.size = vec(o["size"]);
    ob.colour = vec(o["colour"]);
    ob.yaw = o["yaw"];
    s.objs.push_back(ob);
  }
  s.ground_radius = s.json["world"]["ground"]["radius"];
  const Json& bd = s.json["world"]["backdrop"];
  s.backdrop = bd.is_object();
  if (s.backdrop) {
    s.backdrop_radius = bd["radius"];
    s.backdrop_height = bd["height"];
  }
  return s;
}

// Distance along the unit ray to the object, or +inf.
double hit_distance(const Obj& ob, const Vec3& origin, const Vec3& dir) {
  const double inf = std::numeric_limits<double>::infinity();
  // Into the object frame: rotate by -yaw about z around the centre.
  Eigen::Matrix3d Rz;
  Rz << std::cos(ob.yaw), std::sin(ob.yaw), 0, -std::sin(ob.yaw), std::cos(ob.yaw), 0, 0, 0, 1;
  Vec3 o = Rz * (origin - ob.centre), d = Rz * dir;
  Vec3 h = ob.size / 2;
  double best = inf;
  if (ob.primitive == "sphere") {
    // |o + t d|^2 = r^2 with |d| = 1.
    double b = 2 * o.dot(d), c = o.squaredNorm() - h.x() * h.x(), disc = b * b - 4 * c;
    if (disc >= 0) {
      double t = (-b - std::sqrt(disc)) / 2;
      if (t > 0) best = t;
    }
  } else if (ob.primitive == "box") {
    double lo = 0, hi = inf;
    for (int a = 0; a < 3; ++a) {
      if (d[a] == 0) {
        if (std::abs(o[a]) > h[a]) return inf;
        continue;
      }
      double t1 = (-h[a] - o[a]) / d[a], t2 = (h[a] - o[a]) / d[a];
      lo = std::max(lo, std::min(t1, t2));
      hi = std::min(hi, std::max(t1, t2));
    }
    if (lo <= hi && lo > 0) best = lo;
  } else if (ob.primitive == "cylinder") {
    double a = d.x() * d.x() + d.y() * d.y();
    if (a > 0) {
      double b = 2 * (o.x() * d.x() + o.y() * d.y()), c = o.x() * o.x() + o.y() * o.y() - h.x() * h.x();
      double disc = b * b - 4 * a * c;
      if (disc >= 0) {
        double t = (-b - std::sqrt(disc)) / (2 * a);
        if (t > 0 && std::abs(o.z() + t * d.z()) <= h.z()) best = t;
      }
    }
    for (double z : {h.z(), -h.z()}) {
      if (d.z() == 0) break;
      double t = (z - o.z()) / d.z();
      Vec3 p = o + t * d;
      if (t > 0 && t < best && p.x() * p.x() + p.y() * p.y() <= h.x() * h.x()) best = t;
    }
  }
  return best;
}

// Object id first met by the ray (0 ground, backdrop or sky) and the distance.
std::pair<int, double> cast(const Synth& s, const Vec3& origin, const Vec3& dir) {
  int id = 0;
  double best = std::numeric_limits<double>::infinity();
  if (dir.z() < 0) {
    double t = -origin.z() / dir.z();
    Vec3 p = origin + t * dir;
    if (std::hypot(p.x(), p.y()) <= (s.backdrop ? s.backdrop_radius : s.ground_radius)) best = t;
  }
  if (s.backdrop) {
    // From inside the closed cylinder: the ceiling or the far root of the wall.
    if (dir.z() > 0) {
      double t = (s.backdrop_height - origin.z()) / dir.z();
      Vec3 p = origin + t * dir;
      if (std::hypot(p.x(), p.y()) <= s.backdrop_radius) best = std::min(best, t);
    }
    double a = dir.x() * dir.x() + dir.y() * dir.y();
    double b = 2 * (origin.x() * dir.x() + origin.y() * dir.y());
    double c = origin.x() * origin.x() + origin.y() * origin.y() - s.backdrop_radius * s.backdrop_radius;
    if (a > 0 && b * b - 4 * a * c >= 0) {
      double t = (-b + std::sqrt(b * b - 4 * a * c)) / (2 * a);
      double z = origin.z() + t * dir.z();
      if (t > 0 && z >= 0 && z <= s.backdrop_height) best = std::min(best, t);
    }
  }
  for (const auto& ob : s.objs) {
    double t = hit_distance(ob, origin, dir);
    if (t < best) {
      best = t;
      id = ob.id;
    }
  }
  return {id, best};
}

Vec3 pixel_ray(const Cam& c, double u, double v) {
  return (c.R.transpose() * Vec3((u - c.cx) / c.fx, (v - c.cy) / c.fy, 1.0)).normalized();
}

std::string stem(const std::string& name) {
  return fs::path(name).stem().string();
}

// ------------------------------------------------------------------ tests
TEST(Synth, SameSeedSameBytesOtherSeedOtherScene) {
  fs::path a = temp_dir("det_a"), b = temp_dir("det_b"), c = temp_dir("det_c");
  ag2gs::write_synth_scene(a.string(), small_options(11));
  ag2gs::write_synth_scene(b.string(), small_options(11));
  ag2gs::write_synth_scene(c.string(), small_options(12));
  Json files = read_json(a / "synth.json")["files"];
  ASSERT_GT(files.size(), 40u);
  for (const auto& f : files) {
    std::string rel = f;
    ASSERT_TRUE(fs::exists(a / rel)) << rel;
    EXPECT_EQ(read_bytes(a / rel), read_bytes(b / rel)) << rel << " differs between two runs with the same seed";
  }
  for (const char* rel : {"images/view_000.png", "gt/view_001.png", "synth.json", "sparse/0/points3D.bin",
                          "language_features/view_002_f.npy"})
    EXPECT_NE(read_bytes(a / rel), read_bytes(c / rel)) << rel << " is the same for seeds 11 and 12";
  // The CLIP-like model is fixed: a phrase has the same text embedding in every scene.
  Json va = read_json(a / "vocab.json"), vc = read_json(c / "vocab.json");
  int shared = 0;
  for (auto it = va.begin(); it != va.end(); ++it)
    if (vc.contains(it.key())) {
      EXPECT_EQ(it.value(), vc[it.key()]) << it.key();
      ++shared;
    }
  EXPECT_GT(shared, 0);
}

TEST(Synth, GtIdsMatchAnIndependentRayCastOfThePixelCentres) {
  for (const char* which : {"small", "hard"}) {
    const fs::path& dir = scene(which);
    Synth s = load(dir);
    size_t mismatches = 0, object_pixels = 0, total = 0;
    for (const auto& cam : s.cams) {
      cv::Mat gt = read16(dir / "gt" / cam.name);
      ASSERT_EQ(gt.cols, cam.width);
      ASSERT_EQ(gt.rows, cam.height);
      for (int y = 0; y < cam.height; ++y)
        for (int x = 0; x < cam.width; ++x) {
          int id = cast(s, cam.centre(), pixel_ray(cam, x + 0.5, y + 0.5)).first;
          int g = gt.at<uint16_t>(y, x);
          mismatches += id != g;
          object_pixels += g > 0;
          ++total;
        }
    }
    EXPECT_EQ(mismatches, 0u) << which;
    EXPECT_GT(object_pixels, total / 50) << which << ": objects cover too little of the images";
  }
}

TEST(Synth, SceneLayoutIsInsideTheGroundWithoutInterpenetration) {
  for (const char* which : {"small", "hard"}) {
    Synth s = load(scene(which));
    std::set<std::pair<int, int>> touching;
    for (const auto& p : s.json["relations"]["touching"]) touching.insert({p[0].get<int>(), p[1].get<int>()});
    std::set<std::string> categories;
    for (const auto& o : s.objs) {
      EXPECT_TRUE(categories.insert(o.category).second) << "category used twice: " << o.category;
      EXPECT_NEAR(o.centre.z(), o.size.z() / 2, 1e-12) << o.category << " does not stand on the ground";
      double fp = o.primitive == "box" ? std::hypot(o.size.x(), o.size.y()) / 2 : o.size.x() / 2;
      EXPECT_LE(std::hypot(o.centre.x(), o.centre.y()) + fp, s.ground_radius) << o.category;
    }
    for (size_t i = 0; i < s.objs.size(); ++i)
      for (size_t j = i + 1; j < s.objs.size(); ++j) {
        const Obj &a = s.objs[i], &b = s.objs[j];
        if (touching.count({a.id, b.id})) continue;
        double fa = a.primitive == "box" ? std::hypot(a.size.x(), a.size.y()) / 2 : a.size.x() / 2;
        double fb = b.primitive == "box" ? std::hypot(b.size.x(), b.size.y()) / 2 : b.size.x() / 2;
        EXPECT_GT(std::hypot(a.centre.x() - b.centre.x(), a.centre.y() - b.centre.y()), fa + fb)
            << a.category << " and " << b.category << " may interpenetrate";
      }
  }
}

TEST(Synth, HardSceneHasTouchingSimilarThinAndOccludedObjects) {
  Synth s = load(scene("hard"));
  const Json& rel = s.json["relations"];
  ASSERT_EQ(rel["touching"].size(), 1u);
  const Obj& a = s.objs[rel["touching"][0][0].get<int>() - 1];
  const Obj& b = s.objs[rel["touching"][0][1].get<int>() - 1];
  ASSERT_EQ(a.primitive, "box");
  ASSERT_EQ(b.primitive, "box");
  EXPECT_EQ(a.yaw, b.yaw);
  // b's -x face lies in a's +x face plane: the centres are (hx_a + hx_b) apart along a's x axis.
  Vec3 axis(std::cos(a.yaw), std::sin(a.yaw), 0), side(-std::sin(a.yaw), std::cos(a.yaw), 0);
  Vec3 d = b.centre - a.centre;
  EXPECT_NEAR(d.dot(axis), (a.size.x() + b.size.x()) / 2, 1e-12);
  EXPECT_LT(std::abs(d.dot(side)), (a.size.y() + b.size.y()) / 2) << "the faces do not overlap";
  ASSERT_EQ(rel["similar_colour"].size(), 1u);
  const Obj& c = s.objs[rel["similar_colour"][0][0].get<int>() - 1];
  const Obj& e = s.objs[rel["similar_colour"][0][1].get<int>() - 1];
  EXPECT_LT((c.colour - e.colour).norm(), 0.25);
  EXPECT_NE(c.category, e.category);
  ASSERT_EQ(rel["thin"].size(), 1u);
  const Obj& pole = s.objs[rel["thin"][0].get<int>() - 1];
  EXPECT_LT(pole.size.x(), 0.1);
  EXPECT_GT(pole.size.z(), 10 * pole.size.x());
  EXPECT_FALSE(s.json["occlusion_pairs"].empty());
  // The pole is seen behind the red mug from camera 1 (the layout guarantees it).
  bool pole_hidden = false;
  for (const auto& o : s.json["views"][1]["occlusions"])
    pole_hidden = pole_hidden || o["occluded"].get<int>() == pole.id;
  EXPECT_TRUE(pole_hidden);
}

TEST(Synth, LabelPolygonsCoverTheGtMasks) {
  for (const char* which : {"small", "hard"}) {
    const fs::path& dir = scene(which);
    Synth s = load(dir);
    int frames = 0;
    for (const auto& cam : s.cams) {
      fs::path label = dir / "label" / (stem(cam.name) + ".json");
      ASSERT_EQ(fs::exists(label), cam.test) << label;
      if (!cam.test) continue;
      ++frames;
      ag2gs::LabelFrame frame = ag2gs::read_label_frame(label.string());
      EXPECT_EQ(frame.width, cam.width);
      EXPECT_EQ(frame.height, cam.height);
      EXPECT_EQ(frame.name, cam.name);
      cv::Mat gt = read16(dir / "gt" / cam.name);
      std::set<std::string> labelled;
      for (const auto& c : frame.categories()) labelled.insert(c);
      for (const auto& ob : s.objs) {
        cv::Mat g = gt == ob.id;
        int n = cv::countNonZero(g);
        if (n < 6) continue;
        ASSERT_TRUE(labelled.count(ob.category)) << cam.name << ": " << ob.category << " has " << n << " pixels";
        std::vector<unsigned char> m = frame.mask(ob.category);
        int inter = 0, uni = 0;
        for (int y = 0; y < cam.height; ++y)
          for (int x = 0; x < cam.width; ++x) {
            bool a = g.at<uint8_t>(y, x) != 0, b = m[static_cast<size_t>(y) * cam.width + x] != 0;
            inter += a && b;
            uni += a || b;
          }
        EXPECT_GT(static_cast<double>(inter) / uni, 0.95) << which << " " << cam.name << " " << ob.category;
      }
    }
    EXPECT_GE(frames, 1);
  }
}

TEST(Synth, MasksHaveTheLangSplatFormat) {
  for (const char* which : {"small", "half_masks"}) {
    const fs::path& dir = scene(which);
    Synth s = load(dir);
    const int factor = s.json["options"]["mask_factor"];
    for (size_t vi = 0; vi < s.cams.size(); ++vi) {
      const Cam& cam = s.cams[vi];
      const std::string st = stem(cam.name);
      ag2gs::NpyArray ids = ag2gs::read_npy((dir / "language_features" / (st + "_s.npy")).string());
      ag2gs::NpyArray feats = ag2gs::read_npy((dir / "language_features" / (st + "_f.npy")).string());
      const int Hm = cam.height / factor, Wm = cam.width / factor;
      ASSERT_EQ(ids.shape, (std::vector<int64_t>{4, Hm, Wm})) << st;
      ASSERT_EQ(feats.shape.size(), 2u);
      ASSERT_EQ(feats.dim(1), 512);
      const int64_t n = feats.dim(0);
      // Ids: -1 or integers; each level a contiguous range after the previous level's.
      int64_t next = 0;
      std::vector<int64_t> pixels(n, 0);
      for (int l = 0; l < 4; ++l) {
        std::set<int64_t> seen;
        for (int64_t p = 0; p < int64_t(Hm) * Wm; ++p) {
          float v = ids.data[l * Hm * Wm + p];
          ASSERT_EQ(v, std::floor(v));
          if (v < 0) {
            ASSERT_EQ(v, -1.f);
            continue;
          }
          seen.insert(static_cast<int64_t>(v));
          ASSERT_LT(static_cast<int64_t>(v), n);
          ++pixels[static_cast<int64_t>(v)];
        }
        for (int64_t id : seen) EXPECT_EQ(id, next++) << st << " level " << l;
        int expect = s.json["views"][vi]["masks_per_level"][l];
        EXPECT_EQ(static_cast<int>(seen.size()), expect);
      }
      EXPECT_EQ(next, n) << st << ": rows of _f != max id + 1";
      for (int64_t r = 0; r < n; ++r) {
        double norm = 0;
        for (int k = 0; k < 512; ++k) norm += double(feats.data[r * 512 + k]) * feats.data[r * 512 + k];
        EXPECT_NEAR(std::sqrt(norm), 1.0, 1e-5);
        EXPECT_GE(pixels[r], 4) << "mask " << r << " of " << st << " is empty or tiny";
      }
      // masks/<stem>.png = level-3 id + 1, nearest-upsampled to the image size.
      cv::Mat png = read16(dir / "masks" / cam.name);
      ASSERT_EQ(png.cols, cam.width);
      ASSERT_EQ(png.rows, cam.height);
      for (int y = 0; y < cam.height; ++y)
        for (int x = 0; x < cam.width; ++x)
          ASSERT_EQ(png.at<uint16_t>(y, x), ids.data[3 * Hm * Wm + (y / factor) * Wm + x / factor] + 1);
    }
  }
}

TEST(Synth, LargeMasksFollowTheObjectsAndCarryTheirCategoryFeature) {
  const fs::path& dir = scene("small");
  Synth s = load(dir);
  ag2gs::Vocabulary vocab = ag2gs::read_vocabulary((dir / "vocab.json").string());
  int checked = 0;
  for (const auto& cam : s.cams) {
    const std::string st = stem(cam.name);
    ag2gs::NpyArray ids = ag2gs::read_npy((dir / "language_features" / (st + "_s.npy")).string());
    ag2gs::NpyArray feats = ag2gs::read_npy((dir / "language_features" / (st + "_f.npy")).string());
    cv::Mat gt = read16(dir / "gt" / cam.name);
    const int H = cam.height, W = cam.width;
    std::map<int, std::map<int, int>> overlap;  // mask id -> gt id -> pixels
    for (int y = 0; y < H; ++y)
      for (int x = 0; x < W; ++x) {
        int m = static_cast<int>(ids.data[3 * H * W + y * W + x]);
        if (m >= 0) ++overlap[m][gt.at<uint16_t>(y, x)];
      }
    for (const auto& [m, by_gt] : overlap) {
      int best_id = 0, best = 0, total = 0;
      for (const auto& [g, n] : by_gt) {
        total += n;
        if (n > best) best = n, best_id = g;
      }
      ASSERT_GT(best_id, 0) << st << " mask " << m << " lies mostly on the ground";
      // Boundary jitter of a pixel or two only.
      int gt_pixels = cv::countNonZero(gt == best_id);
      EXPECT_GT(double(best) / (total + gt_pixels - best), 0.5) << st << " mask " << m;
      // Its feature is nearest to the object's own phrase among all phrases.
      const std::string& want = s.objs[best_id - 1].category;
      std::string nearest;
      double best_cos = -2;
      for (const auto& [phrase, v] : vocab.phrases) {
        double c = 0;
        for (int k = 0; k < 512; ++k) c += double(v[k]) * feats.data[m * 512 + k];
        if (c > best_cos) best_cos = c, nearest = phrase;
      }
      EXPECT_EQ(nearest, want) << st << " mask " << m;
      EXPECT_GT(best_cos, 0.85);
      EXPECT_LT(best_cos, 0.999) << "text embeddings must be close to, not equal to, mask features";
      ++checked;
    }
  }
  EXPECT_GT(checked, 20);
}

// --removal-gt adds removal_gt/<category>/<test view>.png and changes no other
// file. Inside the removed objects' exact masks the image changes (the ray now
// meets what was behind them); elsewhere only their shadows may change.
TEST(Synth, RemovalGroundTruthTracesTheTestViewsWithoutEachCategory) {
  const fs::path& plain = scene("small");
  const fs::path& dir = scene("removal");
  Synth s = load(dir);
  ASSERT_TRUE(s.json["options"].value("removal_gt", false));
  EXPECT_FALSE(fs::exists(plain / "removal_gt"));
  for (const auto& cam : s.cams) {
    EXPECT_EQ(read_bytes(dir / "images" / cam.name), read_bytes(plain / "images" / cam.name)) << cam.name;
    EXPECT_EQ(read_bytes(dir / "gt" / cam.name), read_bytes(plain / "gt" / cam.name)) << cam.name;
  }
  std::set<std::string> categories;
  for (const auto& o : s.objs) categories.insert(o.category);
  int checked = 0;
  for (const std::string& category : categories) {
    std::set<int> ids;
    for (const auto& o : s.objs)
      if (o.category == category) ids.insert(o.id);
    for (const auto& cam : s.cams) {
      const fs::path gt_file = dir / "removal_gt" / category / cam.name;
      if (!cam.test) {
        EXPECT_FALSE(fs::exists(gt_file)) << gt_file;
        continue;
      }
      cv::Mat removed = cv::imread(gt_file.string(), cv::IMREAD_COLOR);
      cv::Mat image = cv::imread((dir / "images" / cam.name).string(), cv::IMREAD_COLOR);
      cv::Mat gt = read16(dir / "gt" / cam.name);
      ASSERT_FALSE(removed.empty()) << gt_file;
      ASSERT_EQ(removed.size(), image.size()) << gt_file;
      size_t inside = 0, inside_changed = 0, outside_changed = 0;
      for (int y = 0; y < image.rows; ++y)
        for (int x = 0; x < image.cols; ++x) {
          const cv::Vec3b a = image.at<cv::Vec3b>(y, x), b = removed.at<cv::Vec3b>(y, x);
          const bool changed = a != b;
          if (ids.count(gt.at<uint16_t>(y, x))) {
            ++inside;
            inside_changed += changed;
          } else {
            outside_changed += changed;
          }
        }
      if (inside >= 20) {
        ++checked;
        EXPECT_GE(inside_changed, 0.9 * inside) << gt_file;
      }
      // Outside the object only its shadow, cast on the ground, can change.
      EXPECT_LE(outside_changed, std::max<size_t>(3 * inside, 40)) << gt_file;
    }
  }
  EXPECT_GT(checked, 0) << "no removed object is visible in a test view: the test would be vacuous";
}

// --background-masks: the object masks stay exactly as without it, and the
// background (GT id 0) gets masks of its own, cut differently from view to
// view, whose features match no phrase of the scene.
TEST(Synth, BackgroundMasksCoverTheBackgroundOnly) {
  const fs::path& plain = scene("small");
  const fs::path& dir = scene("background");
  Synth s = load(dir);
  ag2gs::Vocabulary vocab = ag2gs::read_vocabulary((dir / "vocab.json").string());
  std::vector<std::map<int, int>> ground_cuts;  // per view: ground point -> background mask id
  for (const auto& cam : s.cams) {
    const std::string st = stem(cam.name);
    ag2gs::NpyArray ids = ag2gs::read_npy((dir / "language_features" / (st + "_s.npy")).string());
    ag2gs::NpyArray ids0 = ag2gs::read_npy((plain / "language_features" / (st + "_s.npy")).string());
    ag2gs::NpyArray feats = ag2gs::read_npy((dir / "language_features" / (st + "_f.npy")).string());
    cv::Mat gt = read16(dir / "gt" / cam.name);
    const int H = cam.height, W = cam.width;
    std::map<int, std::map<int, int>> overlap;  // mask id -> gt id -> pixels
    std::map<int, int> same_object_mask;        // mask id here -> mask id without the option
    int background = 0, background_masked = 0;
    for (int y = 0; y < H; ++y)
      for (int x = 0; x < W; ++x) {
        const size_t p = 3 * size_t(H) * W + size_t(y) * W + x;
        const int m = static_cast<int>(ids.data[p]), m0 = static_cast<int>(ids0.data[p]);
        const int g = gt.at<uint16_t>(y, x);
        if (m >= 0) ++overlap[m][g];
        if (g == 0) ++background, background_masked += m >= 0;
        if (m0 >= 0) {
          // Every object-mask pixel of the plain scene is in one mask here, always the same one.
          ASSERT_GE(m, 0) << st << " (" << x << "," << y << ")";
          auto [it, fresh] = same_object_mask.emplace(m, m0);
          EXPECT_EQ(it->second, m0) << st << " (" << x << "," << y << ")";
        }
      }
    // Most of the background is covered (SAM drops a mask now and then: a quarter can go missing).
    EXPECT_GT(background_masked, 0.5 * background) << st;
    int background_masks = 0;
    for (const auto& [m, by_gt] : overlap) {
      if (same_object_mask.count(m)) continue;
      int total = 0;
      for (const auto& [g, n] : by_gt) total += n;
      // Boundary jitter aside, a background mask lies on the background.
      EXPECT_GT(by_gt.count(0) ? by_gt.at(0) : 0, 0.8 * total) << st << " mask " << m;
      ++background_masks;
      for (const auto& [phrase, v] : vocab.phrases) {
        double c = 0;
        for (int k = 0; k < 512; ++k) c += double(v[k]) * feats.data[m * 512 + k];
        EXPECT_LT(c, 0.5) << st << " background mask " << m << " resembles '" << phrase << "'";
      }
    }
    EXPECT_GE(background_masks, 3) << st;
    // The cut of the ground: the mask at fixed ground points seen from this view,
    // where the 5x5 pixels around them all carry one background mask (so the
    // boundary jitter cannot make two views differ).
    std::map<int, int> at;  // ground point -> mask id
    int point = 0;
    for (double gx = -2.4; gx <= 2.41; gx += 0.4)
      for (double gy = -2.4; gy <= 2.41; gy += 0.4, ++point) {
        const Vec3 pc = cam.R * Vec3(gx, gy, 0) + cam.t;
        if (pc.z() <= 0) continue;
        const int x = static_cast<int>(std::floor(cam.fx * pc.x() / pc.z() + cam.cx));
        const int y = static_cast<int>(std::floor(cam.fy * pc.y() / pc.z() + cam.cy));
        if (x < 2 || y < 2 || x >= W - 2 || y >= H - 2) continue;
        const int m = static_cast<int>(ids.data[3 * size_t(H) * W + size_t(y) * W + x]);
        bool interior = m >= 0 && !same_object_mask.count(m);
        for (int dy = -2; dy <= 2 && interior; ++dy)
          for (int dx = -2; dx <= 2 && interior; ++dx)
            interior = static_cast<int>(ids.data[3 * size_t(H) * W + size_t(y + dy) * W + x + dx]) == m &&
                       gt.at<uint16_t>(y + dy, x + dx) == 0;
        if (interior) at[point] = m;
      }
    ground_cuts.push_back(at);
  }
  // Two views cut the ground alike when every pair of points both see is
  // together in one mask in both views or apart in both.
  int pairs = 0, alike = 0;
  for (size_t a = 0; a < ground_cuts.size(); ++a)
    for (size_t b = a + 1; b < ground_cuts.size(); ++b) {
      std::vector<std::pair<int, int>> both;  // (mask in a, mask in b) of the points both see
      for (const auto& [pt, m] : ground_cuts[a])
        if (ground_cuts[b].count(pt)) both.emplace_back(m, ground_cuts[b].at(pt));
      if (both.size() < 6) continue;
      bool same = true;
      for (size_t i = 0; i < both.size(); ++i)
        for (size_t j = i + 1; j < both.size(); ++j)
          same = same && ((both[i].first == both[j].first) == (both[i].second == both[j].second));
      ++pairs, alike += same;
    }
  ASSERT_GT(pairs, 5);
  EXPECT_LT(alike, pairs / 2) << "the background is cut the same way in most pairs of views";
}

double cosine(const std::vector<float>& a, const std::vector<float>& b) {
  double d = 0, na = 0, nb = 0;
  for (size_t i = 0; i < a.size(); ++i) {
    d += double(a[i]) * b[i];
    na += double(a[i]) * a[i];
    nb += double(b[i]) * b[i];
  }
  return d / std::sqrt(na * nb);
}

TEST(Synth, VocabularyHasTheDesignedSimilarityStructure) {
  for (const char* which : {"small", "hard"}) {
    const fs::path& dir = scene(which);
    Synth s = load(dir);
    ag2gs::Vocabulary v = ag2gs::read_vocabulary((dir / "vocab.json").string());
    EXPECT_EQ(v.dim, 512);
    for (const auto& o : s.objs) EXPECT_TRUE(v.phrases.count(o.category)) << o.category;
    ASSERT_GE(s.json["distractors"].size(), 3u);
    for (const auto& d : s.json["distractors"]) {
      EXPECT_TRUE(v.phrases.count(d.get<std::string>())) << d;
      for (const auto& o : s.objs) EXPECT_NE(o.category, d.get<std::string>());
    }
    EXPECT_EQ(v.phrases.size(), s.objs.size() + s.json["distractors"].size());
    // Cosines: same family ~0.77, same colour ~0.25, nothing shared ~0.15,
    // shrunk a little by the text noise (|noise| 0.15 -> factor ~1/1.02).
    auto split = [](const std::string& p) {
      size_t sp = p.rfind(' ');
      return sp == std::string::npos ? std::make_pair(std::string(), p)
                                     : std::make_pair(p.substr(0, sp), p.substr(sp + 1));
    };
    int same_family = 0, unrelated = 0;
    for (auto a = v.phrases.begin(); a != v.phrases.end(); ++a) {
      EXPECT_NEAR(cosine(a->second, a->second), 1.0, 1e-6);
      for (auto b = std::next(a); b != v.phrases.end(); ++b) {
        auto [ca, fa] = split(a->first);
        auto [cb, fb] = split(b->first);
        bool known = std::set<std::string>{"mug", "ball", "box", "can", "pole"}.count(fa) &&
                     std::set<std::string>{"mug", "ball", "box", "can", "pole"}.count(fb);
        if (!known) fa = a->first, fb = b->first, ca = "-a", cb = "-b";
        double c = cosine(a->second, b->second);
        bool related_colour = ca == cb || (ca == "dark red" && cb == "red") || (ca == "red" && cb == "dark red");
        if (fa == fb) {
          ++same_family;
          EXPECT_GT(c, related_colour ? 0.78 : 0.68) << a->first << " / " << b->first;
          EXPECT_LT(c, related_colour ? 0.9 : 0.82) << a->first << " / " << b->first;
        } else {
          ++unrelated;
          EXPECT_GT(c, related_colour ? 0.17 : 0.07) << a->first << " / " << b->first;
          EXPECT_LT(c, related_colour ? 0.33 : 0.25) << a->first << " / " << b->first;
        }
      }
    }
    EXPECT_GT(same_family, 0) << which;
    EXPECT_GT(unrelated, 0) << which;
  }
}

TEST(Synth, ColmapModelReprojectsPointsWhereTheyAreVisible) {
  const fs::path& dir = scene("small");
  Synth s = load(dir);
  ag2gs::ColmapModel model = ag2gs::read_colmap_model((dir / "sparse" / "0").string());
  ASSERT_EQ(model.cameras_for_images.size(), s.cams.size());
  for (size_t i = 0; i < s.cams.size(); ++i) {
    const ag2gs::Camera& c = model.cameras_for_images[i];
    EXPECT_EQ(c.name, s.cams[i].name);
    EXPECT_EQ(c.width, s.cams[i].width);
    EXPECT_NEAR(c.fx, s.cams[i].fx, 1e-9);
    EXPECT_NEAR(c.cy, s.cams[i].cy, 1e-9);
    EXPECT_LT((c.R - s.cams[i].R).norm(), 1e-9);
    EXPECT_LT((c.t - s.cams[i].t).norm(), 1e-9);
  }
  ASSERT_EQ(model.points.size(), s.json["points_written"].get<size_t>());
  ASSERT_EQ(model.points.size(), 600u);
  std::vector<std::vector<float>> images;
  std::vector<cv::Mat> gts;
  for (const auto& cam : s.cams) {
    int w, h;
    images.push_back(ag2gs::read_rgb((dir / "images" / cam.name).string(), w, h));
    gts.push_back(read16(dir / "gt" / cam.name));
  }
  std::vector<double> errors;
  size_t visible = 0, id_agree = 0, on_objects = 0;
  for (size_t p = 0; p < model.points.size(); ++p) {
    const Vec3 X = model.points[p];
    int seen_in = 0;
    for (size_t v = 0; v < s.cams.size(); ++v) {
      const ag2gs::Camera& c = model.cameras_for_images[v];
      Vec3 xc = c.R * X + c.t;
      if (xc.z() <= 0) continue;
      double u = c.fx * xc.x() / xc.z() + c.cx, vv = c.fy * xc.y() / xc.z() + c.cy;
      if (u < 0 || vv < 0 || u >= c.width || vv >= c.height) continue;
      Vec3 o = s.cams[v].centre(), d = (X - o).normalized();
      auto [id, t] = cast(s, o, d);
      double dist = (X - o).norm();
      if (std::abs(t - dist) > 1e-6 * dist) continue;  // hidden from this view
      ++seen_in;
      ++visible;
      int px = static_cast<int>(u), py = static_cast<int>(vv);
      id_agree += gts[v].at<uint16_t>(py, px) == id;
      on_objects += id > 0;
      const float* rgb = &images[v][(static_cast<size_t>(py) * c.width + px) * 3];
      double e = 0;
      for (int k = 0; k < 3; ++k) e = std::max(e, std::abs(rgb[k] - model.colors[p][k] / 255.0));
      errors.push_back(e);
    }
    EXPECT_GE(seen_in, 1) << "point " << p << " is visible in no view";
  }
  ASSERT_GT(visible, model.points.size());
  EXPECT_GT(on_objects, visible / 20) << "no points on the objects";
  EXPECT_GT(double(id_agree) / visible, 0.95);
  std::sort(errors.begin(), errors.end());
  double median = errors[errors.size() / 2], p90 = errors[errors.size() * 9 / 10];
  std::printf("  %zu visible reprojections, colour error median %.3f, 90th percentile %.3f\n", visible, median, p90);
  EXPECT_LT(median, 0.04);
  EXPECT_LT(p90, 0.15);
}

// With the backdrop (the default) no camera ray escapes to the sky: every
// pixel meets finite geometry, and the sparse points cover the backdrop too
// (SfM needs them there, as in a real capture). Without it the old sky is back.
TEST(Synth, BackdropClosesTheSceneAndCarriesPoints) {
  const fs::path& dir = scene("small");
  Synth s = load(dir);
  ASSERT_TRUE(s.backdrop);
  EXPECT_TRUE(s.json["options"]["backdrop"].get<bool>());
  EXPECT_GT(s.backdrop_radius, s.ground_radius);
  for (const auto& cam : s.cams) {
    Vec3 o = cam.centre();
    EXPECT_LT(std::hypot(o.x(), o.y()), s.backdrop_radius) << cam.name;
    for (int y = 0; y <= cam.height; y += 4)
      for (int x = 0; x <= cam.width; x += 4) {
        auto [id, t] = cast(s, o, pixel_ray(cam, x, y));
        ASSERT_TRUE(std::isfinite(t)) << cam.name << " pixel " << x << "," << y << " sees the sky";
      }
  }
  ag2gs::ColmapModel model = ag2gs::read_colmap_model((dir / "sparse" / "0").string());
  size_t on_wall = 0;
  for (const auto& X : model.points) {
    double r = std::hypot(X.x(), X.y());
    EXPECT_LE(r, s.backdrop_radius + 1e-6);
    EXPECT_GE(X.z(), -1e-6);
    EXPECT_LE(X.z(), s.backdrop_height + 1e-6);
    on_wall += std::abs(r - s.backdrop_radius) < 1e-6;
  }
  EXPECT_GT(on_wall, model.points.size() / 10) << "no sparse points on the backdrop wall";

  fs::path d = temp_dir("sky");
  ag2gs::SynthOptions o = small_options(3);
  o.views = 2;
  o.backdrop = false;
  ag2gs::write_synth_scene(d.string(), o);
  Synth sky = load(d);
  EXPECT_FALSE(sky.backdrop);
  EXPECT_FALSE(sky.json["options"]["backdrop"].get<bool>());
  EXPECT_TRUE(sky.json["world"]["backdrop"].is_null());
  const Cam& cam = sky.cams[0];
  auto [id, t] = cast(sky, cam.centre(), pixel_ray(cam, cam.width / 2.0, 0.5));
  EXPECT_FALSE(std::isfinite(t)) << "the top of the image should see the sky without the backdrop";
}

TEST(Synth, ClicksLieInsideTheirCategorysGtMask) {
  for (const char* which : {"small", "hard"}) {
    const fs::path& dir = scene(which);
    Synth s = load(dir);
    std::vector<ag2gs::Click> clicks = ag2gs::read_clicks((dir / "clicks.json").string());
    std::map<std::string, int> id_of;
    for (const auto& o : s.objs) id_of[o.category] = o.id;
    std::set<std::pair<std::string, std::string>> clicked;
    for (const auto& c : clicks) {
      ASSERT_TRUE(id_of.count(c.category)) << c.category;
      EXPECT_TRUE(clicked.insert({c.frame, c.category}).second) << "two clicks on " << c.category << " in " << c.frame;
      cv::Mat gt = read16(dir / "gt" / (c.frame + ".png"));
      int x = static_cast<int>(c.x), y = static_cast<int>(c.y);
      ASSERT_EQ(gt.at<uint16_t>(y, x), id_of[c.category]) << c.frame << " " << c.category;
    }
    for (const auto& cam : s.cams) {
      cv::Mat gt = read16(dir / "gt" / cam.name);
      for (const auto& o : s.objs) {
        bool should = cam.test && cv::countNonZero(gt == o.id) >= 6;
        EXPECT_EQ(clicked.count({stem(cam.name), o.category}) == 1, should) << cam.name << " " << o.category;
      }
    }
  }
}

TEST(Synth, ColmapProgramReadsTheModel) {
  if (std::system("command -v colmap > /dev/null 2>&1") != 0)
    GTEST_SKIP() << "colmap is not on PATH (scripts/install_deps.sh installs it)";
  const fs::path& dir = scene("small");
  fs::path out = temp_dir("colmap_txt");
  fs::create_directories(out);
  std::string cmd = "QT_QPA_PLATFORM=offscreen colmap model_converter --input_path " + (dir / "sparse" / "0").string() +
                    " --output_path " + out.string() + " --output_type TXT > " + (out / "log.txt").string() + " 2>&1";
  int rc = std::system(cmd.c_str());
  ASSERT_EQ(rc, 0) << read_bytes(out / "log.txt");
  ag2gs::ColmapModel a = ag2gs::read_colmap_model((dir / "sparse" / "0").string());
  ag2gs::ColmapModel b = ag2gs::read_colmap_model(out.string());
  ASSERT_EQ(a.cameras_for_images.size(), b.cameras_for_images.size());
  for (size_t i = 0; i < a.cameras_for_images.size(); ++i) {
    const auto &ca = a.cameras_for_images[i], &cb = b.cameras_for_images[i];
    EXPECT_EQ(ca.name, cb.name);
    EXPECT_NEAR(ca.fx, cb.fx, 1e-9);
    EXPECT_NEAR(ca.cx, cb.cx, 1e-9);
    EXPECT_LT((ca.R - cb.R).norm(), 1e-9);
    EXPECT_LT((ca.t - cb.t).norm(), 1e-9);
  }
  ASSERT_EQ(a.points.size(), b.points.size());
  for (size_t i = 0; i < a.points.size(); ++i) {
    EXPECT_LT((a.points[i] - b.points[i]).norm(), 1e-9);
    EXPECT_EQ(a.colors[i], b.colors[i]);
  }
}

TEST(Synth, TextModelAndRerunsReplaceOldFiles) {
  fs::path d = temp_dir("rerun");
  ag2gs::SynthOptions o = small_options(7);
  o.views = 10;
  ag2gs::write_synth_scene(d.string(), o);
  EXPECT_TRUE(fs::exists(d / "images" / "view_009.png"));
  EXPECT_TRUE(fs::exists(d / "sparse" / "0" / "points3D.bin"));
  o.views = 4;
  o.text_model = true;
  ag2gs::write_synth_scene(d.string(), o);
  EXPECT_FALSE(fs::exists(d / "images" / "view_009.png"));
  EXPECT_FALSE(fs::exists(d / "language_features" / "view_009_s.npy"));
  EXPECT_FALSE(fs::exists(d / "label" / "view_008.json"));
  EXPECT_FALSE(fs::exists(d / "sparse" / "0" / "points3D.bin"));
  EXPECT_TRUE(fs::exists(d / "sparse" / "0" / "points3D.txt"));
  ag2gs::ColmapModel m = ag2gs::read_colmap_model((d / "sparse" / "0").string());
  EXPECT_EQ(m.cameras_for_images.size(), 4u);
  EXPECT_EQ(m.points.size(), 600u);
  for (const auto& e : fs::recursive_directory_iterator(d))
    EXPECT_EQ(e.path().filename().string().find(".tmp."), std::string::npos) << e.path();
}

TEST(Synth, InvalidOptionsAreRejected) {
  fs::path d = temp_dir("invalid");
  auto expect_invalid = [&](ag2gs::SynthOptions o, const std::string& word) {
    try {
      ag2gs::write_synth_scene(d.string(), o);
      ADD_FAILURE() << "accepted options that should fail (" << word << ")";
    } catch (const std::invalid_argument& e) {
      EXPECT_NE(std::string(e.what()).find(word), std::string::npos) << e.what();
    }
  };
  ag2gs::SynthOptions o = small_options(1);
  o.views = 0;
  expect_invalid(o, "views");
  o = small_options(1, true);
  o.objects = 3;
  expect_invalid(o, "hard");
  o = small_options(1);
  o.mask_factor = 5;
  expect_invalid(o, "mask_factor");
  o = small_options(1);
  o.feature_dim = 16;
  expect_invalid(o, "feature_dim");
  o = small_options(1);
  o.width = 2;
  expect_invalid(o, "width");
  EXPECT_FALSE(fs::exists(d / "synth.json"));
}

// The committed samples are what the generator makes from the seed and options
// they record: rerun it and compare every file (PNGs by their pixels, so a
// different zlib does not matter).
TEST(Synth, CommittedSamplesAreReproducible) {
  for (const char* name : {"synth_small", "synth_hard"}) {
    fs::path sample =
        fs::path(std::getenv("AG2GS_SOURCE_DIR") ? std::getenv("AG2GS_SOURCE_DIR") : ".") / "data_samples" / name;
    if (!fs::exists(sample / "synth.json")) GTEST_SKIP() << sample << " is missing (set AG2GS_SOURCE_DIR)";
    Json j = read_json(sample / "synth.json");
    ag2gs::SynthOptions o;
    o.seed = j["seed"];
    const Json& opt = j["options"];
    o.width = opt["width"];
    o.height = opt["height"];
    o.views = opt["views"];
    o.objects = opt["objects"];
    o.feature_dim = opt["feature_dim"];
    o.samples = opt["samples"];
    o.points = opt["points"];
    o.mask_factor = opt["mask_factor"];
    o.hard = opt["hard"];
    o.text_model = opt["text_model"];
    o.backdrop = opt.value("backdrop", false);  // samples from before the backdrop have the sky
    o.wall_points = opt.value("wall_points", true);
    fs::path d = temp_dir(std::string("sample_") + name);
    ag2gs::write_synth_scene(d.string(), o);
    for (const auto& f : j["files"]) {
      std::string rel = f;
      if (fs::path(rel).extension() == ".png") {
        cv::Mat a = cv::imread((sample / rel).string(), cv::IMREAD_UNCHANGED);
        cv::Mat b = cv::imread((d / rel).string(), cv::IMREAD_UNCHANGED);
        ASSERT_FALSE(a.empty()) << rel;
        ASSERT_TRUE(a.size() == b.size() && a.type() == b.type()) << rel;
        EXPECT_EQ(cv::norm(a, b, cv::NORM_INF), 0.0) << name << "/" << rel << " differs from a fresh run";
      } else {
        EXPECT_TRUE(read_bytes(sample / rel) == read_bytes(d / rel))
            << name << "/" << rel << " differs from a fresh run";
      }
    }
  }
}

struct CliResult {
  int code = -1;
  std::string output;
};

CliResult run_cli(const std::string& args) {
  const char* bin = std::getenv("AG2GS_BINARY");
  std::string cmd = std::string(bin ? bin : "./ag2gs") + " " + args + " 2>&1";
  CliResult r;
  FILE* p = popen(cmd.c_str(), "r");
  if (!p) return r;
  char buf[4096];
  while (fgets(buf, sizeof buf, p)) r.output += buf;
  int status = pclose(p);
  r.code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  return r;
}

TEST(Synth, CliWritesASceneAndReportsErrors) {
  const char* bin = std::getenv("AG2GS_BINARY");
  if (!fs::exists(bin ? bin : "./ag2gs")) GTEST_SKIP() << "the ag2gs program is not built (AG2GS_BINARY)";
  fs::path d = temp_dir("cli");
  CliResult r = run_cli("synth " + d.string() + " --width 32 --height 24 --views 3 --points 50 --seed 9");
  ASSERT_EQ(r.code, 0) << r.output;
  EXPECT_NE(r.output.find("objects: 5"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("points: 50"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("view 3/3"), std::string::npos) << r.output;
  EXPECT_TRUE(fs::exists(d / "images" / "view_002.png"));
  EXPECT_EQ(read_json(d / "synth.json")["seed"].get<uint64_t>(), 9u);
  r = run_cli("synth " + d.string() + " --hard --objects 3 --force");
  EXPECT_EQ(r.code, 1) << r.output;
  EXPECT_NE(r.output.find("ag2gs synth: error: hard mode needs at least 5 objects"), std::string::npos) << r.output;
}

}  // namespace
