#include "train/anchors/anchor_model.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <stdexcept>
#include <string>
#include <utility>

#include "host/core/counter_rng.h"
#include "host/core/gaussians.h"
#include "host/core/scalar_math.h"
#include "host/io/json_input.h"

namespace ag2gs {

namespace {

constexpr int kCellBits = 20;
constexpr uint64_t kCellMask = (uint64_t(1) << kCellBits) - 1;
constexpr double kQuatPerturbation = 1e-2;  // half-width of the initial xyz perturbation

// Random-number streams of one (anchor, child) counter.
enum Stream { kOffsetX = 0, kQuatX = 3, kFeatureX = 6 };

int64_t int_pow(int base, int exp) {
  int64_t r = 1;
  for (int i = 0; i < exp; ++i) r *= base;
  return r;
}

// floor(a / b) for b > 0, also for negative a.
int floor_div(int64_t a, int64_t b) {
  int64_t q = a / b;
  if (a % b != 0 && a < 0) --q;
  return static_cast<int>(q);
}

[[noreturn]] void fail_archive(const ModelArchive& archive, const std::string& what) {
  throw std::runtime_error((archive.source.empty() ? std::string("model") : archive.source) +
                           ": anchor model: " + what);
}

}  // namespace

double anchor_uniform01(uint64_t seed, uint64_t voxel_key, int child, int stream) {
  uint64_t h = splitmix64(seed);
  h = splitmix64(h ^ voxel_key);
  h = splitmix64(h ^ (static_cast<uint64_t>(child + 1) << 8) ^ static_cast<uint64_t>(stream));
  return static_cast<double>(h >> 11) * (1.0 / 9007199254740992.0);  // 53 bits
}

uint64_t anchor_voxel_key(int layer, const Eigen::Vector3i& cell) {
  if (layer < 0 || layer >= kMaxLayers) throw std::out_of_range("anchor layer " + std::to_string(layer));
  if (!cell_in_range(cell))
    throw std::out_of_range("anchor cell (" + std::to_string(cell.x()) + ", " + std::to_string(cell.y()) + ", " +
                            std::to_string(cell.z()) + ") is outside +-2^19");
  uint64_t key = static_cast<uint64_t>(layer) << (3 * kCellBits);
  for (int k = 0; k < 3; ++k)
    key |= (static_cast<uint64_t>(cell[k] + kMaxAnchorCell) & kCellMask) << ((2 - k) * kCellBits);
  return key;
}

size_t AnchorModel::KeyHash::operator()(uint64_t key) const {
  return static_cast<size_t>(splitmix64(key));
}

// ---------------------------------------------------------------- config, grid

void AnchorConfig::validate() const {
  auto bad = [](const std::string& what) { throw std::invalid_argument("AnchorConfig: " + what); };
  if (children < 1 || children > 64) bad("children is " + std::to_string(children) + "; use 1..64");
  if (layers < 1 || layers > kMaxLayers) bad("layers is " + std::to_string(layers) + "; use 1..16");
  if (top_cells < 0) bad("top_cells is " + std::to_string(top_cells) + "; use 0 (chosen from the scene) or more");
  if (!(voxel_size >= 0) || !std::isfinite(voxel_size))
    bad("voxel_size must be a finite number > 0 (world units), or 0 to choose it from the scene");
  if (layer_ratio < 2) bad("layer_ratio is " + std::to_string(layer_ratio) + "; it must be at least 2");
  if (init_layer < -1 || init_layer >= layers)
    bad("init_layer is " + std::to_string(init_layer) + "; use -1 (every layer) or 0.." + std::to_string(layers - 1));
  if (init_layers < 1 || init_layers > kMaxLayers)
    bad("init_layers is " + std::to_string(init_layers) + "; use 1..16 (layers seeded from init_layer down)");
  if (!(init_opacity > 0.f && init_opacity < 1.f)) bad("init_opacity must lie in (0, 1)");
  if (!(scale_cap >= 1.f && scale_cap <= 1024.f)) bad("scale_cap must lie in [1, 1024] (voxel edges)");
  if (scale_cap_layers < 1 || scale_cap_layers > kMaxLayers)
    bad("scale_cap_layers is " + std::to_string(scale_cap_layers) + "; use 1..16");
  const float min_cap = scale_cap_layers < layers ? 1.f : scale_cap;
  if (!(init_scale > 0.f && init_scale < min_cap)) {
    char cap[32];
    std::snprintf(cap, sizeof cap, "%g", static_cast<double>(min_cap));
    bad(std::string("init_scale must lie in (0, ") + cap +
        ") (a fraction of the voxel edge below the cap of every layer)");
  }
  if (!(init_feature >= 0.f) || !std::isfinite(init_feature)) bad("init_feature must be finite and >= 0");
  if (sh_degree < 0 || sh_degree > 3) bad("sh_degree is " + std::to_string(sh_degree) + "; use 0..3");
}

VoxelGrid VoxelGrid::from_bounds(const SceneBounds& bounds, const AnchorConfig& config, double top_voxel) {
  config.validate();
  if (!(top_voxel > 0) && config.voxel_size > 0) top_voxel = config.voxel_size;
  if (!(top_voxel > 0) && config.top_cells < 1)
    throw std::invalid_argument("VoxelGrid: top_cells is 0 (chosen from the scene): pass choose_top_voxel's edge");
  double extent = bounds.longest_extent();
  if (!(extent > 0) || !std::isfinite(extent)) extent = 2.0 * bounds.camera_radius;
  if (!(extent > 0) || !std::isfinite(extent))
    throw std::invalid_argument(
        "VoxelGrid: the scene bounds are empty (no spread of SfM points and no camera rig radius); "
        "cannot size the voxels");
  VoxelGrid g;
  g.origin = bounds.lo;
  g.top_voxel = top_voxel > 0 ? top_voxel : extent / config.top_cells;
  g.layer_ratio = config.layer_ratio;
  g.layers = config.layers;
  g.validate();
  return g;
}

void VoxelGrid::validate() const {
  if (!origin.allFinite() || !(top_voxel > 0) || !std::isfinite(top_voxel) || layer_ratio < 2 || layers < 1 ||
      layers > kMaxLayers)
    throw std::invalid_argument("VoxelGrid: origin must be finite, top_voxel > 0, layer_ratio >= 2, 1..16 layers");
}

double VoxelGrid::voxel(int layer) const {
  return top_voxel / static_cast<double>(int_pow(layer_ratio, layer));
}

Eigen::Vector3i VoxelGrid::cell_of(int layer, const Eigen::Vector3d& p) const {
  const double l = voxel(layer);
  Eigen::Vector3i c;
  for (int k = 0; k < 3; ++k) {
    double f = std::floor((p[k] - origin[k]) / l);
    f = std::clamp(f, -1073741824.0, 1073741824.0);  // also maps NaN below
    c[k] = std::isnan(f) ? -1073741824 : static_cast<int>(f);
  }
  return c;
}

Eigen::Vector3d VoxelGrid::centre(int layer, const Eigen::Vector3i& cell) const {
  const double l = voxel(layer);
  return origin + (cell.cast<double>().array() + 0.5).matrix() * l;
}

Eigen::Vector3i VoxelGrid::parent_cell(int layer, const Eigen::Vector3i& cell, int to_layer) const {
  if (to_layer > layer) throw std::invalid_argument("parent_cell: to_layer must not be finer than layer");
  const int64_t f = int_pow(layer_ratio, layer - to_layer);
  return Eigen::Vector3i(floor_div(cell.x(), f), floor_div(cell.y(), f), floor_div(cell.z(), f));
}

// ---------------------------------------------------------------- model

void AnchorModel::reset(const VoxelGrid& grid, const AnchorConfig& config) {
  config.validate();
  grid.validate();
  if (grid.layers != config.layers || grid.layer_ratio != config.layer_ratio)
    throw std::invalid_argument("AnchorModel: the grid's layers/layer_ratio (" + std::to_string(grid.layers) + "/" +
                                std::to_string(grid.layer_ratio) + ") differ from the config's (" +
                                std::to_string(config.layers) + "/" + std::to_string(config.layer_ratio) + ")");
  config_ = config;
  grid_ = grid;
  for (auto* v : {&pos_, &voxel_, &feature_, &offset_, &scale_logit_, &quat_, &opacity_logit_, &sh_}) v->clear();
  layer_.clear();
  cell_.clear();
  index_.clear();
}

AnchorInitStats AnchorModel::initialise_from_points(const std::vector<Eigen::Vector3d>& points,
                                                    const std::vector<Eigen::Vector3<uint8_t>>& colors,
                                                    const VoxelGrid& grid, const AnchorConfig& config, uint64_t seed,
                                                    size_t first_layer_only_from) {
  if (!colors.empty() && colors.size() != points.size())
    throw std::invalid_argument("initialise_from_points: " + std::to_string(colors.size()) + " colours for " +
                                std::to_string(points.size()) + " points");
  reset(grid, config);
  AnchorInitStats stats;
  stats.anchors_per_layer.assign(config.layers, 0);
  std::vector<uint8_t> skipped(points.size(), 0);
  const int first = config.init_layer < 0 ? 0 : config.init_layer;
  const int last = config.init_layer < 0 ? config.layers - 1
                                         : std::min(config.layers - 1, config.init_layer + config.init_layers - 1);
  for (int layer = first; layer <= last; ++layer) {
    // (voxel key, point index), sorted: the keys order like (layer, cell)
    // tuples and ties keep the point order, so colour sums run in a fixed order.
    std::vector<std::pair<uint64_t, uint32_t>> keyed;
    keyed.reserve(points.size());
    const size_t count = layer == first ? points.size() : std::min(points.size(), first_layer_only_from);
    for (size_t i = 0; i < count; ++i) {
      const Eigen::Vector3i c = grid.cell_of(layer, points[i]);
      if (!points[i].allFinite() || !cell_in_range(c)) {
        skipped[i] = 1;
        continue;
      }
      keyed.emplace_back(anchor_voxel_key(layer, c), static_cast<uint32_t>(i));
    }
    std::sort(keyed.begin(), keyed.end());
    for (size_t b = 0; b < keyed.size();) {
      size_t e = b;
      Eigen::Vector3d sum = Eigen::Vector3d::Zero();
      for (; e < keyed.size() && keyed[e].first == keyed[b].first; ++e)
        if (!colors.empty()) sum += colors[keyed[e].second].cast<double>() / 255.0;
      const Eigen::Vector3d mean =
          colors.empty() ? Eigen::Vector3d(Eigen::Vector3d::Constant(0.5)) : Eigen::Vector3d(sum / double(e - b));
      append_anchor(layer, grid.cell_of(layer, points[keyed[b].second]), seed, mean, -1);
      if (config.init_children_at_points) {
        // Children on the voxel's points (evenly spaced through them), each
        // with its point's colour; children beyond the points keep theirs.
        const size_t a = size() - 1, n = e - b, K = static_cast<size_t>(config.children);
        const size_t placed = std::min(n, K);
        const double l = voxel_[a];
        for (size_t i = 0; i < placed; ++i) {
          const uint32_t pt = keyed[b + i * n / placed].second;
          for (int k = 0; k < 3; ++k) {
            offset_[(a * K + i) * 3 + k] = static_cast<float>((points[pt][k] - pos_[3 * a + k]) / l);
            if (!colors.empty())
              sh_[(a * K + i) * kAnchorShCoeffs * 3 + k] = static_cast<float>((colors[pt][k] / 255.0 - 0.5) / kShC0);
          }
        }
      }
      ++stats.anchors_per_layer[layer];
      b = e;
    }
  }
  for (uint8_t s : skipped) (s ? stats.points_skipped : stats.points_used)++;
  return stats;
}

void AnchorModel::append_anchor(int layer, const Eigen::Vector3i& cell, uint64_t seed, const Eigen::Vector3d& colour,
                                int64_t parent_child, double parent_scale_divisor) {
  const int K = config_.children;
  const uint64_t key = anchor_voxel_key(layer, cell);
  // Copy the parent's values first: the vectors below may reallocate.
  float parent_feature[3] = {0, 0, 0}, parent_quat[4] = {1, 0, 0, 0}, parent_opacity = 0;
  float parent_sh[kAnchorShCoeffs * 3] = {};
  const float init_logit = static_cast<float>(logit(double(config_.init_scale) / config_.cap(layer)));
  float scale_logit[3] = {init_logit, init_logit, init_logit};
  if (parent_child >= 0) {
    const size_t pa = static_cast<size_t>(parent_child) / K, pc = static_cast<size_t>(parent_child);
    std::copy_n(&feature_[pa * 3], 3, parent_feature);
    std::copy_n(&quat_[pc * 4], 4, parent_quat);
    parent_opacity = opacity_logit_[pc];
    std::copy_n(&sh_[pc * kAnchorShCoeffs * 3], kAnchorShCoeffs * 3, parent_sh);
    if (parent_scale_divisor > 0) {
      // The parent's world scale over the divisor, in the new voxel's units.
      const double parent_extent = double(config_.cap(layer_[pa])) * voxel_[pa];
      const double extent = double(config_.cap(layer)) * grid_.voxel(layer);
      for (int k = 0; k < 3; ++k) {
        const double world = sigmoid(scale_logit_[pc * 3 + k]) * parent_extent / parent_scale_divisor;
        const double least = double(config_.init_scale) / config_.cap(layer);
        const double u = std::clamp(world / extent, least, std::max(least, 0.9));
        scale_logit[k] = static_cast<float>(logit(u));
      }
    }
  }

  index_.emplace(key, static_cast<int>(size()));
  const Eigen::Vector3d centre = grid_.centre(layer, cell);
  for (int k = 0; k < 3; ++k) {
    pos_.push_back(static_cast<float>(centre[k]));
    cell_.push_back(cell[k]);
    feature_.push_back(
        parent_child >= 0
            ? parent_feature[k]
            : static_cast<float>(config_.init_feature * (2.0 * anchor_uniform01(seed, key, -1, kFeatureX + k) - 1.0)));
  }
  layer_.push_back(layer);
  voxel_.push_back(static_cast<float>(grid_.voxel(layer)));

  const float opacity_logit = static_cast<float>(logit(config_.init_opacity));
  for (int i = 0; i < K; ++i) {
    for (int k = 0; k < 3; ++k) {
      offset_.push_back(static_cast<float>(anchor_uniform01(seed, key, i, kOffsetX + k) - 0.5));
      scale_logit_.push_back(scale_logit[k]);
    }
    if (parent_child >= 0) {
      quat_.insert(quat_.end(), parent_quat, parent_quat + 4);
      opacity_logit_.push_back(std::min(parent_opacity, opacity_logit));
      sh_.insert(sh_.end(), parent_sh, parent_sh + kAnchorShCoeffs * 3);
      continue;
    }
    Eigen::Vector4d q(1, 0, 0, 0);
    for (int k = 0; k < 3; ++k) q[1 + k] = kQuatPerturbation * (2.0 * anchor_uniform01(seed, key, i, kQuatX + k) - 1.0);
    q.normalize();
    for (int k = 0; k < 4; ++k) quat_.push_back(static_cast<float>(q[k]));
    opacity_logit_.push_back(opacity_logit);
    for (int k = 0; k < 3; ++k) sh_.push_back(static_cast<float>((colour[k] - 0.5) / kShC0));
    sh_.insert(sh_.end(), (kAnchorShCoeffs - 1) * 3, 0.f);
  }
}

int AnchorModel::add_anchor(int layer, const Eigen::Vector3i& cell, int64_t parent_child, uint64_t seed,
                            double parent_scale_divisor) {
  if (layer < 0 || layer >= config_.layers)
    throw std::out_of_range("add_anchor: layer " + std::to_string(layer) + " is outside 0.." +
                            std::to_string(config_.layers - 1));
  if (parent_child < -1 || (parent_child >= 0 && static_cast<size_t>(parent_child) >= gaussians()))
    throw std::out_of_range("add_anchor: parent child " + std::to_string(parent_child) + " is outside -1.." +
                            std::to_string(static_cast<int64_t>(gaussians()) - 1));
  if (!cell_in_range(cell) || find(layer, cell) >= 0) return -1;
  append_anchor(layer, cell, seed, Eigen::Vector3d::Constant(0.5), parent_child, parent_scale_divisor);
  return static_cast<int>(size()) - 1;
}

int AnchorModel::find(int layer, const Eigen::Vector3i& cell) const {
  if (layer < 0 || layer >= kMaxLayers || !cell_in_range(cell)) return -1;
  auto it = index_.find(anchor_voxel_key(layer, cell));
  return it == index_.end() ? -1 : it->second;
}

std::vector<int> AnchorModel::remove_anchors(const std::vector<uint8_t>& keep) {
  if (keep.size() != size())
    throw std::invalid_argument("remove_anchors: keep mask has " + std::to_string(keep.size()) + " entries for " +
                                std::to_string(size()) + " anchors");
  const size_t K = static_cast<size_t>(config_.children);
  std::vector<int> kept;
  // Moves row `from` to row `to` (to <= from) of an array with `per` values per row.
  auto move_row = [](auto& v, size_t per, size_t from, size_t to) {
    if (from != to) std::copy_n(v.begin() + from * per, per, v.begin() + to * per);
  };
  size_t n = 0;
  for (size_t a = 0; a < keep.size(); ++a) {
    if (!keep[a]) continue;
    kept.push_back(static_cast<int>(a));
    move_row(pos_, 3, a, n);
    move_row(cell_, 3, a, n);
    move_row(feature_, 3, a, n);
    move_row(layer_, 1, a, n);
    move_row(voxel_, 1, a, n);
    move_row(offset_, 3 * K, a, n);
    move_row(scale_logit_, 3 * K, a, n);
    move_row(quat_, 4 * K, a, n);
    move_row(opacity_logit_, K, a, n);
    move_row(sh_, kAnchorShCoeffs * 3 * K, a, n);
    ++n;
  }
  pos_.resize(n * 3);
  cell_.resize(n * 3);
  feature_.resize(n * 3);
  layer_.resize(n);
  voxel_.resize(n);
  offset_.resize(n * 3 * K);
  scale_logit_.resize(n * 3 * K);
  quat_.resize(n * 4 * K);
  opacity_logit_.resize(n * K);
  sh_.resize(n * kAnchorShCoeffs * 3 * K);
  rebuild_index();
  return kept;
}

void AnchorModel::rebuild_index() {
  index_.clear();
  index_.reserve(size());
  for (size_t a = 0; a < size(); ++a) {
    const Eigen::Vector3i c(cell_[3 * a], cell_[3 * a + 1], cell_[3 * a + 2]);
    index_.emplace(anchor_voxel_key(layer_[a], c), static_cast<int>(a));
  }
}

std::vector<int> AnchorModel::child_rows(const std::vector<int>& anchor_rows, int children) {
  std::vector<int> rows;
  rows.reserve(anchor_rows.size() * children);
  for (int a : anchor_rows)
    for (int i = 0; i < children; ++i) rows.push_back(a < 0 ? -1 : a * children + i);
  return rows;
}

void AnchorModel::check() const {
  const size_t A = size(), N = gaussians();
  auto need = [](const char* name, size_t actual, size_t expected) {
    if (actual != expected)
      throw std::logic_error(std::string("AnchorModel: '") + name + "' holds " + std::to_string(actual) +
                             " values, expected " + std::to_string(expected));
  };
  need("pos", pos_.size(), A * 3);
  need("cell", cell_.size(), A * 3);
  need("voxel", voxel_.size(), A);
  need("feature", feature_.size(), A * 3);
  need("offset", offset_.size(), N * 3);
  need("scale_logit", scale_logit_.size(), N * 3);
  need("quat", quat_.size(), N * 4);
  need("opacity_logit", opacity_logit_.size(), N);
  need("sh", sh_.size(), N * kAnchorShCoeffs * 3);
}

// ---------------------------------------------------------------- archive

void AnchorModel::to_archive(ModelArchive& archive) const {
  check();
  const int64_t A = static_cast<int64_t>(size()), K = config_.children;
  archive.put("anchors/pos", pos_, {A, 3});
  archive.put("anchors/layer", layer_, {A});
  archive.put("anchors/cell", cell_, {A, 3});
  archive.put("anchors/voxel", voxel_, {A});
  archive.put("anchors/feature", feature_, {A, 3});
  archive.put("anchors/offset", offset_, {A, K, 3});
  archive.put("anchors/scale_logit", scale_logit_, {A, K, 3});
  archive.put("anchors/quat", quat_, {A, K, 4});
  archive.put("anchors/opacity_logit", opacity_logit_, {A, K});
  archive.put("anchors/sh", sh_, {A, K, kAnchorShCoeffs, 3});
  const AnchorConfig& c = config_;
  archive.meta["anchors"] = {{"format", 1},
                             {"count", A},
                             {"config",
                              {{"children", c.children},
                               {"layers", c.layers},
                               {"top_cells", c.top_cells},
                               {"voxel_size", c.voxel_size},
                               {"layer_ratio", c.layer_ratio},
                               {"init_layer", c.init_layer},
                               {"init_layers", c.init_layers},
                               {"init_children_at_points", c.init_children_at_points},
                               {"init_opacity", c.init_opacity},
                               {"init_scale", c.init_scale},
                               {"scale_cap", c.scale_cap},
                               {"scale_cap_layers", c.scale_cap_layers},
                               {"init_feature", c.init_feature},
                               {"sh_degree", c.sh_degree}}},
                             {"grid",
                              {{"origin", {grid_.origin.x(), grid_.origin.y(), grid_.origin.z()}},
                               {"top_voxel", grid_.top_voxel},
                               {"layer_ratio", grid_.layer_ratio},
                               {"layers", grid_.layers}}}};
}

AnchorModel AnchorModel::from_archive(const ModelArchive& archive) {
  if (!archive.meta.contains("anchors")) fail_archive(archive, "the archive has no meta entry 'anchors'");
  AnchorConfig c;
  VoxelGrid g;
  try {
    const nlohmann::json& m = archive.meta.at("anchors");
    if (m.at("format").get<int>() != 1)
      fail_archive(archive, "meta 'anchors' has format " + m.at("format").dump() + "; this build reads format 1");
    const nlohmann::json& jc = m.at("config");
    c.children = jc.at("children").get<int>();
    c.layers = jc.at("layers").get<int>();
    c.top_cells = jc.at("top_cells").get<int>();
    c.voxel_size = jc.value("voxel_size", 0.0);
    c.layer_ratio = jc.at("layer_ratio").get<int>();
    c.init_layer = jc.at("init_layer").get<int>();
    c.init_layers = jc.value("init_layers", 1);
    c.init_children_at_points = jc.value("init_children_at_points", false);
    c.init_opacity = jc.at("init_opacity").get<float>();
    c.init_scale = jc.at("init_scale").get<float>();
    c.scale_cap = jc.value("scale_cap", 1.f);
    c.scale_cap_layers = jc.value("scale_cap_layers", kMaxLayers);
    c.init_feature = jc.at("init_feature").get<float>();
    c.sh_degree = jc.at("sh_degree").get<int>();
    const nlohmann::json& jg = m.at("grid");
    for (int k = 0; k < 3; ++k) g.origin[k] = jg.at("origin").at(k).get<double>();
    g.top_voxel = jg.at("top_voxel").get<double>();
    g.layer_ratio = jg.at("layer_ratio").get<int>();
    g.layers = jg.at("layers").get<int>();
  } catch (const nlohmann::json::exception& e) {
    fail_archive(archive, std::string("meta 'anchors' is incomplete or mistyped: ") + json_error_text(e));
  }
  AnchorModel model;
  try {
    model.reset(g, c);
  } catch (const std::invalid_argument& e) {
    fail_archive(archive, std::string("meta 'anchors': ") + e.what());
  }

  // Shapes: A from pos, K from the config; get() names the array on mismatch.
  const Tensor& pos = archive.tensor("anchors/pos");
  if (pos.shape.size() != 2 || pos.shape[1] != 3) fail_archive(archive, "array 'anchors/pos' must have shape [A,3]");
  const int64_t A = pos.shape[0], K = c.children;
  model.pos_ = archive.get<float>("anchors/pos", {A, 3});
  model.layer_ = archive.get<int32_t>("anchors/layer", {A});
  model.cell_ = archive.get<int32_t>("anchors/cell", {A, 3});
  model.voxel_ = archive.get<float>("anchors/voxel", {A});
  model.feature_ = archive.get<float>("anchors/feature", {A, 3});
  model.offset_ = archive.get<float>("anchors/offset", {A, K, 3});
  model.scale_logit_ = archive.get<float>("anchors/scale_logit", {A, K, 3});
  model.quat_ = archive.get<float>("anchors/quat", {A, K, 4});
  model.opacity_logit_ = archive.get<float>("anchors/opacity_logit", {A, K});
  model.sh_ = archive.get<float>("anchors/sh", {A, K, kAnchorShCoeffs, 3});
  // Every parameter finite: a NaN or an infinity would otherwise pass through
  // queries, removal, training and export without a word.
  for (const auto& [name, values] :
       {std::pair<const char*, const std::vector<float>*>{"anchors/feature", &model.feature_},
        {"anchors/offset", &model.offset_},
        {"anchors/scale_logit", &model.scale_logit_},
        {"anchors/quat", &model.quat_},
        {"anchors/opacity_logit", &model.opacity_logit_},
        {"anchors/sh", &model.sh_}})
    for (size_t i = 0; i < values->size(); ++i)
      if (!std::isfinite((*values)[i]))
        fail_archive(archive, std::string("array '") + name + "': element " + std::to_string(i) + " is " +
                                  (std::isnan((*values)[i]) ? "NaN" : "infinite") +
                                  "; the model is damaged: train it again, or resume from an earlier checkpoint");

  // Geometry: layers and cells in range, each voxel once, pos and voxel as the grid says.
  for (int64_t a = 0; a < A; ++a) {
    const std::string at = " of anchor " + std::to_string(a);
    const int layer = model.layer_[a];
    if (layer < 0 || layer >= c.layers)
      fail_archive(archive, "array 'anchors/layer': layer " + std::to_string(layer) + at + " is outside 0.." +
                                std::to_string(c.layers - 1));
    const Eigen::Vector3i cell(model.cell_[3 * a], model.cell_[3 * a + 1], model.cell_[3 * a + 2]);
    if (!cell_in_range(cell)) fail_archive(archive, "array 'anchors/cell': the cell" + at + " is outside +-2^19");
    auto [it, fresh] = model.index_.emplace(anchor_voxel_key(layer, cell), static_cast<int>(a));
    if (!fresh)
      fail_archive(archive, "array 'anchors/cell': anchors " + std::to_string(it->second) + " and " +
                                std::to_string(a) + " share layer " + std::to_string(layer) + " and cell (" +
                                std::to_string(cell.x()) + ", " + std::to_string(cell.y()) + ", " +
                                std::to_string(cell.z()) + ")");
    const Eigen::Vector3d centre = g.centre(layer, cell);
    for (int k = 0; k < 3; ++k)
      if (model.pos_[3 * a + k] != static_cast<float>(centre[k]))
        fail_archive(archive, "array 'anchors/pos': the position" + at + " is not the centre of its voxel");
    if (model.voxel_[a] != static_cast<float>(g.voxel(layer)))
      fail_archive(archive, "array 'anchors/voxel': the edge" + at + " differs from its layer's voxel size");
  }
  return model;
}

// ---------------------------------------------------------------- reference expansion

ExpandedGaussians expand_reference_double(const AnchorModel& model, int active_sh_degree) {
  if (active_sh_degree < 0 || active_sh_degree > model.config().sh_degree)
    throw std::invalid_argument("expand: active SH degree " + std::to_string(active_sh_degree) + " is outside 0.." +
                                std::to_string(model.config().sh_degree));
  model.check();
  const size_t K = static_cast<size_t>(model.children()), N = model.gaussians();
  const int S = sh_coeffs_for_degree(active_sh_degree);
  ExpandedGaussians e;
  e.sh_degree = active_sh_degree;
  e.means.resize(N * 3);
  e.scales.resize(N * 3);
  e.quats.resize(N * 4);
  e.opacities.resize(N);
  e.sh.resize(N * S * 3);
  e.features.resize(N * 3);
  for (size_t g = 0; g < N; ++g) {
    const size_t a = g / K;
    const double l = model.voxel()[a];
    for (int k = 0; k < 3; ++k) {
      e.means[3 * g + k] = double(model.pos()[3 * a + k]) + double(model.offset()[3 * g + k]) * l;
      e.scales[3 * g + k] = sigmoid(model.scale_logit()[3 * g + k]) * (l * model.config().cap(model.layer()[a]));
      e.features[3 * g + k] = model.feature()[3 * a + k];
    }
    for (int k = 0; k < 4; ++k) e.quats[4 * g + k] = model.quat()[4 * g + k];
    e.opacities[g] = sigmoid(model.opacity_logit()[g]);
    for (int j = 0; j < S * 3; ++j) e.sh[g * S * 3 + j] = model.sh()[g * kAnchorShCoeffs * 3 + j];
  }
  return e;
}

GaussianSet ExpandedGaussians::to_float() const {
  GaussianSet s;
  s.sh_degree = sh_degree;
  auto cast = [](const std::vector<double>& v) { return std::vector<float>(v.begin(), v.end()); };
  s.means = cast(means);
  s.scales = cast(scales);
  s.quats = cast(quats);
  s.opacities = cast(opacities);
  s.sh = cast(sh);
  s.features = cast(features);
  return s;
}

GaussianSet expand_reference(const AnchorModel& model, int active_sh_degree) {
  return expand_reference_double(model, active_sh_degree).to_float();
}

}  // namespace ag2gs
