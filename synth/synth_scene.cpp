// The synthetic scene generator: a double-precision CPU ray tracer of textured
// primitives on a bounded ground disc, plus the exact ground truth every later
// stage is measured against. Interface and output layout: synth/synth_scene.h.
//
// World frame: z up, the ground is the disc z = 0, |xy| <= kGroundRadius; the
// objects stand on it inside kPlaceRadius. Cameras sit on a ring outside the
// disc and look at kTarget (COLMAP convention, host/core/gaussians.h). With the
// backdrop (the default) everything is enclosed by a textured cylinder of
// radius kBackdropRadius: its wall up to kBackdropHeight, a floor ring from
// the ground disc out to the wall and a ceiling at kBackdropHeight, so every
// ray from inside meets textured, finite geometry (GT id 0, no masks).
//
// Randomness: every number is splitmix64 of (seed, stream, indices), so a
// value depends only on what it is for, never on the order things ran in.
// The CLIP-like "model" (category and text vectors) does not depend on the
// seed at all: a phrase has the same embedding in every synthetic scene, as
// a real text encoder would give; mask features add per-view noise that does.
#include "synth/synth_scene.h"

#include <spdlog/spdlog.h>
#include <unistd.h>

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <algorithm>
#include <array>
#include <cctype>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <limits>
#include <map>
#include <nlohmann/json.hpp>
#include <opencv2/imgproc.hpp>
#include <set>
#include <stdexcept>
#include <string>
#include <tuple>
#include <vector>

#include "host/core/counter_rng.h"
#include "host/io/colmap_writer.h"
#include "host/io/image_io.h"
#include "host/io/npy_io.h"

namespace ag2gs {

namespace {

namespace fs = std::filesystem;
using Vec3 = Eigen::Vector3d;
using Json = nlohmann::ordered_json;

constexpr double kPi = 3.14159265358979323846;
constexpr double kInf = std::numeric_limits<double>::infinity();

// ------------------------------------------------------------------ scene constants
constexpr double kGroundRadius = 3.0;  // the ground disc; beyond it the backdrop's floor ring (or the sky)
// The backdrop: wall beyond the camera ring (<= 3.8), tall enough that the
// ring's cameras (z <= 1.75, looking 17-21 degrees down; their highest ray,
// a top corner, rises ~4 degrees, so it meets the far wall below z ~2.4)
// never see the ceiling; the ceiling closes the cylinder all the same.
constexpr double kBackdropRadius = 5.5;
constexpr double kBackdropHeight = 4.0;
constexpr double kPlaceRadius = 1.5;   // object footprints stay inside this radius
constexpr double kPlaceMargin = 0.06;  // minimum gap between footprints (except touching pairs)
constexpr double kRingRadius = 3.7;    // camera ring (+- kRingJitter)
constexpr double kRingJitter = 0.1;
constexpr double kCameraHeight = 1.45;  // + [0, kCameraHeightJitter)
constexpr double kCameraHeightJitter = 0.3;
constexpr double kFovX = 55.0 * kPi / 180.0;
const Vec3 kTarget(0.0, 0.0, 0.3);
constexpr double kAmbient = 0.35;
constexpr double kShadowOffset = 1e-7;  // along the normal, against self-shadowing
constexpr double kTMin = 1e-9;

// Masks and labels.
constexpr int kLevels = 4;                // default, small, medium, large
constexpr double kMaskDropRate = 0.05;    // a SAM mask goes missing this often
constexpr double kMaskJitterPx = 1.5;     // boundary displacement amplitude (mask pixels)
constexpr double kMaskJitterScale = 5.0;  // correlation length of the displacement (mask pixels)
constexpr int kMinMaskPixels = 4;         // SAM does not return smaller masks
constexpr int kMinLabelPixels = 6;        // label polygons / clicks need this many GT pixels

// Feature construction: category = wG global + wF family + wC colour + wS
// specific over orthonormal atoms, so the cosine of two categories is the sum
// of the squared weights they share: same family 0.77, same colour 0.25,
// nothing shared 0.15 (wG^2 + wF^2 + wC^2 + wS^2 = 1).
constexpr double kWGlobal2 = 0.15, kWFamily2 = 0.62, kWColour2 = 0.10, kWSpecific2 = 0.13;
constexpr double kTextNoise = 0.15;    // |noise| / |category| of a text embedding
constexpr double kMaskNoise = 0.30;    // of an object-level mask feature
constexpr double kPartNoise = 0.25;    // of a part-level mask feature
constexpr double kPartCategory = 0.8;  // part feature = 0.8 category + 0.45 part + noise
constexpr double kPartOwn = 0.45;
constexpr uint64_t kModelKey = 0x636c69702d6c696bull;  // fixed key of the CLIP-like "model"

// ------------------------------------------------------------------ counter-based random numbers

enum Stream : uint64_t {
  kStreamCamera = 1,
  kStreamLayout,
  kStreamTexture,
  kStreamLight,
  kStreamPoints,
  kStreamJitter,
  kStreamDrop,
  kStreamMaskNoise,
  kStreamPartVec,
  kStreamTextNoise,
  kStreamAtom,
  kStreamDistractor,
  kStreamBackground,
};

struct Rng {
  uint64_t seed;
  uint64_t bits(uint64_t stream, uint64_t a, uint64_t b = 0, uint64_t c = 0, uint64_t d = 0) const {
    uint64_t h = splitmix64(seed ^ 0x5851f42d4c957f2dull);
    h = splitmix64(h ^ stream);
    h = splitmix64(h ^ a);
    h = splitmix64(h ^ b);
    h = splitmix64(h ^ c);
    return splitmix64(h ^ d);
  }
  // Uniform in [0, 1).
  double uniform(uint64_t stream, uint64_t a, uint64_t b = 0, uint64_t c = 0, uint64_t d = 0) const {
    return static_cast<double>(bits(stream, a, b, c, d) >> 11) * 0x1.0p-53;
  }
  double uniform(double lo, double hi, uint64_t stream, uint64_t a, uint64_t b = 0, uint64_t c = 0) const {
    return lo + (hi - lo) * uniform(stream, a, b, c);
  }
  // Standard normal (Box-Muller over two counters).
  double normal(uint64_t stream, uint64_t a, uint64_t b, uint64_t c) const {
    double u1 = 1.0 - uniform(stream, a, b, 2 * c);  // (0, 1]
    double u2 = uniform(stream, a, b, 2 * c + 1);
    return std::sqrt(-2.0 * std::log(u1)) * std::cos(2.0 * kPi * u2);
  }
};

uint64_t hash_string(const std::string& s) {
  uint64_t h = 1469598103934665603ull;  // FNV-1a
  for (unsigned char c : s) {
    h ^= c;
    h *= 1099511628211ull;
  }
  return splitmix64(h);
}

// Value noise in [0, 1] on the integer lattice, smoothstep-interpolated.
double lattice(uint64_t key, int64_t x, int64_t y, int64_t z) {
  uint64_t packed = (static_cast<uint64_t>(x) & 0x1fffff) | ((static_cast<uint64_t>(y) & 0x1fffff) << 21) |
                    ((static_cast<uint64_t>(z) & 0x1fffff) << 42);
  return static_cast<double>(splitmix64(key ^ splitmix64(packed)) >> 11) * 0x1.0p-53;
}

double value_noise(uint64_t key, const Vec3& p) {
  double fx = std::floor(p.x()), fy = std::floor(p.y()), fz = std::floor(p.z());
  auto ix = static_cast<int64_t>(fx), iy = static_cast<int64_t>(fy), iz = static_cast<int64_t>(fz);
  auto smooth = [](double t) { return t * t * (3.0 - 2.0 * t); };
  double sx = smooth(p.x() - fx), sy = smooth(p.y() - fy), sz = smooth(p.z() - fz);
  double v[2][2][2];
  for (int a = 0; a < 2; ++a)
    for (int b = 0; b < 2; ++b)
      for (int c = 0; c < 2; ++c) v[a][b][c] = lattice(key, ix + a, iy + b, iz + c);
  auto lerp = [](double a, double b, double t) { return a + (b - a) * t; };
  double x00 = lerp(v[0][0][0], v[1][0][0], sx), x10 = lerp(v[0][1][0], v[1][1][0], sx);
  double x01 = lerp(v[0][0][1], v[1][0][1], sx), x11 = lerp(v[0][1][1], v[1][1][1], sx);
  return lerp(lerp(x00, x10, sy), lerp(x01, x11, sy), sz);
}

// Three octaves of value noise, in [0, 1].
double fbm(uint64_t key, const Vec3& p) {
  double sum = 0, amp = 1, norm = 0, freq = 1;
  for (int o = 0; o < 3; ++o) {
    sum += amp * value_noise(splitmix64(key + static_cast<uint64_t>(o)), p * freq);
    norm += amp;
    amp *= 0.5;
    freq *= 2.0;
  }
  return sum / norm;
}

double smoothstep(double a, double b, double x) {
  double t = std::clamp((x - a) / (b - a), 0.0, 1.0);
  return t * t * (3.0 - 2.0 * t);
}

// ------------------------------------------------------------------ vocabulary of the scenes
enum class Primitive { kSphere, kBox, kCylinder };
const char* primitive_name(Primitive p) {
  switch (p) {
    case Primitive::kSphere:
      return "sphere";
    case Primitive::kBox:
      return "box";
    case Primitive::kCylinder:
      return "cylinder";
  }
  return "?";
}

enum class Pattern { kStripes, kChecks, kNoise, kWood };
const char* pattern_name(Pattern p) {
  switch (p) {
    case Pattern::kStripes:
      return "stripes";
    case Pattern::kChecks:
      return "checks";
    case Pattern::kNoise:
      return "noise";
    case Pattern::kWood:
      return "wood";
  }
  return "?";
}

struct ColourName {
  const char* name;
  double r, g, b;
  const char* parent;  // a colour whose vector this one shares most of ("dark red" -> "red")
};
// The first kSceneColours are used in ordinary scenes; the rest by hard mode.
constexpr ColourName kColours[] = {
    {"red", 0.80, 0.13, 0.11, nullptr},    {"blue", 0.13, 0.30, 0.82, nullptr},   {"green", 0.16, 0.60, 0.20, nullptr},
    {"yellow", 0.92, 0.80, 0.15, nullptr}, {"orange", 0.93, 0.47, 0.10, nullptr}, {"purple", 0.50, 0.20, 0.68, nullptr},
    {"pink", 0.94, 0.52, 0.66, nullptr},   {"cyan", 0.12, 0.68, 0.76, nullptr},   {"white", 0.90, 0.90, 0.87, nullptr},
    {"black", 0.12, 0.12, 0.13, nullptr},  {"dark red", 0.64, 0.10, 0.10, "red"}, {"wooden", 0.55, 0.36, 0.19, nullptr},
};
constexpr int kNumColours = sizeof(kColours) / sizeof(kColours[0]);
constexpr int kSceneColours = 10;
int colour_index(const std::string& name) {
  for (int i = 0; i < kNumColours; ++i)
    if (name == kColours[i].name) return i;
  throw std::logic_error("unknown colour " + name);
}

struct Family {
  const char* name;
  Primitive primitive;
};
// The first kSceneFamilies appear in ordinary scenes; "pole" is hard mode's thin object.
constexpr Family kFamilies[] = {
    {"mug", Primitive::kCylinder}, {"ball", Primitive::kSphere},   {"box", Primitive::kBox},
    {"can", Primitive::kCylinder}, {"pole", Primitive::kCylinder},
};
constexpr int kNumFamilies = sizeof(kFamilies) / sizeof(kFamilies[0]);
constexpr int kSceneFamilies = 4;
// Phrases never placed in a scene: text-query distractors unrelated to every object.
constexpr const char* kUnrelatedPhrases[] = {"potted plant", "sneaker", "laptop"};

// ------------------------------------------------------------------ the CLIP-like embedding model
using Feature = std::vector<double>;

void normalise(Feature& v) {
  double n = 0;
  for (double x : v) n += x * x;
  n = std::sqrt(n);
  if (n > 0)
    for (double& x : v) x /= n;
}

double dot(const Feature& a, const Feature& b) {
  double s = 0;
  for (size_t i = 0; i < a.size(); ++i) s += a[i] * b[i];
  return s;
}

// Orthonormal atoms ("global", families, colours, category-specific
// directions), Gram-Schmidt over hashed Gaussian vectors in a fixed order.
class EmbeddingModel {
 public:
  explicit EmbeddingModel(int dim) : dim_(dim) {
    std::vector<std::string> names{"global"};
    for (const auto& f : kFamilies) names.push_back(std::string("family:") + f.name);
    for (const char* p : kUnrelatedPhrases) names.push_back(std::string("family:") + p);
    for (const auto& c : kColours) names.push_back(std::string("colour:") + c.name);
    for (const auto& c : kColours)
      for (const auto& f : kFamilies) names.push_back(std::string("category:") + c.name + " " + f.name);
    for (const char* p : kUnrelatedPhrases) names.push_back(std::string("category:") + p);
    if (static_cast<int>(names.size()) > dim)
      throw std::invalid_argument("feature_dim must be at least " + std::to_string(names.size()) +
                                  " (the CLIP-like model needs that many orthogonal directions)");
    Rng rng{kModelKey};
    for (const auto& name : names) {
      Feature v(dim);
      uint64_t key = hash_string(name);
      for (int i = 0; i < dim; ++i) v[i] = rng.normal(kStreamAtom, key, 0, static_cast<uint64_t>(i));
      for (const auto& [other, u] : atoms_) {
        double d = dot(v, u);
        for (int i = 0; i < dim; ++i) v[i] -= d * u[i];
      }
      normalise(v);
      atoms_[name] = v;
    }
  }

