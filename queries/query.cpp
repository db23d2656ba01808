#include "queries/query.h"

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <deque>
#include <limits>
#include <numeric>
#include <sstream>
#include <stdexcept>
#include <unordered_map>

#include "host/core/quantile.h"
#include "host/core/timing.h"
#include "queries/query_settings.h"

namespace ag2gs {

namespace {

}  // namespace

// ------------------------------------------------------------------ config

nlohmann::json QueryConfig::to_json() const {
  return settings_to_json(query_settings(), *this);
}

void QueryConfig::validate() const {
  // Each setting's range: queries/query_settings.cpp.
  if (const std::string p = settings_problem(query_settings(), *this); !p.empty())
    throw std::invalid_argument("query config: " + p);
}

double QueryConfig::equivalent_distance() const {
  return static_cast<double>(tau) * std::sqrt(-2.0 * std::log(static_cast<double>(min_weight)));
}

// ------------------------------------------------------------------ k-d tree

PointKdTree::PointKdTree(const std::vector<float>& points) : points_(points) {
  if (points.size() % 3 != 0) throw std::invalid_argument("PointKdTree: points must be [n,3]");
  const size_t n = points.size() / 3;
  if (n > static_cast<size_t>(std::numeric_limits<int32_t>::max()))
    throw std::invalid_argument("PointKdTree: too many points");
  for (size_t i = 0; i < n; ++i) {
    if (std::isfinite(points[3 * i]) && std::isfinite(points[3 * i + 1]) && std::isfinite(points[3 * i + 2]))
      ids_.push_back(static_cast<int32_t>(i));
  }
  nodes_.reserve(2 * (ids_.size() / 8 + 1));
  if (!ids_.empty()) build(0, static_cast<int>(ids_.size()));
}

int PointKdTree::build(int lo, int hi) {
  const int me = static_cast<int>(nodes_.size());
  nodes_.push_back({});
  nodes_[me].lo = lo;
  nodes_[me].hi = hi;
  if (hi - lo <= 8) return me;
  float mn[3] = {std::numeric_limits<float>::max(), std::numeric_limits<float>::max(),
                 std::numeric_limits<float>::max()};
  float mx[3] = {-mn[0], -mn[1], -mn[2]};
  for (int k = lo; k < hi; ++k)
    for (int c = 0; c < 3; ++c) {
      mn[c] = std::min(mn[c], points_[3 * ids_[k] + c]);
      mx[c] = std::max(mx[c], points_[3 * ids_[k] + c]);
    }
  int axis = 0;
  for (int c = 1; c < 3; ++c)
    if (mx[c] - mn[c] > mx[axis] - mn[axis]) axis = c;
  if (mx[axis] == mn[axis]) return me;  // all points equal: a leaf
  const int mid = lo + (hi - lo) / 2;
  // Order by (coordinate, id): the split does not depend on the sort's stability.
  std::nth_element(ids_.begin() + lo, ids_.begin() + mid, ids_.begin() + hi, [&](int32_t a, int32_t b) {
    const float pa = points_[3 * a + axis], pb = points_[3 * b + axis];
    return pa < pb || (pa == pb && a < b);
  });
  const float split = points_[3 * ids_[mid] + axis];
  const int left = build(lo, mid);
  const int right = build(mid, hi);
  nodes_[me].axis = axis;
  nodes_[me].split = split;
  nodes_[me].left = left;
  nodes_[me].right = right;
  return me;
}

void PointKdTree::search(int node, const Eigen::Vector3d& p, int* best, double* best_d2) const {
  const Node& nd = nodes_[node];
  if (nd.axis < 0) {
    for (int k = nd.lo; k < nd.hi; ++k) {
      const int id = ids_[k];
      const double dx = p[0] - points_[3 * id], dy = p[1] - points_[3 * id + 1], dz = p[2] - points_[3 * id + 2];
      const double d2 = dx * dx + dy * dy + dz * dz;
      if (d2 < *best_d2 || (d2 == *best_d2 && id < *best)) {
        *best_d2 = d2;
        *best = id;
      }
    }
    return;
  }
  // Points left of the split have coordinate <= split, right ones >= split.
  const double diff = p[nd.axis] - static_cast<double>(nd.split);
  const int near = diff < 0 ? nd.left : nd.right;
  const int far = diff < 0 ? nd.right : nd.left;
  search(near, p, best, best_d2);
  if (diff * diff <= *best_d2) search(far, p, best, best_d2);
}

void PointKdTree::search_k(int node, const Eigen::Vector3d& p, size_t k,
                           std::vector<std::pair<double, int>>* heap) const {
  const Node& nd = nodes_[node];
  if (nd.axis < 0) {
    for (int i = nd.lo; i < nd.hi; ++i) {
      const int id = ids_[i];
      const double dx = p[0] - points_[3 * id], dy = p[1] - points_[3 * id + 1], dz = p[2] - points_[3 * id + 2];
      const std::pair<double, int> e(dx * dx + dy * dy + dz * dz, id);
      if (heap->size() < k) {
        heap->push_back(e);
        std::push_heap(heap->begin(), heap->end());
      } else if (e < heap->front()) {
        std::pop_heap(heap->begin(), heap->end());
        heap->back() = e;
        std::push_heap(heap->begin(), heap->end());
      }
    }
    return;
  }
  const double diff = p[nd.axis] - static_cast<double>(nd.split);
  search_k(diff < 0 ? nd.left : nd.right, p, k, heap);
  if (heap->size() < k || diff * diff <= heap->front().first) search_k(diff < 0 ? nd.right : nd.left, p, k, heap);
}

std::vector<int> PointKdTree::nearest_k(const Eigen::Vector3d& p, int k) const {
  std::vector<std::pair<double, int>> heap;
  if (k <= 0 || nodes_.empty()) return {};
  search_k(0, p, static_cast<size_t>(k), &heap);
  std::sort(heap.begin(), heap.end());
  std::vector<int> out;
  for (const auto& e : heap) out.push_back(e.second);
  return out;
}

int PointKdTree::nearest(const Eigen::Vector3d& p, double* dist2) const {
  int best = -1;
  double best_d2 = std::numeric_limits<double>::infinity();
  if (!ids_.empty() && p.allFinite()) search(0, p, &best, &best_d2);
  if (dist2) *dist2 = best_d2;
  return best;
}

// ------------------------------------------------------------------ growing

std::vector<int32_t> region_grow(const AnchorGraph& graph, const std::vector<float>& features,
                                 const std::vector<int32_t>& seeds, float tau, float min_weight) {
  const size_t a = graph.anchors();
  if (features.size() != 3 * a)
    throw std::invalid_argument("region_grow: features hold " + std::to_string(features.size() / 3) +
                                " anchors, the graph " + std::to_string(a) + " (rebuild the graph for this model)");
  std::vector<uint8_t> in(a, 0);
  std::vector<int32_t> sorted_seeds = seeds;
  std::sort(sorted_seeds.begin(), sorted_seeds.end());
  std::deque<int32_t> queue;
  for (int32_t s : sorted_seeds) {
    if (s < 0 || static_cast<size_t>(s) >= a)
      throw std::invalid_argument("region_grow: seed " + std::to_string(s) + " is not an anchor id (0.." +
                                  std::to_string(a) + ")");
    if (!in[s]) {
      in[s] = 1;
      queue.push_back(s);
    }
  }
  const double inv_two_tau2 = 1.0 / (2.0 * static_cast<double>(tau) * tau);
  const auto& off = graph.row_offsets();
  const auto& nb = graph.neighbours();
  while (!queue.empty()) {
    const int32_t i = queue.front();
    queue.pop_front();
    const float* fi = &features[3 * static_cast<size_t>(i)];
    for (int32_t e = off[i]; e < off[i + 1]; ++e) {
      const int32_t j = nb[e];
      if (in[j]) continue;
      const float* fj = &features[3 * static_cast<size_t>(j)];
      double d2 = 0;
      for (int c = 0; c < 3; ++c) {
        const double d = static_cast<double>(fi[c]) - fj[c];
        d2 += d * d;
      }
      if (std::exp(-d2 * inv_two_tau2) > static_cast<double>(min_weight)) {
        in[j] = 1;
        queue.push_back(j);
      }
    }
  }
  std::vector<int32_t> out;
  for (size_t i = 0; i < a; ++i)
    if (in[i]) out.push_back(static_cast<int32_t>(i));
  return out;
}

std::vector<double> text_scores(const LanguageFeatures& language, const std::vector<float>& embedding) {
  if (static_cast<int>(embedding.size()) != language.dim)
    throw std::invalid_argument("the text embedding has " + std::to_string(embedding.size()) +
                                " dimensions, the model's language features " + std::to_string(language.dim) +
                                " (use an embedding from the CLIP model that made the scene's features)");
  double en = 0;
  for (float v : embedding) en += static_cast<double>(v) * v;
  en = std::sqrt(en);
  if (!(en > 0) || !std::isfinite(en))
    throw std::invalid_argument("the text embedding is zero or not finite");
  const int d = language.dim;
  std::vector<double> scores(language.clusters(), std::numeric_limits<double>::quiet_NaN());
  for (int c = 0; c < language.clusters(); ++c) {
    if (language.matches[c] <= 0) continue;
    const float* f = &language.features[static_cast<size_t>(c) * d];
    double dot = 0, fn = 0;
    for (int k = 0; k < d; ++k) {
      dot += static_cast<double>(f[k]) * embedding[k];
      fn += static_cast<double>(f[k]) * f[k];
    }
    if (fn > 0) scores[c] = dot / (std::sqrt(fn) * en);
  }
  return scores;
}

// ------------------------------------------------------------------ engine

QueryEngine::QueryEngine(Runtime& rt, const AnchorModel& model, const QueryConfig& config)
    : rt_(rt), model_(model), config_(config), renderer_(rt), device_(rt) {
  config_.validate();
  const auto t0 = std::chrono::steady_clock::now();
  graph_ = AnchorGraph::build(model, config_.graph_cell_scale);
  tree_ = PointKdTree(model.pos());
  gaussians_ = expand_reference(model, 0);
  device_.upload(gaussians_);
  selection_features_ = gaussians_.features;
  // One small render compiles the renderer's kernels now, so that the first
  // query's latency is the query's own.
  Camera warm;
  warm.width = warm.height = 16;
  warm.fx = warm.fy = 16;
  warm.cx = warm.cy = 8;
  renderer_.forward(device_, warm, RenderSettings{});
  prepare_ms_ = ms_since(t0);
}

void QueryEngine::set_language(const Clustering& clustering, const LanguageFeatures& language) {
  if (clustering.anchor_cluster.size() != model_.size())
    throw std::invalid_argument("the clustering covers " + std::to_string(clustering.anchor_cluster.size()) +
                                " anchors, the model has " + std::to_string(model_.size()) + " (re-run stage 3)");
  if (language.clusters() != clustering.clusters())
    throw std::invalid_argument("language features for " + std::to_string(language.clusters()) +
                                " clusters, the clustering has " + std::to_string(clustering.clusters()) +
                                " (re-run stage 3)");
  clustering_ = clustering;
  language_ = language;
  have_language_ = true;
}

std::vector<int32_t> similar_anchors(const std::vector<float>& features, const std::vector<float>& seed_features,
                                     double max_distance) {
  if (features.size() % 3 != 0 || seed_features.size() % 3 != 0)
    throw std::invalid_argument("similar_anchors: features and seed features must be [n,3]");
  const double d2max = max_distance * max_distance;
  std::vector<int32_t> out;
  for (size_t a = 0; a < features.size() / 3; ++a) {
    for (size_t s = 0; s < seed_features.size() / 3; ++s) {
      double d2 = 0;
      for (int k = 0; k < 3; ++k) {
        const double x = static_cast<double>(features[3 * a + k]) - seed_features[3 * s + k];
        d2 += x * x;
      }
      if (d2 < d2max) {
        out.push_back(static_cast<int32_t>(a));
        break;
      }
    }
  }
  return out;
}

Eigen::Vector2d full_size_click(const Camera& full, const Camera& camera, double x, double y) {
  return {(std::floor(x) + 0.5) * camera.width / full.width, (std::floor(y) + 0.5) * camera.height / full.height};
}

namespace {

// The feature group of anchors that holds the most of a pixel's blending
// weight (see QueryEngine::click): anchors in order of first appearance
// along the ray, each joining the first group whose first anchor passes the
// growing rule with it. Ties go to the nearer group.
struct DominantGroup {
  int32_t anchor = -1;  // the group's heaviest anchor, -1 when nothing blends
  double weight = 0;    // the group's blending weight
  double depth = 0;     // its weighted mean depth
};

DominantGroup dominant_group(const std::vector<Renderer::PixelContribution>& contrib, const AnchorModel& model,
                             float tau, float min_weight, float front_weight) {
  const uint32_t K = static_cast<uint32_t>(model.children());
  struct AnchorSum {
    uint32_t anchor;
    double weight = 0, weighted_depth = 0;
  };
  std::vector<AnchorSum> anchors;
  std::unordered_map<uint32_t, size_t> index;
  for (const auto& c : contrib) {
    const uint32_t a = c.gaussian / K;
    auto [it, fresh] = index.emplace(a, anchors.size());
    if (fresh) anchors.push_back({a});
    anchors[it->second].weight += c.weight;
    anchors[it->second].weighted_depth += static_cast<double>(c.weight) * c.depth;
  }
  struct Group {
    const float* feature;  // the first anchor's
    double weight = 0, weighted_depth = 0;
    const AnchorSum* heaviest = nullptr;
  };
  std::vector<Group> groups;
  const double inv_2tau2 = 1.0 / (2.0 * double(tau) * tau);
  for (const AnchorSum& e : anchors) {
    const float* f = &model.feature()[3 * static_cast<size_t>(e.anchor)];
    size_t home = 0;
    for (; home < groups.size(); ++home) {
      double d2 = 0;
      for (int c = 0; c < 3; ++c) d2 += (double(f[c]) - groups[home].feature[c]) * (double(f[c]) - groups[home].feature[c]);
      if (std::exp(-d2 * inv_2tau2) > min_weight) break;
    }
    if (home == groups.size()) groups.push_back({f});
    Group& g = groups[home];
    g.weight += e.weight;
    g.weighted_depth += e.weighted_depth;
    if (!g.heaviest || e.weight > g.heaviest->weight) g.heaviest = &e;
  }
  DominantGroup out;
  const Group* top = nullptr;
  if (front_weight > 0)
    for (const Group& g : groups)  // in order of first appearance along the ray
      if (g.weight >= front_weight) {
        top = &g;
        break;
      }
  if (!top)  // the heaviest (also when no group reaches front_weight)
    for (const Group& g : groups)
      if (!top || g.weight > top->weight) top = &g;
  if (top && top->weight > 0) {
    out.anchor = static_cast<int32_t>(top->heaviest->anchor);
    out.weight = top->weight;
    out.depth = top->weighted_depth / top->weight;
  }
  return out;
}

}  // namespace

ClickResult QueryEngine::click(const Camera& camera, double x, double y) {
  const auto t0 = std::chrono::steady_clock::now();
  camera.validate();
  if (!(x >= 0 && y >= 0 && x < camera.width && y < camera.height))
    throw std::invalid_argument("click (" + std::to_string(x) + ", " + std::to_string(y) + ") is outside the " +
                                std::to_string(camera.width) + "x" + std::to_string(camera.height) + " image of view " +
                                (camera.name.empty() ? std::string("?") : camera.name) +
                                " (x in [0, width), y in [0, height), pixels at the loaded resolution)");
  ClickResult r;
  r.pixel_x = static_cast<int>(std::floor(x));
  r.pixel_y = static_cast<int>(std::floor(y));
  RenderSettings settings;
  settings.sh_degree = 0;
  if (!features_are_model_) {  // mask() left selection weights there
    device_.features.upload(gaussians_.features);
    features_are_model_ = true;
  }
  renderer_.forward(device_, camera, settings);
  const RenderOutput out = renderer_.download_output();
  const size_t p = static_cast<size_t>(r.pixel_y) * out.width + r.pixel_x;
  r.alpha = out.alpha[p];
  if (!(r.alpha >= config_.min_click_alpha)) {
    std::ostringstream msg;
    msg << "the click at pixel (" << r.pixel_x << ", " << r.pixel_y << ") of view "
        << (camera.name.empty() ? std::string("?") : camera.name) << " hits the background: rendered alpha "
        << r.alpha << " < " << config_.min_click_alpha << "; click on an object";
    throw std::runtime_error(msg.str());
  }
  // What the pixel shows: the anchors blended there, grouped by feature with
  // the region-growing rule (a group's first anchor and another join when
  // their bilateral weight exceeds min_weight), and the group holding the
  // most blending weight; its weighted mean depth, and the feature of its
  // heaviest anchor. Not the ray's means, which on a thin or half-transparent
  // object (a pole in front of a wall) fall between the object and what lies
  // behind it; and by group, since such an object's weight is spread over
  // several anchors, none of which alone outweighs the wall.
  r.depth = out.depth[p] / r.alpha;
  r.pixel_feature = {out.feature[3 * p] / static_cast<float>(r.alpha), out.feature[3 * p + 1] / static_cast<float>(r.alpha),
                     out.feature[3 * p + 2] / static_cast<float>(r.alpha)};
  if (config_.click_dominant) {
    const DominantGroup top =
        dominant_group(renderer_.pixel_contributions(r.pixel_x, r.pixel_y), model_, config_.tau, config_.min_weight,
                       config_.click_front_weight);
    if (top.anchor >= 0) {
      r.dominant_anchor = top.anchor;
      r.dominant_weight = top.weight;
      r.depth = top.depth;
      for (int c = 0; c < 3; ++c) r.pixel_feature[c] = model_.feature()[3 * static_cast<size_t>(top.anchor) + c];
    }
  }
  if (support_) {  // the ray's median depth (contributions come front to back)
    double acc = 0;
    for (const auto& c : renderer_.pixel_contributions(r.pixel_x, r.pixel_y)) {
      acc += c.weight;
      r.depth = c.depth;
      if (acc >= 0.5 * r.alpha) break;
    }
  }
  const double u = r.pixel_x + 0.5, v = r.pixel_y + 0.5;
  const Eigen::Vector3d xc((u - camera.cx) / camera.fx * r.depth, (v - camera.cy) / camera.fy * r.depth, r.depth);
  r.point = camera.R.transpose() * (xc - camera.t);
  if (support_) {
    r.seed = tree_.nearest(r.point);
    if (r.seed < 0) throw std::runtime_error("the model has no anchors to select");
    const float* c = &model_.pos()[3 * static_cast<size_t>(r.seed)];
    r.seed_distance = (r.point - Eigen::Vector3d(c[0], c[1], c[2])).norm();
    r.selected = support_grow(model_, *support_, r.seed);
    if (r.selected.empty()) {
      std::ostringstream msg;
      msg << "the click at pixel (" << r.pixel_x << ", " << r.pixel_y << ") of view "
          << (camera.name.empty() ? std::string("?") : camera.name) << " hits the support plane itself (height "
          << support_->height(r.point) << " over it); click on an object standing on it";
      throw std::runtime_error(msg.str());
    }
    r.ms = ms_since(t0);
    return r;
  }
  const std::vector<int> candidates = tree_.nearest_k(r.point, config_.click_candidates);
  if (candidates.empty()) throw std::runtime_error("the model has no anchors to select");
  double best = std::numeric_limits<double>::infinity();
  for (int a : candidates) {  // nearest first: ties keep the nearer
    double d2 = 0;
    for (int c = 0; c < 3; ++c) {
      const double x = static_cast<double>(model_.feature()[3 * static_cast<size_t>(a) + c]) - r.pixel_feature[c];
      d2 += x * x;
    }
    if (d2 < best) {
      best = d2;
      r.seed = a;
    }
  }
  const float* c = &model_.pos()[3 * static_cast<size_t>(r.seed)];
  r.seed_distance = (r.point - Eigen::Vector3d(c[0], c[1], c[2])).norm();
  if (config_.grow) {
    r.selected = region_grow(graph_, model_.feature(), {r.seed}, config_.tau, config_.min_weight);
  } else {
    const float* f = &model_.feature()[3 * static_cast<size_t>(r.seed)];
    r.selected = similar_anchors(model_.feature(), {f[0], f[1], f[2]}, config_.equivalent_distance());
  }
  r.ms = ms_since(t0);
  return r;
}

// Anchors whose children lie higher than this many plane tolerances over
// the plane stand on it; those within it of the plane are the band (the
// plane itself, and an object's base).
constexpr double kSupportMargin = 2.0;

// The base's reach across up: this quantile of the distances of the
// object's lowest anchors from its axis (the largest distance followed a few
// table anchors that the object's component took in, onto the table).
constexpr double kBaseReachQuantile = 0.9;

std::vector<int32_t> support_grow(const AnchorModel& model, const Plane& plane, int32_t seed, double link_factor) {
  const size_t A = model.size();
  if (seed < 0 || static_cast<size_t>(seed) >= A)
    throw std::invalid_argument("support_grow: seed " + std::to_string(seed) + " is not one of the model's anchors");
  if (!(link_factor > 0)) throw std::invalid_argument("support_grow: link_factor must be > 0");
  auto pos = [&](size_t a) {
    return Eigen::Vector3d(model.pos()[3 * a], model.pos()[3 * a + 1], model.pos()[3 * a + 2]);
  };
  // An anchor's height: the mean height of its children (centre + offset x
  // voxel edge), where training put its Gaussians; a coarse anchor's own
  // centre can lie far from the surface it models.
  const int K = model.children();
  std::vector<double> height(A);
  std::vector<uint8_t> above(A), band(A);
  double max_voxel = 0;
  const double margin = kSupportMargin * plane.tolerance;
  for (size_t a = 0; a < A; ++a) {
    const double l = model.voxel()[a];
    double h = 0;
    for (int k = 0; k < K; ++k) {
      const float* o = &model.offset()[3 * (a * K + k)];
      h += plane.height(pos(a) + l * Eigen::Vector3d(o[0], o[1], o[2]));
    }
    height[a] = h / K;
    above[a] = height[a] > margin;
    band[a] = !above[a] && height[a] > -margin;
    max_voxel = std::max(max_voxel, l);
  }
  if (!above[seed]) return {};
  // A hash grid of cell = the longest link, so that linked anchors lie in
  // neighbouring cells; cells visited in a fixed order, so the result does
  // not depend on hash order (the BFS below is order-free anyway: components).
  const double cell = link_factor * max_voxel;
  auto key_of = [&](const Eigen::Vector3d& p) {
    const Eigen::Vector3d q = (p / cell).array().floor();
    return std::array<int64_t, 3>{static_cast<int64_t>(q(0)), static_cast<int64_t>(q(1)), static_cast<int64_t>(q(2))};
  };
  auto hash = [](const std::array<int64_t, 3>& k) {
    return static_cast<uint64_t>(k[0]) * 73856093ull ^ static_cast<uint64_t>(k[1]) * 19349663ull ^
           static_cast<uint64_t>(k[2]) * 83492791ull;
  };
  std::unordered_map<uint64_t, std::vector<int32_t>> grid;
  for (size_t a = 0; a < A; ++a) grid[hash(key_of(pos(a)))].push_back(static_cast<int32_t>(a));
  auto for_links = [&](size_t a, auto&& visit) {
    const Eigen::Vector3d p = pos(a);
    const std::array<int64_t, 3> k = key_of(p);
    for (int dz = -1; dz <= 1; ++dz)
      for (int dy = -1; dy <= 1; ++dy)
        for (int dx = -1; dx <= 1; ++dx) {
          auto it = grid.find(hash({k[0] + dx, k[1] + dy, k[2] + dz}));
          if (it == grid.end()) continue;
          for (int32_t b : it->second) {
            if (static_cast<size_t>(b) == a) continue;
            const double reach = link_factor * std::max(model.voxel()[a], model.voxel()[b]);
            if ((pos(b) - p).squaredNorm() < reach * reach) visit(static_cast<size_t>(b));
          }
        }
  };
  std::vector<uint8_t> in(A, 0);
  std::deque<size_t> queue{static_cast<size_t>(seed)};
  in[seed] = 1;
  while (!queue.empty()) {
    const size_t a = queue.front();
    queue.pop_front();
    for_links(a, [&](size_t b) {
      if (above[b] && !in[b]) {
        in[b] = 1;
        queue.push_back(b);
      }
    });
  }
  // The base: the component's axis (its mean across up) and the reach
  // across up of its lowest part (the lowest tenth of its height, the
  // kBaseReachQuantile of their distances from the axis); band anchors
  // linked to the component within that reach.
  const Eigen::Vector3d up = plane.normal;
  auto across = [&](const Eigen::Vector3d& d) { return d - d.dot(up) * up; };
  Eigen::Vector3d axis = Eigen::Vector3d::Zero();
  size_t n = 0;
  double top = -INFINITY, bottom = INFINITY;
  for (size_t a = 0; a < A; ++a)
    if (in[a]) {
      axis += pos(a);
      ++n;
      top = std::max(top, height[a]);
      bottom = std::min(bottom, height[a]);
    }
  axis /= static_cast<double>(n);
  std::vector<double> low;
  for (size_t a = 0; a < A; ++a)
    if (in[a] && height[a] < bottom + 0.1 * (top - bottom) + margin) low.push_back(across(pos(a) - axis).norm());
  const double reach = quantile(std::move(low), kBaseReachQuantile);  // never empty: the lowest anchor is in it
  std::vector<uint8_t> base(A, 0);
  for (size_t a = 0; a < A; ++a) {
    if (!in[a]) continue;
    for_links(a, [&](size_t b) {
      if (band[b] && !in[b] && across(pos(b) - axis).norm() <= reach) base[b] = 1;
    });
  }
  std::vector<int32_t> out;
  for (size_t a = 0; a < A; ++a)
    if (in[a] || base[a]) out.push_back(static_cast<int32_t>(a));
  return out;
}

TextResult QueryEngine::text(const std::vector<float>& embedding, const std::vector<std::vector<float>>& rivals) {
  if (!have_language_) throw std::logic_error("QueryEngine::text before set_language");
  const auto t0 = std::chrono::steady_clock::now();
  TextResult r;
  r.scores = text_scores(language_, embedding);
  double any_best = -std::numeric_limits<double>::infinity();
  for (double s : r.scores)
    if (!std::isnan(s)) any_best = std::max(any_best, s);
  if (!std::isfinite(any_best))
    throw std::invalid_argument("no cluster of the model has a language feature (stage 3 found no mask matches)");
  // The clusters the phrase wins against every rival.
  std::vector<uint8_t> wins(r.scores.size(), 0);
  for (size_t c = 0; c < r.scores.size(); ++c)
    wins[c] = !std::isnan(r.scores[c]) && r.scores[c] >= config_.text_threshold;
  for (const std::vector<float>& rival : rivals) {
    const std::vector<double> rs = text_scores(language_, rival);
    for (size_t c = 0; c < r.scores.size(); ++c)
      if (wins[c] && rs[c] > r.scores[c]) wins[c] = 0;
  }
  r.best = -std::numeric_limits<double>::infinity();
  for (size_t c = 0; c < r.scores.size(); ++c)
    if (wins[c]) {
      r.best = std::max(r.best, r.scores[c]);
      ++r.won;
    }
  if (r.won == 0) {
    r.none = true;
    r.best = any_best;
    r.ms = ms_since(t0);
    return r;
  }
  std::vector<uint8_t> seed_cluster(r.scores.size(), 0);
  for (size_t c = 0; c < r.scores.size(); ++c) {
    if (wins[c] && r.scores[c] >= r.best - config_.text_margin) {
      seed_cluster[c] = 1;
      r.seed_clusters.push_back(static_cast<int32_t>(c));
    }
  }
  for (size_t a = 0; a < clustering_.anchor_cluster.size(); ++a) {
    const int32_t c = clustering_.anchor_cluster[a];
    if (c >= 0 && seed_cluster[c]) r.seeds.push_back(static_cast<int32_t>(a));
  }
  if (config_.grow) {
    r.selected = region_grow(graph_, model_.feature(), r.seeds, config_.tau, config_.min_weight);
  } else {
    // Each seed cluster's mean feature (double sums, in anchor order).
    std::vector<double> sum(3 * r.scores.size(), 0.0);
    std::vector<int64_t> count(r.scores.size(), 0);
    for (int32_t a : r.seeds) {
      const int32_t c = clustering_.anchor_cluster[a];
      for (int k = 0; k < 3; ++k) sum[3 * c + k] += model_.feature()[3 * static_cast<size_t>(a) + k];
      ++count[c];
    }
    std::vector<float> means;
    for (int32_t c : r.seed_clusters)
      if (count[c] > 0)
        for (int k = 0; k < 3; ++k) means.push_back(static_cast<float>(sum[3 * c + k] / count[c]));
    r.selected = similar_anchors(model_.feature(), means, config_.equivalent_distance());
  }
  r.ms = ms_since(t0);
  return r;
}

std::vector<uint8_t> QueryEngine::mask(const Camera& camera, const std::vector<int32_t>& selected) {
  camera.validate();
  const int k = model_.children();
  std::fill(selection_features_.begin(), selection_features_.end(), 0.f);
  for (int32_t a : selected) {
    if (a < 0 || static_cast<size_t>(a) >= model_.size())
      throw std::invalid_argument("mask: anchor id " + std::to_string(a) + " out of range");
    for (int i = 0; i < k; ++i) selection_features_[3 * (static_cast<size_t>(a) * k + i)] = 1.f;
  }
  device_.features.upload(selection_features_);
  features_are_model_ = false;
  RenderSettings settings;
  settings.sh_degree = 0;
  renderer_.forward(device_, camera, settings);
  const size_t pixels = static_cast<size_t>(camera.width) * camera.height;
  std::vector<float> weight;
  renderer_.device_feature().download(weight, pixels);  // planar [3,H,W]: channel 0 first
  std::vector<uint8_t> m(pixels);
  for (size_t p = 0; p < pixels; ++p) m[p] = weight[p] > config_.mask_threshold ? 1 : 0;
  return m;
}

GaussianSet gaussians_of_anchors(const AnchorModel& model, int sh_degree, const std::vector<uint8_t>& in_selection,
                                 bool want) {
  if (in_selection.size() != model.size())
    throw std::invalid_argument("gaussians_of_anchors: selection of " + std::to_string(in_selection.size()) +
                                " anchors for a model of " + std::to_string(model.size()));
  const GaussianSet all = expand_reference(model, sh_degree);
  const int k = model.children();
  std::vector<size_t> ids;
  for (size_t a = 0; a < model.size(); ++a)
    if ((in_selection[a] != 0) == want)
      for (int i = 0; i < k; ++i) ids.push_back(a * k + i);
  return all.rows(ids);
}

}  // namespace ag2gs
