#include "queries/semantic_eval.h"

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <map>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <stdexcept>
#include <unordered_map>

#include "host/render/renderer.h"

namespace ag2gs {

namespace fs = std::filesystem;

std::vector<int32_t> read_gt_ids(const Scene& scene, int view) {
  const SceneView& v = scene.views().at(view);
  const std::string path = (fs::path(scene.dir()) / "gt" / (v.stem + ".png")).string();
  cv::Mat m = cv::imread(path, cv::IMREAD_UNCHANGED);
  if (m.empty())
    throw std::runtime_error(path + ": missing or unreadable ground-truth id map (a scene from `ag2gs synth` has one "
                             "per image under gt/)");
  if (m.channels() != 1 || (m.depth() != CV_8U && m.depth() != CV_16U))
    throw std::runtime_error(path + ": a ground-truth id map must be a one-channel 8- or 16-bit PNG");
  const int w = v.camera.width, h = v.camera.height;
  if (m.cols != w || m.rows != h) cv::resize(m, m, cv::Size(w, h), 0, 0, cv::INTER_NEAREST);
  std::vector<int32_t> ids(size_t(w) * h);
  for (int y = 0; y < h; ++y)
    for (int x = 0; x < w; ++x)
      ids[size_t(y) * w + x] = m.depth() == CV_8U ? m.at<uint8_t>(y, x) : m.at<uint16_t>(y, x);
  return ids;
}

std::vector<int32_t> anchor_ground_truth(Runtime& rt, const AnchorModel& model, Scene& scene,
                                         const std::vector<int>& views, const AnchorTruthOptions& options) {
  const size_t A = model.size();
  // votes[a] : object id -> count; few distinct ids per anchor.
  std::vector<std::map<int32_t, int>> votes(A);
  if (A == 0) return {};
  const GaussianSet set = expand_reference(model, 0);
  Renderer renderer(rt);
  RenderSettings settings;
  settings.sh_degree = 0;
  const auto& pos = model.pos();
  const auto& voxel = model.voxel();
  for (int v : views) {
    const Camera& cam = scene.views().at(v).camera;
    const std::vector<int32_t> gt = read_gt_ids(scene, v);
    const RenderOutput out = renderer.render(set, cam, settings);
    const int W = cam.width, H = cam.height;
    for (size_t a = 0; a < A; ++a) {
      const Eigen::Vector3d x(pos[3 * a], pos[3 * a + 1], pos[3 * a + 2]);
      const Eigen::Vector3d c = cam.R * x + cam.t;
      if (!(c.z() > 1e-6)) continue;
      const double u = cam.fx * c.x() / c.z() + cam.cx, w = cam.fy * c.y() / c.z() + cam.cy;
      if (!(u >= 0 && w >= 0 && u < W && w < H)) continue;
      const size_t p = size_t(int(w)) * W + size_t(int(u));
      const float alpha = out.alpha[p];
      if (!(alpha >= options.min_alpha)) continue;
      const double depth = out.depth[p] / alpha;
      if (std::abs(depth - c.z()) > options.depth_tolerance * voxel[a]) continue;
      ++votes[a][gt[p]];
    }
  }
  std::vector<int32_t> truth(A, -1);
  for (size_t a = 0; a < A; ++a) {
    int best = 0;
    for (const auto& [id, n] : votes[a])  // ascending ids: ties keep the smaller
      if (n > best) best = n, truth[a] = id;
  }
  return truth;
}

namespace {
double pairs(int64_t n) { return 0.5 * double(n) * double(n - 1); }
}  // namespace

double adjusted_rand_index(const std::vector<int32_t>& a, const std::vector<int32_t>& b) {
  if (a.size() != b.size()) throw std::invalid_argument("adjusted_rand_index: labelings differ in length");
  const size_t n = a.size();
  if (n < 2) return 1.0;
  std::map<std::pair<int32_t, int32_t>, int64_t> table;
  std::map<int32_t, int64_t> ra, rb;
  for (size_t i = 0; i < n; ++i) {
    ++table[{a[i], b[i]}];
    ++ra[a[i]];
    ++rb[b[i]];
  }
  double index = 0, sa = 0, sb = 0;
  for (const auto& [k, c] : table) index += pairs(c);
  for (const auto& [k, c] : ra) sa += pairs(c);
  for (const auto& [k, c] : rb) sb += pairs(c);
  const double expected = sa * sb / pairs(int64_t(n));
  const double max_index = 0.5 * (sa + sb);
  if (max_index == expected) return 1.0;  // both trivial partitions (all one class or all singletons)
  return (index - expected) / (max_index - expected);
}

ClusterQuality cluster_quality(const std::vector<int32_t>& truth, const std::vector<int32_t>& clusters) {
  if (truth.size() != clusters.size())
    throw std::invalid_argument("cluster_quality: " + std::to_string(truth.size()) + " truth labels for " +
                                std::to_string(clusters.size()) + " cluster ids");
  ClusterQuality q;
  std::map<int32_t, std::map<int32_t, int64_t>> per_cluster;
  std::vector<int32_t> ta, ca;
  int32_t singleton = -2;  // unclustered anchors: each its own cluster (ids below -1)
  for (size_t i = 0; i < truth.size(); ++i) {
    if (truth[i] >= 0 && clusters[i] >= 0) {
      ++q.clustered_anchors;
      ++per_cluster[clusters[i]][truth[i]];
    }
    if (truth[i] >= 1) {
      ++q.object_anchors;
      ta.push_back(truth[i]);
      ca.push_back(clusters[i] >= 0 ? clusters[i] : singleton--);
    }
  }
  int64_t majority = 0;
  for (const auto& [c, counts] : per_cluster) {
    int64_t best = 0;
    for (const auto& [t, n] : counts) best = std::max(best, n);
    majority += best;
  }
  q.purity = q.clustered_anchors ? double(majority) / double(q.clustered_anchors) : 0.0;
  q.ari = adjusted_rand_index(ta, ca);
  return q;
}

std::vector<ObjectCategoryResult> object_categories(
    const std::vector<int32_t>& truth, const std::vector<int32_t>& clusters,
    const std::vector<std::pair<int, std::string>>& objects, const std::vector<float>& language, int dim,
    const std::vector<std::pair<std::string, std::vector<float>>>& vocabulary) {
  if (truth.size() != clusters.size()) throw std::invalid_argument("object_categories: truth/cluster size mismatch");
  if (dim <= 0 || language.size() % size_t(dim) != 0)
    throw std::invalid_argument("object_categories: language features are not [C, dim]");
  const size_t C = language.size() / size_t(dim);
  auto cosine = [dim](const float* x, const std::vector<float>& y) {
    double xy = 0, xx = 0, yy = 0;
    for (int d = 0; d < dim; ++d) xy += double(x[d]) * y[d], xx += double(x[d]) * x[d], yy += double(y[d]) * y[d];
    return xx > 0 && yy > 0 ? xy / std::sqrt(xx * yy) : 0.0;
  };
  std::vector<ObjectCategoryResult> results;
  for (const auto& [id, category] : objects) {
    ObjectCategoryResult r;
    r.object = id;
    r.category = category;
    std::map<int32_t, int> count;
    for (size_t i = 0; i < truth.size(); ++i)
      if (truth[i] == id) {
        ++r.anchors;
        if (clusters[i] >= 0) ++count[clusters[i]];
      }
    int best = 0;
    for (const auto& [c, n] : count)
      if (n > best) best = n, r.cluster = c;
    r.cluster_share = r.anchors ? double(best) / r.anchors : 0.0;
    if (r.cluster >= 0 && size_t(r.cluster) < C) {
      const float* f = &language[size_t(r.cluster) * dim];
      double best_cos = -2;
      for (const auto& [name, vec] : vocabulary) {
        if (int(vec.size()) != dim) throw std::invalid_argument("object_categories: vocabulary entry '" + name +
                                                                "' has another dimension than the language features");
        const double c = cosine(f, vec);
        if (name == category) r.cosine_true = c;
        if (c > best_cos) best_cos = c, r.predicted = name;
      }
      bool has_feature = false;
      for (int d = 0; d < dim; ++d) has_feature |= f[d] != 0.f;
      if (!has_feature) r.predicted.clear();
      r.cosine_best = has_feature ? best_cos : 0.0;
    }
    r.correct = !r.predicted.empty() && r.predicted == category;
    results.push_back(r);
  }
  return results;
}

std::vector<std::pair<int, std::string>> read_synth_objects(const std::string& scene_dir) {
  const std::string path = (fs::path(scene_dir) / "synth.json").string();
  std::ifstream in(path);
  if (!in) throw std::runtime_error(path + ": missing; the object ground truth comes from a scene made by `ag2gs synth`");
  nlohmann::json j;
  try {
    in >> j;
    std::vector<std::pair<int, std::string>> objects;
    for (const auto& o : j.at("objects")) objects.emplace_back(o.at("id").get<int>(), o.at("category").get<std::string>());
    return objects;
  } catch (const nlohmann::json::exception& e) {
    throw std::runtime_error(path + ": not a synth.json with objects[].id and objects[].category (" + e.what() + ")");
  }
}

}  // namespace ag2gs