  int dim() const { return dim_; }

  const Feature& atom(const std::string& name) const { return atoms_.at(name); }

  // The colour direction; a colour with a parent shares 0.8 of its parent's.
  Feature colour(const std::string& name) const {
    const ColourName& c = kColours[colour_index(name)];
    Feature v = atom("colour:" + name);
    if (c.parent) {
      const Feature& p = atom(std::string("colour:") + c.parent);
      for (int i = 0; i < dim_; ++i) v[i] = 0.8 * p[i] + 0.6 * v[i];
    }
    return v;
  }

  // Unit category vector of "colour family" or of an unrelated phrase.
  Feature category(const std::string& colour, const std::string& family) const {
    Feature v(dim_, 0.0);
    auto add = [&](const Feature& a, double w2) {
      double w = std::sqrt(w2);
      for (int i = 0; i < dim_; ++i) v[i] += w * a[i];
    };
    add(atom("global"), kWGlobal2);
    if (colour.empty()) {  // an unrelated phrase: its own family, no colour
      add(atom("family:" + family), kWFamily2 + kWColour2);
      add(atom("category:" + family), kWSpecific2);
    } else {
      add(atom("family:" + family), kWFamily2);
      add(this->colour(colour), kWColour2);
      add(atom("category:" + colour + " " + family), kWSpecific2);
    }
    normalise(v);
    return v;
  }

 private:
  int dim_;
  std::map<std::string, Feature> atoms_;
};

// normalise(base + noise), |noise| ~ amplitude (Gaussian, per-component sd amplitude / sqrt(D)).
Feature noisy(const Feature& base, double amplitude, const Rng& rng, uint64_t stream, uint64_t a, uint64_t b,
              uint64_t c) {
  Feature v = base;
  double sd = amplitude / std::sqrt(static_cast<double>(v.size()));
  for (size_t i = 0; i < v.size(); ++i) v[i] += sd * rng.normal(stream, a, b, (c << 16) ^ static_cast<uint64_t>(i));
  normalise(v);
  return v;
}

// ------------------------------------------------------------------ geometry
struct Object {
  int id = 0;  // 1..K, the value in gt/
  std::string category, family, colour_name;
  Primitive primitive = Primitive::kSphere;
  Vec3 centre = Vec3::Zero();  // geometric centre; z = half height (it stands on z = 0)
  Vec3 half = Vec3::Zero();    // half extents in the object frame (sphere r,r,r; cylinder r,r,h/2)
  double yaw = 0;              // rotation about +z of the object frame
  double cos_yaw = 1, sin_yaw = 0;
  Vec3 colour = Vec3::Zero();  // base albedo
  Pattern pattern = Pattern::kNoise;
  double pattern_param = 0;  // stripes: bands over the height; checks: cell size (m)
  uint64_t texture_key = 0;
  bool removed = false;  // left out of every ray (the removal ground truth)

  void set_yaw(double y) {
    yaw = y;
    cos_yaw = std::cos(y);
    sin_yaw = std::sin(y);
  }
  // Radius of the circle containing the footprint on the ground.
  double footprint() const { return primitive == Primitive::kBox ? std::hypot(half.x(), half.y()) : half.x(); }
  Vec3 to_local(const Vec3& p) const { return dir_to_local(p - centre); }
  Vec3 dir_to_local(const Vec3& d) const {
    return {cos_yaw * d.x() + sin_yaw * d.y(), -sin_yaw * d.x() + cos_yaw * d.y(), d.z()};
  }
  Vec3 dir_to_world(const Vec3& d) const {
    return {cos_yaw * d.x() - sin_yaw * d.y(), sin_yaw * d.x() + cos_yaw * d.y(), d.z()};
  }
};

struct Ray {
  Vec3 o, d;  // d unit
};

// The surfaces of object 0.
enum Surface { kSurfaceGround = 0, kSurfaceFloor, kSurfaceWall, kSurfaceCeiling };

struct Hit {
  double t = kInf;
  int object = -1;  // -1 sky, 0 ground or backdrop, 1..K objects
  // box: 0..5 = +x,-x,+y,-y,+z,-z; cylinder: 0 side, 1 top, 2 bottom; sphere 0;
  // object 0: a Surface (ground disc, backdrop floor ring, wall, ceiling)
  int face = 0;
  Vec3 local = Vec3::Zero();   // hit point in the object frame
  Vec3 normal = Vec3::Zero();  // world, unit, facing the ray
};

// Nearest intersection with `o` at t in (tmin, tmax); fills t, face, local
// point and local normal. Rays start outside every object in our use, but the
// far roots are handled too.
bool intersect(const Object& obj, const Ray& ray, double tmin, double tmax, double& t_out, int& face, Vec3& lp,
               Vec3& ln) {
  Vec3 o = obj.to_local(ray.o), d = obj.dir_to_local(ray.d);
  double best = tmax;
  bool found = false;
  switch (obj.primitive) {
    case Primitive::kSphere: {
      double r = obj.half.x();
      double b = o.dot(d), c = o.squaredNorm() - r * r, disc = b * b - c;
      if (disc < 0) return false;
      double sq = std::sqrt(disc);
      for (double t : {-b - sq, -b + sq})
        if (t > tmin && t < best) {
          best = t;
          found = true;
          face = 0;
          break;
        }
      if (found) {
        lp = o + best * d;
        ln = lp / r;
      }
      break;
    }
    case Primitive::kBox: {
      double tnear = -kInf, tfar = kInf;
      int near_axis = -1, far_axis = -1;
      bool near_neg = false, far_neg = false;
      for (int a = 0; a < 3; ++a) {
        double h = obj.half[a];
        if (d[a] == 0.0) {
          if (o[a] < -h || o[a] > h) return false;
          continue;
        }
        double t1 = (-h - o[a]) / d[a], t2 = (h - o[a]) / d[a];
        // Entering through the face whose outward normal opposes d.
        bool enter_neg = d[a] > 0;  // entering the -h face when moving +
        if (t1 > t2) std::swap(t1, t2);
        if (t1 > tnear) {
          tnear = t1;
          near_axis = a;
          near_neg = enter_neg;
        }
        if (t2 < tfar) {
          tfar = t2;
          far_axis = a;
          far_neg = !enter_neg;
        }
      }
      if (tnear > tfar) return false;
      int axis = -1;
      bool neg = false;
      if (tnear > tmin && tnear < best) {
        best = tnear;
        axis = near_axis;
        neg = near_neg;
      } else if (tfar > tmin && tfar < best) {
        best = tfar;
        axis = far_axis;
        neg = far_neg;
      }
      if (axis < 0) return false;
      found = true;
      face = 2 * axis + (neg ? 1 : 0);
      lp = o + best * d;
      ln = Vec3::Zero();
      ln[axis] = neg ? -1.0 : 1.0;
      break;
    }
    case Primitive::kCylinder: {
      double r = obj.half.x(), hz = obj.half.z();
      double a = d.x() * d.x() + d.y() * d.y();
      if (a > 0) {
        double b = o.x() * d.x() + o.y() * d.y(), c = o.x() * o.x() + o.y() * o.y() - r * r;
        double disc = b * b - a * c;
        if (disc >= 0) {
          double sq = std::sqrt(disc);
          for (double t : {(-b - sq) / a, (-b + sq) / a}) {
            double z = o.z() + t * d.z();
            if (t > tmin && t < best && z >= -hz && z <= hz) {
              best = t;
              found = true;
              face = 0;
              lp = o + t * d;
              ln = Vec3(lp.x() / r, lp.y() / r, 0.0);
              break;
            }
          }
        }
      }
      if (d.z() != 0.0) {
        for (int cap = 0; cap < 2; ++cap) {
          double z = cap == 0 ? hz : -hz;
          double t = (z - o.z()) / d.z();
          if (!(t > tmin && t < best)) continue;
          double x = o.x() + t * d.x(), y = o.y() + t * d.y();
          if (x * x + y * y > r * r) continue;
          best = t;
          found = true;
          face = cap == 0 ? 1 : 2;
          lp = Vec3(x, y, z);
          ln = Vec3(0, 0, cap == 0 ? 1.0 : -1.0);
        }
      }
      break;
    }
  }
  if (found) t_out = best;
  return found;
}

struct Light {
  Vec3 direction;  // towards the light, unit
};

struct Scene {
  std::vector<Object> objects;  // objects[k].id == k + 1
  Light light;
  uint64_t ground_key = 0;
  bool backdrop = false;
  uint64_t backdrop_key = 0;

