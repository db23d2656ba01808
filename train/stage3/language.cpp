#include "train/stage3/language.h"

#include <spdlog/spdlog.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>

#include "host/core/timing.h"
#include "host/io/json_input.h"
#include "host/losses/mask_loss.h"  // kMaskAlphaMin
#include "host/render/renderer.h"
#include "train/anchors/expander.h"

namespace ag2gs {

namespace {

[[noreturn]] void fail_archive(const ModelArchive& archive, const std::string& what) {
  throw std::runtime_error("model " + (archive.source.empty() ? std::string("(in memory)") : archive.source) + ": " +
                           what);
}

// Running sums of G over a pixel set.
struct FeatureSum {
  int64_t pixels = 0;        // all pixels of the set
  int64_t with_feature = 0;  // those with a feature
  double g[3] = {0, 0, 0};
};

}  // namespace

void LanguageConfig::validate() const {
  if (!std::isfinite(min_score)) throw std::invalid_argument("language: min_score must be finite");
  if (!(softmax_scale > 0.f) || !std::isfinite(softmax_scale) || softmax_scale > 80.f)
    throw std::invalid_argument("language: softmax_scale must lie in (0, 80] (exp(scale * S) must stay finite)");
  if (!(instance_fraction >= 0.5f && instance_fraction < 1.f))
    throw std::invalid_argument("language: instance_fraction must lie in [0.5, 1)");
}

std::vector<MaskMatch> score_view(const std::vector<int32_t>& ids, int clusters, const std::vector<float>& feature_chw,
                                  const std::vector<float>& alpha, const ViewMasks& masks,
                                  const LanguageConfig& config) {
  config.validate();
  const size_t npix = static_cast<size_t>(masks.width) * masks.height;
  const int L = masks.layers;
  if (ids.size() != npix)
    throw std::invalid_argument("score_view: instance ids hold " + std::to_string(ids.size()) +
                                " pixels, the masks are " + std::to_string(masks.width) + "x" +
                                std::to_string(masks.height) + "; render at the masks' resolution");
  if (feature_chw.size() != npix * 3)
    throw std::invalid_argument("score_view: feature map must be [3,H,W] at the masks' size");
  if (config.normalise_by_alpha && alpha.size() != npix)
    throw std::invalid_argument("score_view: alpha must be [H,W] at the masks' size (or set normalise_by_alpha off)");
  if (L < 0 || L > 16) throw std::invalid_argument("score_view: at most 16 mask layers (SAM has 4 levels)");
  if (masks.labels.size() != npix * static_cast<size_t>(L))
    throw std::invalid_argument("score_view: mask labels must be [layers,H,W]");
  const int M = masks.count;

  std::vector<FeatureSum> cs(clusters), ms(M);
  std::vector<uint64_t> pairs;  // (cluster << 32) | mask, one per (pixel, distinct mask) inside a cluster
  int32_t seen[16];
  for (size_t p = 0; p < npix; ++p) {
    double g[3] = {feature_chw[p], feature_chw[npix + p], feature_chw[2 * npix + p]};
    bool has = true;
    if (config.normalise_by_alpha) {
      const float a = alpha[p];
      has = a >= kMaskAlphaMin;  // false for NaN
      if (has)
        for (double& x : g) x = static_cast<double>(static_cast<float>(x) / a);
    }
    auto add = [&](FeatureSum& s) {
      ++s.pixels;
      if (!has) return;
      ++s.with_feature;
      for (int k = 0; k < 3; ++k) s.g[k] += g[k];
    };
    const int32_t c = ids[p];
    if (c >= clusters || c < -1)
      throw std::invalid_argument("score_view: instance id " + std::to_string(c) + " outside [-1, " +
                                  std::to_string(clusters) + ")");
    if (c >= 0) add(cs[c]);
    int nseen = 0;
    for (int l = 0; l < L; ++l) {
      const int32_t m = masks.labels[static_cast<size_t>(l) * npix + p];
      if (m < 0) continue;
      if (m >= M) throw std::invalid_argument("score_view: mask label " + std::to_string(m) + " >= mask count");
      if (std::find(seen, seen + nseen, m) != seen + nseen) continue;
      seen[nseen++] = m;
      add(ms[m]);
      if (c >= 0) pairs.push_back((static_cast<uint64_t>(c) << 32) | static_cast<uint32_t>(m));
    }
  }
  std::sort(pairs.begin(), pairs.end());

  std::vector<MaskMatch> out;
  for (size_t i = 0; i < pairs.size();) {
    size_t j = i;
    while (j < pairs.size() && pairs[j] == pairs[i]) ++j;
    MaskMatch mm;
    mm.cluster = static_cast<int32_t>(pairs[i] >> 32);
    mm.mask = static_cast<int32_t>(pairs[i] & 0xffffffffu);
    mm.intersection = static_cast<int64_t>(j - i);
    const FeatureSum& a = cs[mm.cluster];
    const FeatureSum& b = ms[mm.mask];
    mm.iou = static_cast<double>(mm.intersection) / static_cast<double>(a.pixels + b.pixels - mm.intersection);
    if (a.with_feature > 0 && b.with_feature > 0) {
      double d = 0;
      for (int k = 0; k < 3; ++k) d += std::abs(a.g[k] / a.with_feature - b.g[k] / b.with_feature);
      mm.feature_l1 = d;
      mm.score = mm.iou * (1.0 - d);
    } else {
      mm.feature_l1 = std::numeric_limits<double>::quiet_NaN();
      mm.score = 0;
    }
    out.push_back(mm);
    i = j;
  }
  return out;
}

int LanguageFeatures::with_language() const {
  return static_cast<int>(std::count_if(matches.begin(), matches.end(), [](int32_t m) { return m > 0; }));
}

LanguageAccumulator::LanguageAccumulator(int clusters, int dim, const LanguageConfig& config)
    : clusters_(clusters),
      dim_(dim),
      config_(config),
      weight_sum_(clusters, 0.0),
      acc_(static_cast<size_t>(clusters) * dim, 0.0),
      matches_(clusters, 0) {
  config.validate();
  if (clusters < 0 || dim < 1) throw std::invalid_argument("language: need clusters >= 0 and a CLIP dimension >= 1");
}

void LanguageAccumulator::add_view(const std::vector<MaskMatch>& matches, const ViewMasks& masks) {
  if (masks.feature_dim != dim_ || masks.features.size() != static_cast<size_t>(masks.count) * dim_)
    throw std::invalid_argument("language: the view's masks carry " + std::to_string(masks.feature_dim) +
                                "-d CLIP features, expected " + std::to_string(dim_));
  for (const MaskMatch& m : matches) {
    if (!(m.score > config_.min_score)) continue;
    if (m.cluster < 0 || m.cluster >= clusters_ || m.mask < 0 || m.mask >= masks.count)
      throw std::invalid_argument("language: match (cluster " + std::to_string(m.cluster) + ", mask " +
                                  std::to_string(m.mask) + ") out of range");
    // S <= 1 and scale <= 80: e^{scale S} is finite, no max-subtraction needed.
    const double e = std::exp(static_cast<double>(config_.softmax_scale) * m.score);
    weight_sum_[m.cluster] += e;
    const float* clip = masks.features.data() + static_cast<size_t>(m.mask) * dim_;
    double* acc = acc_.data() + static_cast<size_t>(m.cluster) * dim_;
    for (int k = 0; k < dim_; ++k) acc[k] += e * clip[k];
    ++matches_[m.cluster];
  }
}

LanguageFeatures LanguageAccumulator::finish() const {
  LanguageFeatures out;
  out.dim = dim_;
  out.matches = matches_;
  out.features.assign(static_cast<size_t>(clusters_) * dim_, 0.f);
  for (int c = 0; c < clusters_; ++c) {
    if (matches_[c] == 0) continue;
    const double* acc = acc_.data() + static_cast<size_t>(c) * dim_;
    double norm = 0;
    for (int k = 0; k < dim_; ++k) {
      const double x = acc[k] / weight_sum_[c];
      norm += x * x;
    }
    norm = std::sqrt(norm);
    if (!(norm > 0)) continue;  // matched features cancelled out: leave the row zero
    for (int k = 0; k < dim_; ++k)
      out.features[static_cast<size_t>(c) * dim_ + k] = static_cast<float>(acc[k] / weight_sum_[c] / norm);
  }
  return out;
}

LanguageFeatures attach_language(Runtime& rt, const AnchorModel& model, const Clustering& clustering, Scene& scene,
                                 const std::vector<int>& views, const LanguageConfig& config, LanguageStats* stats) {
  config.validate();
  const auto t_start = std::chrono::steady_clock::now();
  if (clustering.anchor_cluster.size() != model.size())
    throw std::invalid_argument("attach_language: the clustering covers " +
                                std::to_string(clustering.anchor_cluster.size()) + " anchors, the model has " +
                                std::to_string(model.size()) + "; cluster the model again");
  if (scene.semantics() != SemanticsKind::language_features)
    throw std::runtime_error("scene " + scene.dir() +
                             " has no CLIP features: language features need language_features/<stem>_s.npy and "
                             "<stem>_f.npy per image (masks/ PNGs carry no CLIP features)");
  LanguageStats st;
  auto t0 = std::chrono::steady_clock::now();
  DeviceAnchors anchors(rt);
  anchors.upload(model);
  DeviceGaussians gaussians(rt);
  Expander expander(rt);
  expander.forward(anchors, gaussians, 0);
  rt.queue().finish();
  anchors.release();  // the views need the Gaussians only
  st.expand_ms = ms_since(t0);

  Renderer renderer(rt);
  InstanceMapper mapper(rt);
  mapper.set_clusters(clustering.anchor_cluster, model.children(), config.instance_fraction);
  std::unique_ptr<LanguageAccumulator> acc;
  const int C = clustering.clusters();
  std::vector<int32_t> ids;
  std::vector<float> feature, alpha;
  for (int v : views) {
    if (v < 0 || static_cast<size_t>(v) >= scene.views().size())
      throw std::invalid_argument("attach_language: view index " + std::to_string(v) + " out of range");
    std::shared_ptr<const ViewMasks> masks = scene.masks(v);
    if (!masks || masks->count == 0) continue;
    if (!acc) acc = std::make_unique<LanguageAccumulator>(C, masks->feature_dim, config);
    const Camera& cam = scene.views()[v].camera;
    if (masks->width != cam.width || masks->height != cam.height)
      throw std::runtime_error("attach_language: masks of view " + scene.views()[v].name + " are " +
                               std::to_string(masks->width) + "x" + std::to_string(masks->height) +
                               ", the camera renders " + std::to_string(cam.width) + "x" + std::to_string(cam.height));
    t0 = std::chrono::steady_clock::now();
    RenderSettings settings;
    settings.sh_degree = 0;
    // The instance walk blends the feature and the alpha too: no blend pass.
    renderer.bin(gaussians, cam, settings);
    rt.queue().finish();
    st.render_ms += ms_since(t0);
    t0 = std::chrono::steady_clock::now();
    mapper.compute_with_images(renderer);
    rt.queue().finish();
    st.instance_ms += ms_since(t0);
    t0 = std::chrono::steady_clock::now();
    const size_t npix = static_cast<size_t>(cam.width) * cam.height;
    mapper.device_ids().download(ids, npix);
    mapper.device_feature().download(feature, npix * 3);
    if (config.normalise_by_alpha) mapper.device_alpha().download(alpha, npix);
    std::vector<MaskMatch> matches = score_view(ids, C, feature, alpha, *masks, config);
    st.pairs += matches.size();
    for (const MaskMatch& m : matches) st.matches += m.score > config.min_score;
    acc->add_view(matches, *masks);
    st.score_ms += ms_since(t0);
    ++st.views;
  }
  LanguageFeatures out;
  if (acc) {
    out = acc->finish();
  } else {
    spdlog::warn("attach_language: none of the {} views has SAM masks; no cluster gets a language feature",
                 views.size());
    out.dim = scene.feature_dim();
    out.matches.assign(C, 0);
    out.features.assign(static_cast<size_t>(C) * out.dim, 0.f);
  }
  st.total_ms = ms_since(t_start);
  if (stats) *stats = st;
  return out;
}

void language_to_archive(ModelArchive& archive, const LanguageFeatures& language, const LanguageConfig& config) {
  const int64_t C = language.clusters(), D = language.dim;
  archive.put("clusters/language", language.features, {C, D});
  archive.put("clusters/language_matches", language.matches, {C});
  archive.meta["language"] = {{"format", 1},
                              {"dim", language.dim},
                              {"clusters_with_language", language.with_language()},
                              {"min_score", config.min_score},
                              {"softmax_scale", config.softmax_scale},
                              {"normalise_by_alpha", config.normalise_by_alpha},
                              {"instance_fraction", config.instance_fraction},
                              {"cluster_feature", "mean rendered feature over the instance pixels"}};
}

LanguageFeatures language_from_archive(const ModelArchive& archive, int clusters) {
  if (!archive.has("clusters/language") || !archive.meta.contains("language"))
    fail_archive(archive, "has no language features; run stage 3 (ag2gs train --stages 3) on it first");
  LanguageFeatures out;
  try {
    out.dim = archive.meta.at("language").at("dim").get<int>();
  } catch (const nlohmann::json::exception& e) {
    fail_archive(archive, std::string("meta 'language' is incomplete or mistyped: ") + json_error_text(e));
  }
  if (out.dim < 0) fail_archive(archive, "meta 'language': negative dim");
  out.features = archive.get<float>("clusters/language", {clusters, out.dim});
  out.matches = archive.get<int32_t>("clusters/language_matches", {clusters});
  for (int c = 0; c < clusters; ++c)
    if (out.matches[c] < 0) fail_archive(archive, "clusters/language_matches has a negative entry");
  for (size_t i = 0; i < out.features.size(); ++i)
    if (!std::isfinite(out.features[i]))
      fail_archive(archive, "array 'clusters/language': element " + std::to_string(i) +
                                " is not a finite number; the file is damaged: run stage 3 again (ag2gs train "
                                "SCENE_DIR -o MODEL_DIR --stages 3)");
  return out;
}

Stage3Result run_stage3(Runtime& rt, const AnchorModel& model, const AnchorGraphView& graph, Scene& scene,
                        const std::vector<int>& views, const Stage3Config& config) {
  if (graph.anchors != model.size())
    throw std::invalid_argument("stage 3: the graph covers " + std::to_string(graph.anchors) +
                                " anchors, the model has " + std::to_string(model.size()) + "; rebuild the graph");
  if (!(config.tau > 0.f)) throw std::invalid_argument("stage 3: tau must be > 0");
  Stage3Result r;
  const auto t0 = std::chrono::steady_clock::now();
  AnchorGraphView g = graph;
  g.edge_values = nullptr;
  std::vector<float> values = edge_feature_distances(g, model.feature());
  if (config.cluster.edge_value == EdgeValue::bilateral_weight)
    for (float& v : values) v = static_cast<float>(std::exp(-double(v) * v / (2.0 * config.tau * config.tau)));
  g.edge_values = values.data();
  r.clustering = cluster_anchors(g, config.cluster);
  r.cluster_ms = ms_since(t0);
  r.language = attach_language(rt, model, r.clustering, scene, views, config.language, &r.stats);
  return r;
}

}  // namespace ag2gs