  // Nearest hit along the ray. When `all_t` is given it receives, per object,
  // the nearest t at which the ray meets it (kInf when never): occlusion stats.
  Hit trace(const Ray& ray, std::vector<double>* all_t = nullptr) const {
    Hit h;
    if (all_t) all_t->assign(objects.size(), kInf);
    auto set = [&](double t, int surface, const Vec3& normal) {
      h.t = t;
      h.object = 0;
      h.face = surface;
      h.local = ray.o + t * ray.d;
      h.normal = normal;
    };
    // Ground disc (and the backdrop's floor ring out to the wall), seen from above only.
    const double floor_radius = backdrop ? kBackdropRadius : kGroundRadius;
    if (ray.d.z() < 0 && ray.o.z() > 0) {
      double t = -ray.o.z() / ray.d.z();
      Vec3 p = ray.o + t * ray.d;
      double r2 = p.x() * p.x() + p.y() * p.y();
      if (t > kTMin && r2 <= floor_radius * floor_radius)
        set(t, r2 <= kGroundRadius * kGroundRadius ? kSurfaceGround : kSurfaceFloor, Vec3(0, 0, 1));
    }
    if (backdrop) {
      // Ceiling disc, seen from below.
      if (ray.d.z() > 0 && ray.o.z() < kBackdropHeight) {
        double t = (kBackdropHeight - ray.o.z()) / ray.d.z();
        Vec3 p = ray.o + t * ray.d;
        if (t > kTMin && t < h.t && p.x() * p.x() + p.y() * p.y() <= kBackdropRadius * kBackdropRadius)
          set(t, kSurfaceCeiling, Vec3(0, 0, -1));
      }
      // Wall: |o_xy + t d_xy| = R with 0 <= z <= height, nearest root.
      double a = ray.d.x() * ray.d.x() + ray.d.y() * ray.d.y();
      if (a > 0) {
        double b = ray.o.x() * ray.d.x() + ray.o.y() * ray.d.y();
        double c = ray.o.x() * ray.o.x() + ray.o.y() * ray.o.y() - kBackdropRadius * kBackdropRadius;
        double disc = b * b - a * c;
        if (disc >= 0) {
          double sq = std::sqrt(disc);
          for (double t : {(-b - sq) / a, (-b + sq) / a}) {
            double z = ray.o.z() + t * ray.d.z();
            if (t > kTMin && t < h.t && z >= 0 && z <= kBackdropHeight) {
              Vec3 p = ray.o + t * ray.d;
              set(t, kSurfaceWall, Vec3(-p.x(), -p.y(), 0).normalized());
              break;
            }
          }
        }
      }
    }
    for (size_t k = 0; k < objects.size(); ++k) {
      if (objects[k].removed) continue;
      double t;
      int face;
      Vec3 lp, ln;
      double tmax = all_t ? kInf : h.t;
      if (!intersect(objects[k], ray, kTMin, tmax, t, face, lp, ln)) continue;
      if (all_t) (*all_t)[k] = t;
      if (t < h.t) {
        h.t = t;
        h.object = objects[k].id;
        h.face = face;
        h.local = lp;
        h.normal = objects[k].dir_to_world(ln);
      }
    }
    if (h.object >= 0 && h.normal.dot(ray.d) > 0) h.normal = -h.normal;
    return h;
  }

  bool shadowed(const Vec3& p, const Vec3& n) const {
    Ray r{p + kShadowOffset * n, light.direction};
    for (const auto& obj : objects) {
      if (obj.removed) continue;
      double t;
      int face;
      Vec3 lp, ln;
      if (intersect(obj, r, kTMin, kInf, t, face, lp, ln)) return true;
    }
    return false;
  }
};

Vec3 sky(const Vec3& d) {
  const Vec3 haze(0.74, 0.76, 0.78), horizon(0.86, 0.89, 0.93), zenith(0.38, 0.57, 0.86);
  if (d.z() < 0) return horizon + (haze - horizon) * smoothstep(0.0, 0.35, -d.z());
  return horizon + (zenith - horizon) * smoothstep(0.0, 0.7, d.z());
}

// The backdrop's textures: layered value noise over the world point (no
// seams, no repeats), several colours, sharp-edged blobs and fine grain, so
// every patch looks different (good for SIFT matching and for SfM).
Vec3 lerp3(const Vec3& a, const Vec3& b, double t) {
  return a + (b - a) * t;
}

Vec3 wall_albedo(const Scene& scene, const Vec3& p) {
  const uint64_t k = scene.backdrop_key;
  const Vec3 terracotta(0.66, 0.40, 0.30), sage(0.46, 0.57, 0.44), slate(0.36, 0.44, 0.60), sand(0.80, 0.72, 0.55);
  Vec3 warp(fbm(splitmix64(k + 1), p * 0.7), fbm(splitmix64(k + 2), p * 0.7), 0.0);
  Vec3 q = p + 1.5 * warp;
  Vec3 a = lerp3(terracotta, sand, smoothstep(0.35, 0.65, fbm(splitmix64(k + 3), q * 0.9)));
  Vec3 b = lerp3(slate, sage, smoothstep(0.35, 0.65, fbm(splitmix64(k + 4), q * 1.1)));
  Vec3 c = lerp3(a, b, smoothstep(0.42, 0.58, fbm(splitmix64(k + 5), p * 0.6)));
  // Irregular horizontal bands and dark and light blobs with sharp edges.
  double band = std::sin(p.z() * 5.0 + 4.0 * fbm(splitmix64(k + 6), p * 0.8));
  c *= 0.88 + 0.12 * band;
  double blobs = value_noise(splitmix64(k + 7), p * 2.6);
  c *= 1.0 - 0.5 * smoothstep(0.70, 0.74, blobs);
  double spots = value_noise(splitmix64(k + 8), p * 3.7 + Vec3(0.3, 0.7, 0.1));
  c = lerp3(c, Vec3(0.92, 0.90, 0.84), 0.7 * smoothstep(0.76, 0.80, spots));
  double fine = value_noise(splitmix64(k + 9), p * 7.0);
  return (c * (0.88 + 0.24 * fine)).cwiseMin(1.0);
}

Vec3 floor_albedo(const Scene& scene, const Vec3& p) {
  const uint64_t k = splitmix64(scene.backdrop_key + 100);
  const Vec3 soil(0.45, 0.37, 0.27), moss(0.36, 0.45, 0.26), stone(0.58, 0.57, 0.54);
  Vec3 flat(p.x(), p.y(), 0.0);
  Vec3 c = lerp3(soil, moss, smoothstep(0.38, 0.62, fbm(splitmix64(k + 1), flat * 1.2)));
  double pebbles = value_noise(splitmix64(k + 2), flat * 3.5);
  c = lerp3(c, stone, smoothstep(0.68, 0.72, pebbles));
  double fine = value_noise(splitmix64(k + 3), flat * 8.0 + Vec3(0, 0, 0.5));
  return (c * (0.85 + 0.3 * fine)).cwiseMin(1.0);
}

Vec3 ceiling_albedo(const Scene& scene, const Vec3& p) {
  const uint64_t k = splitmix64(scene.backdrop_key + 200);
  Vec3 flat(p.x(), p.y(), 0.0);
  Vec3 c = lerp3(Vec3(0.85, 0.83, 0.78), Vec3(0.62, 0.66, 0.72), smoothstep(0.4, 0.6, fbm(k, flat * 0.8)));
  c *= 1.0 - 0.4 * smoothstep(0.68, 0.72, value_noise(splitmix64(k + 1), flat * 2.2));
  return (c * (0.88 + 0.24 * value_noise(splitmix64(k + 2), flat * 6.0))).cwiseMin(1.0);
}

Vec3 ground_albedo(const Scene& scene, const Vec3& p) {
  const double cell = 0.5;
  int parity = static_cast<int>(std::floor(p.x() / cell) + std::floor(p.y() / cell)) & 1;
  Vec3 a = parity ? Vec3(0.64, 0.61, 0.56) : Vec3(0.48, 0.46, 0.43);
  double n = fbm(scene.ground_key, Vec3(p.x() * 2.5, p.y() * 2.5, 0.0));
  double fine = value_noise(splitmix64(scene.ground_key + 17), Vec3(p.x() * 14.0, p.y() * 14.0, 0.5));
  return a * (0.78 + 0.3 * n + 0.12 * fine);
}

// The second tone of an object's pattern: darker for light colours, lighter for dark ones.
Vec3 variant_colour(const Vec3& c) {
  double luma = 0.3 * c.x() + 0.59 * c.y() + 0.11 * c.z();
  if (luma > 0.45) return c * 0.58;
  return (c * 1.7 + Vec3::Constant(0.1)).cwiseMin(1.0);
}

Vec3 object_albedo(const Object& obj, const Vec3& q) {
  Vec3 a = obj.colour, b = variant_colour(obj.colour);
  double mix = 0;  // 0 = base, 1 = variant
  switch (obj.pattern) {
    case Pattern::kStripes: {
      double band = std::floor((q.z() + obj.half.z()) / (2.0 * obj.half.z()) * obj.pattern_param);
      mix = static_cast<int64_t>(band) & 1 ? 1.0 : 0.0;
      break;
    }
    case Pattern::kChecks: {
      double c = obj.pattern_param;
      auto s = static_cast<int64_t>(std::floor(q.x() / c) + std::floor(q.y() / c) + std::floor(q.z() / c));
      mix = s & 1 ? 1.0 : 0.0;
      break;
    }
    case Pattern::kNoise:
      mix = smoothstep(0.42, 0.58, fbm(obj.texture_key, q * 7.0));
      break;
    case Pattern::kWood: {
      double g = q.z() * 6.0 + 0.9 * fbm(obj.texture_key, Vec3(q.x() * 8.0, q.y() * 8.0, q.z() * 2.0));
      double f = g - std::floor(g);
      mix = smoothstep(0.35, 0.5, f) * (1.0 - smoothstep(0.75, 0.9, f));
      break;
    }
  }
  Vec3 c = a + (b - a) * mix;
  double fine = value_noise(splitmix64(obj.texture_key + 5), q * 18.0);
  return (c * (0.9 + 0.2 * fine)).cwiseMin(1.0);
}

Vec3 radiance(const Scene& scene, const Ray& ray, const Hit& h) {
  if (h.object < 0) return sky(ray.d);
  Vec3 p = ray.o + h.t * ray.d;
  Vec3 albedo;
  if (h.object > 0) {
    albedo = object_albedo(scene.objects[h.object - 1], h.local);
  } else {
    switch (h.face) {
      case kSurfaceFloor:
        albedo = floor_albedo(scene, p);
        break;
      case kSurfaceWall:
        albedo = wall_albedo(scene, p);
        break;
      case kSurfaceCeiling:
        albedo = ceiling_albedo(scene, p);
        break;
      default:
        albedo = ground_albedo(scene, p);
    }
  }
  double ndl = std::max(0.0, h.normal.dot(scene.light.direction));
  if (ndl > 0 && scene.shadowed(p, h.normal)) ndl = 0;
  return (albedo * (kAmbient + (1.0 - kAmbient) * ndl)).cwiseMin(1.0);
}

// The ray through image point (u, v) (pixel units, COLMAP convention).
Ray camera_ray(const Camera& cam, double u, double v) {
  Vec3 dc((u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, 1.0);
  return {cam.center(), (cam.R.transpose() * dc).normalized()};
}

// ------------------------------------------------------------------ cameras and layout
std::string view_stem(int i) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "view_%03d", i);
  return buf;
}

bool is_test_view(int i) {
  return i % 8 == 0;
}

std::vector<Camera> make_cameras(const SynthOptions& opt, const Rng& rng) {
  std::vector<Camera> cams;
  double phase = 2.0 * kPi * rng.uniform(kStreamCamera, 0);
  for (int i = 0; i < opt.views; ++i) {
    double theta = phase + 2.0 * kPi * i / opt.views;
    double radius = kRingRadius + kRingJitter * (2.0 * rng.uniform(kStreamCamera, 1, i) - 1.0);
    double height = kCameraHeight + kCameraHeightJitter * rng.uniform(kStreamCamera, 2, i);
    Vec3 c(radius * std::cos(theta), radius * std::sin(theta), height);
    Vec3 fwd = (kTarget - c).normalized();
    Vec3 right = fwd.cross(Vec3(0, 0, 1)).normalized();
    Vec3 down = fwd.cross(right);
    Camera cam;
    cam.width = opt.width;
    cam.height = opt.height;
    cam.fx = cam.fy = 0.5 * opt.width / std::tan(0.5 * kFovX);
    cam.cx = 0.5 * opt.width;
    cam.cy = 0.5 * opt.height;
    cam.R.row(0) = right.transpose();
    cam.R.row(1) = down.transpose();
    cam.R.row(2) = fwd.transpose();
    cam.t = -cam.R * c;
    cam.name = view_stem(i) + ".png";
    cams.push_back(cam);
  }
  return cams;
}

// An object of `family` in `colour` with a size drawn from the family's ranges
// (times `scale`), a pattern and a yaw; position left at the origin.
Object make_object(const Rng& rng, int id, int family, int colour, double scale, uint64_t attempt) {
  Object o;
  o.id = id;
  o.family = kFamilies[family].name;
  o.colour_name = kColours[colour].name;
  o.category = o.colour_name + " " + o.family;
  o.primitive = kFamilies[family].primitive;
  o.colour = Vec3(kColours[colour].r, kColours[colour].g, kColours[colour].b);
  auto u = [&](double lo, double hi, uint64_t what) { return rng.uniform(lo, hi, kStreamLayout, id, attempt, what); };
  std::string f = o.family;
  std::array<Pattern, 3> patterns{};
  size_t n_patterns = 0;
  if (f == "mug") {
    double r = u(0.20, 0.27, 1) * scale;
    o.half = Vec3(r, r, 0.5 * u(0.28, 0.42, 2) * scale);
    patterns = {Pattern::kStripes, Pattern::kChecks};
    n_patterns = 2;
  } else if (f == "can") {
    double r = u(0.11, 0.15, 1) * scale;
    o.half = Vec3(r, r, 0.5 * u(0.42, 0.62, 2) * scale);
    patterns = {Pattern::kStripes, Pattern::kNoise};
    n_patterns = 2;
  } else if (f == "ball") {
    double r = u(0.18, 0.33, 1) * scale;
    o.half = Vec3(r, r, r);
    patterns = {Pattern::kChecks, Pattern::kNoise};
    n_patterns = 2;
  } else if (f == "box") {
    o.half = Vec3(u(0.13, 0.28, 1), u(0.13, 0.28, 2), 0.5 * u(0.24, 0.6, 3)) * scale;
    patterns = {Pattern::kChecks, Pattern::kNoise, Pattern::kStripes};
    n_patterns = 3;
  } else {  // pole: the thin object
    double r = u(0.035, 0.045, 1);
    o.half = Vec3(r, r, 0.5 * u(1.0, 1.2, 2));
    patterns = {Pattern::kWood};
    n_patterns = 1;
  }
  o.set_yaw(u(0.0, kPi, 4));
  o.pattern = patterns[static_cast<size_t>(u(0.0, 1.0, 5) * n_patterns) % n_patterns];
  o.pattern_param = o.pattern == Pattern::kStripes ? std::floor(u(4.0, 8.0, 6)) : u(0.09, 0.14, 6);
  o.texture_key = rng.bits(kStreamTexture, id);
  o.centre = Vec3(0, 0, o.half.z());
  return o;
}

bool overlaps(const Object& a, const Object& b) {
  double d = std::hypot(a.centre.x() - b.centre.x(), a.centre.y() - b.centre.y());
  return d < a.footprint() + b.footprint() + kPlaceMargin;
}

bool inside_placement(const Object& o) {
  return std::hypot(o.centre.x(), o.centre.y()) + o.footprint() <= kPlaceRadius;
}

// Drops `o` at a random free spot (rejection sampling); false when none found.
bool place_randomly(const Rng& rng, Object& o, const std::vector<Object>& placed) {
  for (uint64_t attempt = 0; attempt < 2000; ++attempt) {
    double rho = (kPlaceRadius - o.footprint()) * std::sqrt(rng.uniform(kStreamLayout, 1000 + o.id, attempt, 1));
    double phi = 2.0 * kPi * rng.uniform(kStreamLayout, 1000 + o.id, attempt, 2);
    o.centre = Vec3(rho * std::cos(phi), rho * std::sin(phi), o.half.z());
    bool ok = inside_placement(o);
    for (const auto& p : placed) ok = ok && !overlaps(o, p);
    if (ok) return true;
  }
  return false;
}

struct Layout {
  std::vector<Object> objects;
  std::vector<std::pair<int, int>> touching;        // ids
  std::vector<std::pair<int, int>> similar_colour;  // ids
  std::vector<int> thin;                            // ids
};

// Ordinary scenes: distinct colours while they last, random families, every
// category unique, no two footprints closer than kPlaceMargin.
Layout layout_ordinary(const SynthOptions& opt, const Rng& rng, int first_id, std::vector<Object> placed,
                       std::set<std::string> used) {
  Layout lay;
  lay.objects = std::move(placed);
  int k_total = opt.objects;
  double scale = k_total > 6 ? std::sqrt(6.0 / k_total) : 1.0;
  // A seed-dependent order of the scene colours (Fisher-Yates on counters).
  std::vector<int> order(kSceneColours);
  for (int i = 0; i < kSceneColours; ++i) order[i] = i;
  for (int i = kSceneColours - 1; i > 0; --i) {
    int j = static_cast<int>(rng.bits(kStreamLayout, 77, i) % static_cast<uint64_t>(i + 1));
    std::swap(order[i], order[j]);
  }
  std::vector<int> family_order(kSceneFamilies);
  for (int i = 0; i < kSceneFamilies; ++i) family_order[i] = i;
  for (int i = kSceneFamilies - 1; i > 0; --i) {
    int j = static_cast<int>(rng.bits(kStreamLayout, 99, i) % static_cast<uint64_t>(i + 1));
    std::swap(family_order[i], family_order[j]);
  }
  std::set<std::string> used_colours;
  for (const auto& o : lay.objects) used_colours.insert(o.colour_name);
  int next_colour = 0;
  for (int id = first_id; id <= k_total; ++id) {
    // Pick an unused colour first, then any colour whose category with some family is free.
    int colour = -1, family = -1;
    for (int c = 0; c < kSceneColours * 2 && colour < 0; ++c) {
      int cand = order[(next_colour + c) % kSceneColours];
      bool fresh = !used_colours.count(kColours[cand].name);
      if (c < kSceneColours && !fresh) continue;
      // Every family once in the first objects, then at random.
      int j = id - first_id;
      int f0 =
          j < kSceneFamilies ? family_order[j] : static_cast<int>(rng.bits(kStreamLayout, 88, id) % kSceneFamilies);
      for (int df = 0; df < kSceneFamilies; ++df) {
        int f = (f0 + df) % kSceneFamilies;
        if (!used.count(std::string(kColours[cand].name) + " " + kFamilies[f].name)) {
          colour = cand;
          family = f;
          next_colour = (next_colour + c + 1) % kSceneColours;
          break;
        }
      }
    }
    if (colour < 0) throw std::invalid_argument("too many objects: no unique category left");
    bool ok = false;
    for (uint64_t attempt = 0; attempt < 8 && !ok; ++attempt) {
      Object o = make_object(rng, id, family, colour, scale * (1.0 - 0.08 * attempt), attempt);
      if (place_randomly(rng, o, lay.objects)) {
        lay.objects.push_back(o);
        ok = true;
      }
    }
    if (!ok)
      throw std::invalid_argument("could not place " + std::to_string(k_total) +
                                  " objects without overlap on the ground; use fewer --objects");
    used.insert(lay.objects.back().category);
    used_colours.insert(lay.objects.back().colour_name);
  }
  return lay;
}

// Hard scenes: ids 1-2 a red and a dark red mug side by side
// (similar colour, similar category); id 3 a thin wooden pole just behind the
// red mug as camera 1 sees it (occlusion); ids 4-5 a yellow and a blue box
// touching face to face; further objects placed as in ordinary scenes.
Layout layout_hard(const SynthOptions& opt, const Rng& rng, const std::vector<Camera>& cams) {
  Vec3 c1 = cams[cams.size() > 1 ? 1 : 0].center();
  Vec3 u = Vec3(c1.x(), c1.y(), 0).normalized();  // towards camera 1
  Vec3 v(-u.y(), u.x(), 0);
  const int mug = 0, box = 2, pole = 4;
  for (uint64_t attempt = 0; attempt < 500; ++attempt) {
    auto U = [&](double lo, double hi, uint64_t what) {
      return rng.uniform(lo, hi, kStreamLayout, 500, attempt, what);
    };
    Object red = make_object(rng, 1, mug, colour_index("red"), 1.0, attempt);
    Object dark = make_object(rng, 2, mug, colour_index("dark red"), 1.0, attempt);
    Object pol = make_object(rng, 3, pole, colour_index("wooden"), 1.0, attempt);
    Object yel = make_object(rng, 4, box, colour_index("yellow"), 1.0, attempt);
    Object blu = make_object(rng, 5, box, colour_index("blue"), 1.0, attempt);
    red.half.z() = 0.5 * U(0.38, 0.46, 1);
    red.centre = U(0.8, 1.0, 2) * u;
    red.centre.z() = red.half.z();
    double side = rng.uniform(kStreamLayout, 500, attempt, 3) < 0.5 ? -1.0 : 1.0;
    dark.centre = red.centre + side * (red.footprint() + dark.footprint() + U(0.07, 0.14, 4)) * v;
    dark.centre.z() = dark.half.z();
    pol.centre = red.centre - (red.footprint() + pol.footprint() + U(0.1, 0.18, 5)) * u + U(-0.05, 0.05, 6) * v;
    pol.centre.z() = pol.half.z();
    // The touching boxes: blue's -x face lies in yellow's +x face plane.
    double phi = std::atan2(-u.y(), -u.x()) + U(-0.5, 0.5, 7);
    yel.half = Vec3(U(0.17, 0.23, 8), U(0.17, 0.23, 9), 0.5 * U(0.5, 0.66, 10));
    blu.half = Vec3(U(0.12, 0.17, 11), U(0.11, 0.15, 12), 0.5 * U(0.26, 0.4, 13));
    blu.set_yaw(yel.yaw);
    Vec3 yc = U(0.75, 1.0, 14) * Vec3(std::cos(phi), std::sin(phi), 0);
    yel.centre = Vec3(yc.x(), yc.y(), yel.half.z());
    double off = U(-0.5, 0.5, 15) * (yel.half.y() - blu.half.y());
    Vec3 rel = yel.dir_to_world(Vec3(yel.half.x() + blu.half.x(), off, 0));
    blu.centre = Vec3(yel.centre.x() + rel.x(), yel.centre.y() + rel.y(), blu.half.z());
    std::vector<Object> objs{red, dark, pol, yel, blu};
    bool ok = true;
    for (size_t i = 0; i < objs.size() && ok; ++i) {
      ok = inside_placement(objs[i]);
      for (size_t j = i + 1; j < objs.size() && ok; ++j)
        if (!(i == 3 && j == 4)) ok = !overlaps(objs[i], objs[j]);
    }
    if (!ok) continue;
    std::set<std::string> used;
    for (const auto& o : objs) used.insert(o.category);
    Layout lay = layout_ordinary(opt, rng, 6, objs, used);
    lay.touching = {{4, 5}};
    lay.similar_colour = {{1, 2}};
    lay.thin = {3};
    return lay;
  }
  throw std::runtime_error("could not lay out the hard scene (no attempt fitted)");
}

// ------------------------------------------------------------------ per-view products
struct ViewRender {
  std::vector<float> rgb;  // [H,W,3]
  std::vector<int> gt;     // [H,W] object id, 0 = ground/backdrop/sky
  // (occluded id, occluder id) -> pixels whose centre ray meets the occluded
  // object behind the occluder.
  std::map<std::pair<int, int>, int> occlusion;
};

ViewRender render_view(const Scene& scene, const Camera& cam, int samples) {
  ViewRender out;
  const int W = cam.width, H = cam.height;
  out.rgb.assign(static_cast<size_t>(W) * H * 3, 0.f);
  out.gt.assign(static_cast<size_t>(W) * H, 0);
  std::vector<double> all_t;
  const double inv = 1.0 / (samples * samples);
  for (int y = 0; y < H; ++y)
    for (int x = 0; x < W; ++x) {
      Vec3 sum = Vec3::Zero();
      for (int sy = 0; sy < samples; ++sy)
        for (int sx = 0; sx < samples; ++sx) {
          Ray r = camera_ray(cam, x + (sx + 0.5) / samples, y + (sy + 0.5) / samples);
          sum += radiance(scene, r, scene.trace(r));
        }
      sum *= inv;
      size_t p = static_cast<size_t>(y) * W + x;
      for (int c = 0; c < 3; ++c) out.rgb[3 * p + c] = static_cast<float>(sum[c]);
      Ray centre = camera_ray(cam, x + 0.5, y + 0.5);
      Hit h = scene.trace(centre, &all_t);
      int id = std::max(h.object, 0);
      out.gt[p] = id;
      if (id > 0)
        for (size_t k = 0; k < all_t.size(); ++k)
          if (static_cast<int>(k) + 1 != id && all_t[k] < kInf) ++out.occlusion[{static_cast<int>(k) + 1, id}];
    }
  return out;
}

// Part index of a hit at each mask level: 0 default (box faces, cylinder
// side/top, sphere halves along the object's x), 1 small (upper/lower
// half), 2 medium and 3 large (the whole object).
int part_of(const Object& o, const Hit& h, int level) {
  if (level >= 2) return 0;
  if (level == 1) return h.local.z() > 0 ? 0 : 1;
  switch (o.primitive) {
    case Primitive::kBox:
      return h.face;
    case Primitive::kCylinder:
      return h.face;
    case Primitive::kSphere:
      return h.local.x() >= 0 ? 0 : 1;
  }
  return 0;
}

struct MaskKey {
  int level, object, part;
  bool operator<(const MaskKey& o) const { return std::tie(level, object, part) < std::tie(o.level, o.object, o.part); }
};

struct ViewMasksOut {
  int width = 0, height = 0;
  std::vector<float> ids;      // [4,Hm,Wm], -1 = none
  std::vector<MaskKey> masks;  // row i of _f describes mask id i
  std::array<int, kLevels> per_level{};
};

// How SAM's automatic mode cuts the background of one view: the ground disc
// in four quarters about a centre and angle drawn per view (so the cuts move
// from view to view, as SAM's do), the floor ring, the wall in two halves
// split at that angle, the ceiling.
struct BackgroundCut {
  double c = 1, s = 0, cx = 0, cy = 0;  // cos and sin of the angle, the centre

  BackgroundCut(int view, const Rng& rng) {
    const double angle = 2.0 * kPi * rng.uniform(kStreamBackground, view, 0);
    c = std::cos(angle);
    s = std::sin(angle);
    cx = kPlaceRadius * (2.0 * rng.uniform(kStreamBackground, view, 1) - 1.0) / 3.0;
    cy = kPlaceRadius * (2.0 * rng.uniform(kStreamBackground, view, 2) - 1.0) / 3.0;
  }

  // The region of a hit on object 0 (a Surface), in 0..7: the `part` of
  // object 0's masks.
  int region(const Hit& h) const {
    const Vec3& p = h.local;  // world point for object 0
    switch (h.face) {
      case kSurfaceGround: {
        const double u = c * (p.x() - cx) + s * (p.y() - cy), v = -s * (p.x() - cx) + c * (p.y() - cy);
        return (u >= 0 ? 0 : 1) + (v >= 0 ? 0 : 2);
      }
      case kSurfaceFloor:
        return 4;
      case kSurfaceWall:
        return c * p.x() + s * p.y() >= 0 ? 5 : 6;
      default:
        return 7;
    }
  }
};

ViewMasksOut make_masks(const Scene& scene, const Camera& cam, int view, int factor, const Rng& rng,
                        bool background_masks) {
  ViewMasksOut m;
  const int Wm = cam.width / factor, Hm = cam.height / factor;
  m.width = Wm;
  m.height = Hm;
  const size_t n = static_cast<size_t>(Wm) * Hm;
  // Exact (object, part) per mask pixel from its centre ray.
  std::vector<int> obj(n, 0);
  std::vector<std::array<int, kLevels>> part(n);
  const BackgroundCut cut(view, rng);
  for (int y = 0; y < Hm; ++y)
    for (int x = 0; x < Wm; ++x) {
      Ray r = camera_ray(cam, (x + 0.5) * factor, (y + 0.5) * factor);
      Hit h = scene.trace(r);
      size_t p = static_cast<size_t>(y) * Wm + x;
      obj[p] = std::max(h.object, 0);
      if (obj[p] > 0)
        for (int l = 0; l < kLevels; ++l) part[p][l] = part_of(scene.objects[obj[p] - 1], h, l);
      else if (h.object == 0 && background_masks)
        part[p].fill(cut.region(h));
      else
        part[p].fill(-1);  // sky, or background without masks
    }
  m.ids.assign(kLevels * n, -1.f);
  int next_id = 0;
  for (int level = 0; level < kLevels; ++level) {
    // SAM-like boundaries: each pixel takes the label of a pixel displaced by a
    // smooth field of up to ~kMaskJitterPx (independent per view and level).
    uint64_t kx = rng.bits(kStreamJitter, view, level, 0), ky = rng.bits(kStreamJitter, view, level, 1);
    std::vector<int> code(n, -1);
    std::map<int, int> count;
    for (int y = 0; y < Hm; ++y)
      for (int x = 0; x < Wm; ++x) {
        Vec3 q(x / kMaskJitterScale, y / kMaskJitterScale, 0.5);
        int dx = static_cast<int>(std::lround(kMaskJitterPx * (2.0 * value_noise(kx, q) - 1.0)));
        int dy = static_cast<int>(std::lround(kMaskJitterPx * (2.0 * value_noise(ky, q) - 1.0)));
        int sx = std::clamp(x + dx, 0, Wm - 1), sy = std::clamp(y + dy, 0, Hm - 1);
        size_t src = static_cast<size_t>(sy) * Wm + sx;
        if (part[src][level] < 0) continue;
        int c = obj[src] * 8 + part[src][level];
        code[static_cast<size_t>(y) * Wm + x] = c;
        ++count[c];
      }
    // Keep masks in (object, part) order; drop tiny ones and ~kMaskDropRate at random.
    std::map<int, int> id_of;
    for (const auto& [c, pixels] : count) {
      if (pixels < kMinMaskPixels) continue;
      if (rng.uniform(kStreamDrop, view, level, static_cast<uint64_t>(c)) < kMaskDropRate) continue;
      id_of[c] = next_id++;
      m.masks.push_back({level, c / 8, c % 8});
      ++m.per_level[level];
    }
    float* out = &m.ids[level * n];
    for (size_t p = 0; p < n; ++p) {
      auto it = code[p] >= 0 ? id_of.find(code[p]) : id_of.end();
      if (it != id_of.end()) out[p] = static_cast<float>(it->second);
    }
  }
  return m;
}

// CLIP-like feature of a mask: the object's category vector (mixed with a
// part direction below level 2) plus per-view noise, unit length.
Feature mask_feature(const EmbeddingModel& model, const std::vector<Feature>& category_vec, const MaskKey& k, int view,
                     const Rng& rng) {
  uint64_t c = static_cast<uint64_t>(k.object * 8 + k.part);
  if (k.object == 0) {
    // Background (floor, wall, ceiling): a direction per surface kind, unrelated to every category.
    const uint64_t kind = k.part < 4 ? 0 : static_cast<uint64_t>(k.part);
    Feature v(model.dim());
    for (int i = 0; i < model.dim(); ++i) v[i] = rng.normal(kStreamBackground, 100 + kind, 0, static_cast<uint64_t>(i));
    normalise(v);
    return noisy(v, kMaskNoise, rng, kStreamMaskNoise, view, k.level, c);
  }
  const Feature& cat = category_vec[k.object - 1];
  if (k.level >= 2) return noisy(cat, kMaskNoise, rng, kStreamMaskNoise, view, k.level, c);
  Feature part(model.dim());
  for (int i = 0; i < model.dim(); ++i) part[i] = rng.normal(kStreamPartVec, k.level, c, static_cast<uint64_t>(i));
  normalise(part);
  Feature v(model.dim());
  for (int i = 0; i < model.dim(); ++i) v[i] = kPartCategory * cat[i] + kPartOwn * part[i];
  return noisy(v, kPartNoise, rng, kStreamMaskNoise, view, k.level, c);
}

// ------------------------------------------------------------------ files
void write_text_atomic(const fs::path& path, const std::string& text) {
  fs::path tmp = path.parent_path() / ("." + path.filename().string() + ".tmp." + std::to_string(::getpid()));
  {
    std::ofstream f(tmp, std::ios::binary | std::ios::trunc);
    f.write(text.data(), static_cast<std::streamsize>(text.size()));
    f.flush();
    if (!f) {
      std::error_code ec;
      fs::remove(tmp, ec);
      throw std::runtime_error(path.string() + ": could not write the file (is the directory writable?)");
    }
  }
  std::error_code ec;
  fs::rename(tmp, path, ec);
  if (ec) {
    fs::remove(tmp, ec);
    throw std::runtime_error(path.string() + ": could not move the finished file into place: " + ec.message());
  }
}

// Rounds to 1e-7 so JSON numbers stay short (features are unit vectors).
double short_float(double v) {
  return std::round(v * 1e7) / 1e7;
}

Json vec_json(const Vec3& v) {
  return Json::array({v.x(), v.y(), v.z()});
}

// Files in our folders named like our outputs but not written by this run
// (more views or another split in an earlier run) would mix two scenes: they go.
void remove_stale(const fs::path& dir, const std::set<std::string>& keep) {
  if (!fs::is_directory(dir)) return;
  std::vector<fs::path> stale;
  for (const auto& e : fs::directory_iterator(dir)) {
    std::string name = e.path().filename().string();
    if (name.rfind("view_", 0) != 0 || keep.count(name)) continue;
    size_t i = 5;
    while (i < name.size() && std::isdigit(static_cast<unsigned char>(name[i]))) ++i;
    if (i == 5) continue;
    std::string rest = name.substr(i);
    if (rest == ".png" || rest == ".json" || rest == "_s.npy" || rest == "_f.npy") stale.push_back(e.path());
  }
  std::sort(stale.begin(), stale.end());
  for (const auto& p : stale) {
    spdlog::debug("removing stale {}", p.string());
    fs::remove(p);
  }
}

void validate(const SynthOptions& o) {
  auto bad = [](const std::string& what) { throw std::invalid_argument(what); };
  if (o.width < 8 || o.width > 8192 || o.height < 8 || o.height > 8192)
    bad("width and height must be in 8..8192 (got " + std::to_string(o.width) + "x" + std::to_string(o.height) + ")");
  if (o.views < 1 || o.views > 999) bad("views must be in 1..999 (got " + std::to_string(o.views) + ")");
  if (o.objects < 1 || o.objects > 16) bad("objects must be in 1..16 (got " + std::to_string(o.objects) + ")");
  if (o.hard && o.objects < 5)
    bad("hard mode needs at least 5 objects (two touching, two of similar colour, one thin; got " +
        std::to_string(o.objects) + ")");
  if (o.samples < 1 || o.samples > 16) bad("samples must be in 1..16 (got " + std::to_string(o.samples) + ")");
  if (o.points < 0 || o.points > 10000000) bad("points must be in 0..10000000 (got " + std::to_string(o.points) + ")");
  if (o.mask_factor < 1 || o.width % o.mask_factor || o.height % o.mask_factor || o.width / o.mask_factor < 4 ||
      o.height / o.mask_factor < 4)
    bad("mask_factor must be >= 1 and divide width and height, leaving at least 4x4 mask pixels (got " +
        std::to_string(o.mask_factor) + " for " + std::to_string(o.width) + "x" + std::to_string(o.height) + ")");
}

// The scene's folders, made, and cleared of what an earlier run wrote that
// this one will not (other views, the other COLMAP format, removal ground truth).
struct SceneFolders {
  fs::path root, images, sparse, lf, masks_dir, gt_dir, label_dir;
};
SceneFolders make_scene_folders(const std::string& out_dir, const SynthOptions& opt) {
  SceneFolders d;
  d.root = out_dir;
  d.images = d.root / "images";
  d.sparse = d.root / "sparse" / "0";
  d.lf = d.root / "language_features";
  d.masks_dir = d.root / "masks";
  d.gt_dir = d.root / "gt";
  d.label_dir = d.root / "label";
  const fs::path &root = d.root, &images = d.images, &sparse = d.sparse, &lf = d.lf, &masks_dir = d.masks_dir,
                 &gt_dir = d.gt_dir, &label_dir = d.label_dir;
  try {
    for (const auto& d : {images, sparse, lf, masks_dir, gt_dir, label_dir}) fs::create_directories(d);
  } catch (const fs::filesystem_error& e) {
    throw std::runtime_error(out_dir + ": cannot create the scene folders: " + e.what());
  }
  {
    std::set<std::string> png, npy, labels;
    for (int i = 0; i < opt.views; ++i) {
      png.insert(view_stem(i) + ".png");
      npy.insert(view_stem(i) + "_s.npy");
      npy.insert(view_stem(i) + "_f.npy");
      if (is_test_view(i)) labels.insert(view_stem(i) + ".json");
    }
    for (const auto& d : {images, masks_dir, gt_dir}) remove_stale(d, png);
    // An earlier run's removal ground truth would describe other objects.
    std::error_code ec;
    fs::remove_all(root / "removal_gt", ec);
    remove_stale(lf, npy);
    remove_stale(label_dir, labels);
    // The reader prefers .bin: a model of the other format from an earlier run must go.
    const char* other = opt.text_model ? ".bin" : ".txt";
    for (const char* f : {"cameras", "images", "points3D"}) fs::remove(sparse / (std::string(f) + other));
  }
  return d;
}

// A test view's labels (every visible object's outline, per connected part,
// as polygons with boxes) and one click per object deep inside it, from the
// exact object ids of the pixels.
Json label_objects(const Scene& scene, ViewRender& vr, const std::map<int, int>& pixels, const std::string& stem,
                   int W, int H, Json& clicks) {
  Json objs = Json::array();
  cv::Mat gt_mat(H, W, CV_32S, vr.gt.data());
  for (const auto& [id, n] : pixels) {
    if (n < kMinLabelPixels) continue;
    const Object& o = scene.objects[id - 1];
    cv::Mat mask = gt_mat == id;  // CV_8U 0/255
    cv::Mat comp, stats, centroids;
    int nc = cv::connectedComponentsWithStats(mask, comp, stats, centroids, 8, CV_32S);
    for (int c = 1; c < nc; ++c) {
      if (stats.at<int>(c, cv::CC_STAT_AREA) < kMinLabelPixels) continue;
      cv::Mat one = comp == c;
      std::vector<std::vector<cv::Point>> contours;
      cv::findContours(one, contours, cv::RETR_EXTERNAL, cv::CHAIN_APPROX_SIMPLE);
      for (const auto& contour : contours) {
        Json seg = Json::array();
        for (const auto& pt : contour) seg.push_back(Json::array({pt.x, pt.y}));
        // fillPoly needs 3 points; a 1-2 pixel run gets a degenerate triangle.
        while (seg.size() < 3) seg.push_back(seg.back());
        cv::Rect bb = cv::boundingRect(contour);
        objs.push_back(Json{{"category", o.category},
                            {"segmentation", seg},
                            {"bbox", Json::array({bb.x, bb.y, bb.x + bb.width - 1, bb.y + bb.height - 1})}});
      }
    }
    // A click deep inside the object: the maximum of the distance transform
    // (padded so the image border counts as outside; first maximum in raster order).
    cv::Mat padded;
    cv::copyMakeBorder(mask, padded, 1, 1, 1, 1, cv::BORDER_CONSTANT, 0);
    cv::Mat dist;
    cv::distanceTransform(padded, dist, cv::DIST_L2, cv::DIST_MASK_PRECISE);
    cv::Point best;
    cv::minMaxLoc(dist, nullptr, nullptr, nullptr, &best);
    clicks.push_back(
        Json{{"frame", stem}, {"x", best.x - 1}, {"y", best.y - 1}, {"category", o.category}, {"object", id}});
  }
  return objs;
}

// Every test view traced again without each category's objects.
void write_removal_gt(const fs::path& root, const Scene& scene, const std::vector<Camera>& cams,
                      const SynthOptions& opt, std::vector<std::string>& files) {
  const int W = opt.width, H = opt.height;
  std::set<std::string> categories;
  for (const auto& o : scene.objects) categories.insert(o.category);
  for (const std::string& category : categories) {
    Scene without = scene;
    for (auto& o : without.objects) o.removed = o.category == category;
    const fs::path dir = root / "removal_gt" / category;
    try {
      fs::create_directories(dir);
    } catch (const fs::filesystem_error& e) {
      throw std::runtime_error(dir.string() + ": cannot create the folder: " + e.what());
    }
    for (int i = 0; i < opt.views; ++i) {
      if (!is_test_view(i)) continue;
      const std::string stem = view_stem(i);
      ViewRender vr = render_view(without, cams[i], opt.samples);
      write_rgb_png((dir / (stem + ".png")).string(), vr.rgb, W, H);
      files.push_back("removal_gt/" + category + "/" + stem + ".png");
    }
    spdlog::info("synth: removal ground truth without \"{}\"", category);
  }
}

// Sparse points on visible surfaces: rays through random pixels of random views.
void sample_points(const Scene& scene, const std::vector<Camera>& cams, const SynthOptions& opt, const Rng& rng,
                   std::vector<Eigen::Vector3d>& points, std::vector<Eigen::Vector3<uint8_t>>& colors) {
  const int W = opt.width, H = opt.height;
  points.reserve(opt.points);
  colors.reserve(opt.points);
  for (int n = 0; n < opt.points; ++n) {
    for (uint64_t attempt = 0; attempt < 64; ++attempt) {
      int view = static_cast<int>(rng.bits(kStreamPoints, n, attempt, 0) % static_cast<uint64_t>(opt.views));
      double u = W * rng.uniform(kStreamPoints, n, attempt, 1), v = H * rng.uniform(kStreamPoints, n, attempt, 2);
      Ray r = camera_ray(cams[view], u, v);
      Hit h = scene.trace(r);
      if (h.object < 0) continue;  // sky (never with the backdrop)
      const Vec3 p = r.o + h.t * r.d;
      if (opt.backdrop && !opt.wall_points && std::hypot(p.x(), p.y()) > kBackdropRadius - 1e-3 && p.z() > 1e-6)
        continue;  // on the wall
      Vec3 c = radiance(scene, r, h);
      points.push_back(p);
      colors.emplace_back(static_cast<uint8_t>(std::lround(c.x() * 255.0)),
                          static_cast<uint8_t>(std::lround(c.y() * 255.0)),
                          static_cast<uint8_t>(std::lround(c.z() * 255.0)));
      break;
    }
  }
}

// Two unused colour/family pairs of the scene's palette, and unrelated phrases.
std::vector<std::string> pick_distractors(const Scene& scene, const Rng& rng) {
  std::vector<std::string> distractors;
  std::set<std::string> used;
  for (const auto& o : scene.objects) used.insert(o.category);
  std::vector<std::string> free;
  for (int c = 0; c < kSceneColours; ++c)
    for (int fam = 0; fam < kSceneFamilies; ++fam) {
      std::string p = std::string(kColours[c].name) + " " + kFamilies[fam].name;
      if (!used.count(p)) free.push_back(p);
    }
  for (int d = 0; d < 2 && !free.empty(); ++d) {
    size_t j = rng.bits(kStreamDistractor, d) % free.size();
    distractors.push_back(free[j]);
    free.erase(free.begin() + static_cast<std::ptrdiff_t>(j));
  }
  for (const char* p : kUnrelatedPhrases) distractors.push_back(p);
  return distractors;
}

// synth.json's objects.
Json objects_json(const Scene& scene) {
  Json objects = Json::array();
  for (const auto& o : scene.objects) {
    Json size = Json::array({2 * o.half.x(), 2 * o.half.y(), 2 * o.half.z()});
    objects.push_back(Json{{"id", o.id},
                           {"category", o.category},
                           {"family", o.family},
                           {"colour_name", o.colour_name},
                           {"primitive", primitive_name(o.primitive)},
                           {"centre", vec_json(o.centre)},
                           {"size", size},
                           {"yaw", o.yaw},
                           {"colour", vec_json(o.colour)},
                           {"pattern", pattern_name(o.pattern)}});
  }
  return objects;
}

// synth.json's cameras.
Json cameras_json(const std::vector<Camera>& cams, const SynthOptions& opt) {
  Json cameras = Json::array();
  for (int i = 0; i < opt.views; ++i) {
    const Camera& c = cams[i];
    Json R = Json::array();
    for (int r = 0; r < 3; ++r) R.push_back(Json::array({c.R(r, 0), c.R(r, 1), c.R(r, 2)}));
    cameras.push_back(Json{{"name", c.name},
                           {"test", is_test_view(i)},
                           {"width", c.width},
                           {"height", c.height},
                           {"fx", c.fx},
                           {"fy", c.fy},
                           {"cx", c.cx},
                           {"cy", c.cy},
                           {"R", R},
                           {"t", vec_json(c.t)},
                           {"centre", vec_json(c.center())}});
  }
  return cameras;
}

// vocab.json: a text embedding per scene category and distractor, from the
// same embedding model as the features (the text encoder does not depend on
// the scene seed).
Json vocabulary_json(const Scene& scene, const EmbeddingModel& model, const std::vector<Feature>& category_vec,
                     const std::vector<std::string>& distractors) {
  Json vocab = Json::object();
  const Rng text_rng{kModelKey};  // the text encoder does not depend on the scene seed
  auto add_phrase = [&](const std::string& phrase, const Feature& cat) {
    Feature t = noisy(cat, kTextNoise, text_rng, kStreamTextNoise, hash_string(phrase), 0, 0);
    Json arr = Json::array();
    for (double x : t) arr.push_back(short_float(x));
    vocab[phrase] = arr;
  };
  for (size_t k = 0; k < scene.objects.size(); ++k) add_phrase(scene.objects[k].category, category_vec[k]);
  for (const auto& p : distractors) {
    size_t sp = p.find(' ');
    bool coloured = sp != std::string::npos && p.substr(sp + 1).find(' ') == std::string::npos &&
                    std::any_of(std::begin(kColours), std::end(kColours),
                                [&](const ColourName& c) { return p.substr(0, sp) == c.name; });
    add_phrase(p, coloured ? model.category(p.substr(0, sp), p.substr(sp + 1)) : model.category("", p));
  }
  return vocab;
}

// synth.json: everything needed to rebuild and check the scene.
Json synth_record(const SynthOptions& opt, const Scene& scene, const Layout& lay, const std::vector<Camera>& cams,
                  const Json& objects, const Json& cameras, const std::vector<std::string>& distractors,
                  size_t points_written, const std::map<std::pair<int, int>, int>& occlusion_total,
                  const Json& views_json, const std::vector<std::string>& files) {
  const int W = opt.width, H = opt.height, f = opt.mask_factor;
  auto pairs = [](const std::vector<std::pair<int, int>>& v) {
    Json a = Json::array();
    for (const auto& [x, y] : v) a.push_back(Json::array({x, y}));
    return a;
  };
  Json occ_pairs = Json::array();
  for (const auto& [pair, n] : occlusion_total)
    occ_pairs.push_back(Json{{"occluded", pair.first}, {"occluder", pair.second}, {"pixels", n}});
  Json synth{{"generator", "ag2gs synth"},
             {"format_version", 1},
             {"seed", opt.seed},
             {"options",
              {{"width", opt.width},
               {"height", opt.height},
               {"views", opt.views},
               {"objects", opt.objects},
               {"feature_dim", opt.feature_dim},
               {"samples", opt.samples},
               {"points", opt.points},
               {"mask_factor", opt.mask_factor},
               {"hard", opt.hard},
               {"text_model", opt.text_model},
               {"backdrop", opt.backdrop}}},
             {"world",
              {{"up", "+z"},
               {"ground", {{"shape", "disc"}, {"z", 0.0}, {"radius", kGroundRadius}}},
               {"backdrop", opt.backdrop ? Json{{"shape", "closed cylinder around the z axis"},
                                                {"radius", kBackdropRadius},
                                                {"height", kBackdropHeight},
                                                {"surfaces",
                                                 "wall (radius, 0 <= z <= height), floor ring (z = 0, ground "
                                                 "radius < r <= radius), ceiling (z = height, r <= radius)"}}
                                         : Json(nullptr)}}},
             {"light", {{"direction", vec_json(scene.light.direction)}, {"ambient", kAmbient}, {"shadows", true}}},
             {"conventions",
              {{"size", "full extents in the object frame: sphere [2r,2r,2r], box [2hx,2hy,h], cylinder [2r,2r,h]"},
               {"centre", "geometric centre; objects stand on z = 0"},
               {"yaw", "rotation about +z from the object frame to the world"},
               {"gt", "gt/<stem>.png: object id of the pixel centre ray (1..K), 0 ground, backdrop or sky"},
               {"masks", "masks/<stem>.png = language_features level-3 id + 1 (0 none), nearest-upsampled"},
               {"mask_levels",
                "0 default: box faces, cylinder side/top, sphere halves; 1 small: upper/lower halves; "
                "2 medium and 3 large: whole objects (independent boundary jitter and drops)"},
               {"clicks", "integer pixel column x and row y (pixel centre at x+0.5, y+0.5)"},
               {"label_bbox", "[x0, y0, x1, y1] inclusive pixel indices"}}},
             {"objects", objects},
             {"relations",
              {{"touching", pairs(lay.touching)}, {"similar_colour", pairs(lay.similar_colour)}, {"thin", lay.thin}}},
             {"distractors", distractors},
             {"cameras", cameras},
             {"test_views",
              [&] {
                Json a = Json::array();
                for (int i = 0; i < opt.views; ++i)
                  if (is_test_view(i)) a.push_back(cams[i].name);
                return a;
              }()},
             {"points_written", points_written},
             {"outliers", 0},
             {"masks",
              {{"levels", Json::array({"default", "small", "medium", "large"})},
               {"width", W / f},
               {"height", H / f},
               {"drop_rate", kMaskDropRate},
               {"jitter_px", kMaskJitterPx},
               {"min_pixels", kMinMaskPixels}}},
             {"features",
              {{"dim", opt.feature_dim},
               {"cosine_same_family", kWGlobal2 + kWFamily2},
               {"cosine_same_colour", kWGlobal2 + kWColour2},
               {"cosine_unrelated", kWGlobal2},
               {"text_noise", kTextNoise},
               {"mask_noise", kMaskNoise},
               {"part_noise", kPartNoise}}},
             {"occlusion_pairs", occ_pairs},
             {"views", views_json},
             {"files", files}};
  return synth;
}

}  // namespace

void write_synth_scene(const std::string& out_dir, const SynthOptions& opt) {
  validate(opt);
  const EmbeddingModel model(opt.feature_dim);  // throws for too small a dimension
  const Rng rng{opt.seed};
  const int W = opt.width, H = opt.height;

  // ---- scene
  std::vector<Camera> cams = make_cameras(opt, rng);
  Layout lay = opt.hard ? layout_hard(opt, rng, cams) : layout_ordinary(opt, rng, 1, {}, {});
  Scene scene;
  scene.objects = lay.objects;
  {
    double az = 2.0 * kPi * rng.uniform(kStreamLight, 0), el = rng.uniform(0.75, 1.05, kStreamLight, 1);
    scene.light.direction = Vec3(std::cos(az) * std::cos(el), std::sin(az) * std::cos(el), std::sin(el));
  }
  scene.ground_key = rng.bits(kStreamTexture, 0xffff);
  scene.backdrop = opt.backdrop;
  scene.backdrop_key = rng.bits(kStreamTexture, 0xfffe);
  std::vector<Feature> category_vec;
  for (const auto& o : scene.objects) category_vec.push_back(model.category(o.colour_name, o.family));

  // ---- folders
  const SceneFolders dirs = make_scene_folders(out_dir, opt);
  const fs::path &root = dirs.root, &images = dirs.images, &sparse = dirs.sparse, &lf = dirs.lf,
                 &masks_dir = dirs.masks_dir, &gt_dir = dirs.gt_dir, &label_dir = dirs.label_dir;

  std::vector<std::string> files;
  Json clicks = Json::array();
  Json views_json = Json::array();
  std::map<std::pair<int, int>, int> occlusion_total;
  const int f = opt.mask_factor;
  for (int i = 0; i < opt.views; ++i) {
    const Camera& cam = cams[i];
    const std::string stem = view_stem(i);
    ViewRender vr = render_view(scene, cam, opt.samples);
    write_rgb_png((images / (stem + ".png")).string(), vr.rgb, W, H);
    std::vector<float> gtf(vr.gt.begin(), vr.gt.end());
    write_gray16_png((gt_dir / (stem + ".png")).string(), gtf, W, H, 1.f);
    files.push_back("images/" + stem + ".png");
    files.push_back("gt/" + stem + ".png");

    // SAM-like masks, CLIP-like features, and the level-3 PNG at full size.
    ViewMasksOut vm = make_masks(scene, cam, i, f, rng, opt.background_masks);
    write_npy((lf / (stem + "_s.npy")).string(), vm.ids, {kLevels, vm.height, vm.width});
    std::vector<float> feats(vm.masks.size() * static_cast<size_t>(opt.feature_dim));
    for (size_t m = 0; m < vm.masks.size(); ++m) {
      Feature v = mask_feature(model, category_vec, vm.masks[m], i, rng);
      for (int d = 0; d < opt.feature_dim; ++d) feats[m * opt.feature_dim + d] = static_cast<float>(v[d]);
    }
    write_npy((lf / (stem + "_f.npy")).string(), feats,
              {static_cast<int64_t>(vm.masks.size()), static_cast<int64_t>(opt.feature_dim)});
    std::vector<float> large(static_cast<size_t>(W) * H);
    const size_t level3 = 3 * static_cast<size_t>(vm.width) * vm.height;
    for (int y = 0; y < H; ++y)
      for (int x = 0; x < W; ++x)
        large[static_cast<size_t>(y) * W + x] = vm.ids[level3 + static_cast<size_t>(y / f) * vm.width + x / f] + 1.f;
    write_gray16_png((masks_dir / (stem + ".png")).string(), large, W, H, 1.f);
    files.push_back("language_features/" + stem + "_s.npy");
    files.push_back("language_features/" + stem + "_f.npy");
    files.push_back("masks/" + stem + ".png");

    // Visible objects and, for test views, labels and clicks from the exact GT.
    std::map<int, int> pixels;
    for (int id : vr.gt)
      if (id > 0) ++pixels[id];
    Json visible = Json::array();
    for (const auto& [id, n] : pixels) visible.push_back(Json{{"id", id}, {"pixels", n}});
    if (is_test_view(i)) {
      Json objs = label_objects(scene, vr, pixels, stem, W, H, clicks);
      Json label{{"info", {{"width", W}, {"height", H}, {"name", stem + ".png"}}}, {"objects", objs}};
      write_text_atomic(label_dir / (stem + ".json"), label.dump() + "\n");
      files.push_back("label/" + stem + ".json");
    }

    Json occ = Json::array();
    for (const auto& [pair, n] : vr.occlusion) {
      occ.push_back(Json{{"occluded", pair.first}, {"occluder", pair.second}, {"pixels", n}});
      occlusion_total[pair] += n;
    }
    views_json.push_back(
        Json{{"name", cam.name},
             {"test", is_test_view(i)},
             {"visible", visible},
             {"masks_per_level", Json::array({vm.per_level[0], vm.per_level[1], vm.per_level[2], vm.per_level[3]})},
             {"occlusions", occ}});
    spdlog::info("synth: view {}/{} {}{}: {} objects visible, {} masks", i + 1, opt.views, cam.name,
                 is_test_view(i) ? " (test)" : "", pixels.size(), vm.masks.size());
  }
  if (opt.hard && occlusion_total.empty()) spdlog::warn("synth: hard scene without any occlusion between objects");

  // ---- removal ground truth: every test view traced again without each
  // category's objects (all objects of a category go together, as a text
  // query selects them together).
  if (opt.removal_gt) write_removal_gt(root, scene, cams, opt, files);

  // ---- sparse points on visible surfaces: rays through random pixels of random views.
  std::vector<Eigen::Vector3d> points;
  std::vector<Eigen::Vector3<uint8_t>> colors;
  sample_points(scene, cams, opt, rng, points, colors);
  write_colmap_model(sparse.string(), cams, points, colors, !opt.text_model);
  for (const char* name : {"cameras", "images", "points3D"})
    files.push_back(std::string("sparse/0/") + name + (opt.text_model ? ".txt" : ".bin"));

  // ---- vocabulary: scene categories plus distractors (two unused colour/family
  // pairs, related to scene objects by colour or family, and unrelated phrases).
  const std::vector<std::string> distractors = pick_distractors(scene, rng);
  const Json vocab = vocabulary_json(scene, model, category_vec, distractors);
  write_text_atomic(root / "vocab.json", vocab.dump() + "\n");
  write_text_atomic(root / "clicks.json", clicks.dump(1) + "\n");
  files.push_back("vocab.json");
  files.push_back("clicks.json");

  // ---- synth.json: everything needed to rebuild and check the scene.
  const Json objects = objects_json(scene);
  const Json cameras = cameras_json(cams, opt);
  files.push_back("synth.json");
  Json synth = synth_record(opt, scene, lay, cams, objects, cameras, distractors, points.size(), occlusion_total,
                            views_json, files);
  // Written only when on, so scenes generated without it keep their bytes.
  if (opt.background_masks) synth["options"]["background_masks"] = true;
  if (opt.removal_gt) synth["options"]["removal_gt"] = true;
  // Written only when off, so the files of default scenes stay as they were.
  if (!opt.wall_points) synth["options"]["wall_points"] = false;
  write_text_atomic(root / "synth.json", synth.dump(1) + "\n");
  spdlog::info("synth: wrote {} views, {} objects, {} points to {}", opt.views, scene.objects.size(), points.size(),
               out_dir);
}

}  // namespace ag2gs
