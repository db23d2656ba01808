// Language attachment (train/stage3/language.h): the sparse scoring against a
// brute-force per-pair reference, the softmax attachment against its formula,
// and a rendered scene of separated objects with known answer: every cluster
// must receive its own object's CLIP vector.
#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <map>
#include <random>
#include <tuple>

#include "tests/reference/language_reference.h"
#include "tests/test_util.h"
#include "train/stage3/instance_map.h"
#include "train/stage3/language.h"

namespace ag2gs {
namespace {

void expect_same_matches(const std::vector<MaskMatch>& got, const std::vector<MaskMatch>& ref) {
  ASSERT_EQ(got.size(), ref.size());
  for (size_t i = 0; i < got.size(); ++i) {
    EXPECT_EQ(got[i].cluster, ref[i].cluster);
    EXPECT_EQ(got[i].mask, ref[i].mask);
    EXPECT_EQ(got[i].intersection, ref[i].intersection);
    EXPECT_NEAR(got[i].iou, ref[i].iou, 1e-12);
    if (std::isnan(ref[i].feature_l1)) {
      EXPECT_TRUE(std::isnan(got[i].feature_l1));
      EXPECT_EQ(got[i].score, 0.0);
    } else {
      EXPECT_NEAR(got[i].feature_l1, ref[i].feature_l1, 1e-9);
      EXPECT_NEAR(got[i].score, ref[i].score, 1e-9);
    }
  }
}

// Random blocky instance map, two mask layers, random features and alpha.
struct RandomView {
  std::vector<int32_t> ids;
  std::vector<float> feat, alpha;
  ViewMasks masks;
};
RandomView random_view(int W, int H, int clusters, int masks_per_layer, uint32_t seed, int dim) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<float> u(0.f, 1.f);
  RandomView v;
  const size_t npix = static_cast<size_t>(W) * H;
  v.ids.resize(npix);
  v.feat.resize(npix * 3);
  v.alpha.resize(npix);
  v.masks.width = W;
  v.masks.height = H;
  v.masks.layers = 2;
  v.masks.count = 2 * masks_per_layer;
  v.masks.labels.resize(2 * npix);
  // Blocks of 8x8 (clusters) and 6x6 / 10x10 (masks) so overlaps are partial.
  std::vector<int> cb((W / 8 + 1) * (H / 8 + 1)), m0((W / 6 + 1) * (H / 6 + 1)), m1((W / 10 + 1) * (H / 10 + 1));
  for (int& x : cb) x = static_cast<int>(rng() % (clusters + 1)) - 1;
  for (int& x : m0) x = static_cast<int>(rng() % (masks_per_layer + 1)) - 1;
  for (int& x : m1) x = static_cast<int>(rng() % (masks_per_layer + 1)) - 1;
  for (int y = 0; y < H; ++y)
    for (int x = 0; x < W; ++x) {
      const size_t p = static_cast<size_t>(y) * W + x;
      v.ids[p] = cb[(y / 8) * (W / 8 + 1) + x / 8];
      const int a = m0[(y / 6) * (W / 6 + 1) + x / 6], b = m1[(y / 10) * (W / 10 + 1) + x / 10];
      v.masks.labels[p] = a;
      v.masks.labels[npix + p] = b < 0 ? -1 : b + masks_per_layer;
      v.alpha[p] = u(rng) < 0.1f ? 0.05f : 0.2f + 0.8f * u(rng);
      for (int k = 0; k < 3; ++k) v.feat[k * npix + p] = v.alpha[p] * (0.3f * k + 0.2f * u(rng));
    }
  v.masks.feature_dim = dim;
  v.masks.features.resize(static_cast<size_t>(v.masks.count) * dim);
  std::normal_distribution<float> nrm(0.f, 1.f);
  for (float& f : v.masks.features) f = nrm(rng);
  return v;
}

TEST(Language, ScoreViewMatchesPerPairReference) {
  for (uint32_t seed = 1; seed <= 3; ++seed) {
    RandomView v = random_view(45 + seed, 37, 6, 5, seed, 4);
    for (bool by_alpha : {true, false}) {
      LanguageConfig cfg;
      cfg.normalise_by_alpha = by_alpha;
      expect_same_matches(score_view(v.ids, 6, v.feat, v.alpha, v.masks, cfg),
                          ref::language_scores_reference(v.ids, 6, v.feat, v.alpha, v.masks, by_alpha));
    }
  }
  // A mask whose every pixel is featureless (alpha < 0.1): its pairs score 0.
  RandomView v = random_view(40, 32, 4, 3, 9, 4);
  for (size_t p = 0; p < v.ids.size(); ++p)
    if (v.masks.labels[p] == 0) v.alpha[p] = 0.01f;
  LanguageConfig cfg;
  const std::vector<MaskMatch> got = score_view(v.ids, 4, v.feat, v.alpha, v.masks, cfg);
  expect_same_matches(got, ref::language_scores_reference(v.ids, 4, v.feat, v.alpha, v.masks, true));
  // Size mismatches are refused.
  std::vector<int32_t> short_ids(v.ids.begin(), v.ids.end() - 1);
  EXPECT_THROW(score_view(short_ids, 4, v.feat, v.alpha, v.masks, cfg), std::invalid_argument);
  std::vector<int32_t> bad = v.ids;
  bad[0] = 4;
  EXPECT_THROW(score_view(bad, 4, v.feat, v.alpha, v.masks, cfg), std::invalid_argument);
}

TEST(Language, AccumulatorIsSoftmaxWeightedMean) {
  const int C = 6, D = 8;
  LanguageConfig cfg;
  cfg.min_score = 0.05f;  // random views score low: keep enough matches
  LanguageAccumulator acc(C, D, cfg);
  // Reference: gather all (cluster, S, clip) over views, then the formula.
  std::vector<std::vector<std::pair<double, std::vector<double>>>> all(C);
  for (uint32_t seed = 1; seed <= 3; ++seed) {
    RandomView v = random_view(48, 40, C, 5, seed + 10, D);
    const std::vector<MaskMatch> mm = score_view(v.ids, C, v.feat, v.alpha, v.masks, cfg);
    acc.add_view(mm, v.masks);
    for (const MaskMatch& m : mm)
      if (m.score > cfg.min_score)
        all[m.cluster].push_back({m.score, std::vector<double>(v.masks.features.begin() + m.mask * D,
                                                               v.masks.features.begin() + (m.mask + 1) * D)});
  }
  const LanguageFeatures lf = acc.finish();
  ASSERT_EQ(lf.clusters(), C);
  int with = 0;
  for (int c = 0; c < C; ++c) {
    EXPECT_EQ(lf.matches[c], static_cast<int>(all[c].size()));
    if (all[c].empty()) {
      for (int k = 0; k < D; ++k) EXPECT_EQ(lf.features[c * D + k], 0.f);
      continue;
    }
    ++with;
    const std::vector<double> want = ref::language_feature_reference(all[c], D, 10);
    for (int k = 0; k < D; ++k) EXPECT_NEAR(lf.features[c * D + k], want[k], 1e-6) << c << "," << k;
  }
  EXPECT_EQ(lf.with_language(), with);
  EXPECT_GT(with, 2);
}

// Separated objects, each a cluster of anchors (K = 2 children) with its own
// semantic feature, in front of an unclustered backdrop; two views; masks are
// the rendered ground truth of each object alone (alpha > 0.3), plus a mask
// spanning objects 0 and 1 and a backdrop mask, each with its own CLIP vector.
TEST(Language, SeparatedObjectsGetTheirOwnClipVectors) {
  const int objects = 4, per_object = 12, K = 2, D = 16, backdrop = 10;
  const int A = objects * per_object + backdrop;
  std::mt19937 rng(3);
  std::uniform_real_distribution<float> u(-1.f, 1.f);
  GaussianSet g;
  g.sh_degree = 0;
  g.resize(static_cast<size_t>(A) * K);
  std::vector<int32_t> ac(A);
  const float cx[objects] = {-0.9f, 0.9f, -0.9f, 0.9f}, cy[objects] = {-0.7f, -0.7f, 0.7f, 0.7f};
  for (int a = 0; a < A; ++a) {
    const int o = a < objects * per_object ? a / per_object : -1;
    ac[a] = o;
    for (int i = 0; i < K; ++i) {
      const size_t n = static_cast<size_t>(a) * K + i;
      if (o >= 0) {
        g.means[3 * n] = cx[o] + 0.22f * u(rng);
        g.means[3 * n + 1] = cy[o] + 0.22f * u(rng);
        g.means[3 * n + 2] = 4.f + 0.2f * u(rng);
        for (int k = 0; k < 3; ++k) g.scales[3 * n + k] = 0.09f + 0.03f * u(rng);
        g.opacities[n] = 0.85f + 0.1f * u(rng);
        for (int k = 0; k < 3; ++k) g.features[3 * n + k] = 0.15f * ((o + k) % 4) + 0.05f * (k == o % 3);
      } else {
        g.means[3 * n] = 2.5f * u(rng);
        g.means[3 * n + 1] = 1.6f * u(rng);
        g.means[3 * n + 2] = 9.f;
        for (int k = 0; k < 3; ++k) g.scales[3 * n + k] = 1.2f;
        g.opacities[n] = 0.9f;
        for (int k = 0; k < 3; ++k) g.features[3 * n + k] = 0.9f;
      }
      g.quats[4 * n] = 1.f;
    }
  }
  std::vector<std::vector<float>> clip(objects + 2, std::vector<float>(D));
  std::normal_distribution<float> nrm(0.f, 1.f);
  for (auto& v : clip)
    for (float& x : v) x = nrm(rng);

  LanguageConfig cfg;
  LanguageAccumulator acc(objects, D, cfg);
  std::vector<std::vector<std::pair<double, int>>> ref_matches(objects);  // (S, clip index)
  Renderer renderer(test::runtime());
  InstanceMapper mapper(test::runtime());
  for (int view = 0; view < 2; ++view) {
    Camera cam;
    cam.width = 96;
    cam.height = 64;
    cam.fx = cam.fy = 70;
    cam.cx = 48.2;
    cam.cy = 31.7;
    cam.t = Eigen::Vector3d(0.15 * view, -0.1 * view, 0.0);
    const size_t npix = static_cast<size_t>(cam.width) * cam.height;
    // Ground truth: each object alone.
    ViewMasks masks;
    masks.width = cam.width;
    masks.height = cam.height;
    masks.layers = 2;
    masks.count = objects + 2;
    masks.labels.assign(2 * npix, -1);
    for (int o = 0; o < objects; ++o) {
      GaussianSet alone = g;
      for (int a = 0; a < A; ++a)
        if (ac[a] != o)
          for (int i = 0; i < K; ++i) alone.opacities[static_cast<size_t>(a) * K + i] = 0.f;
      const RenderOutput r = renderer.render(alone, cam);
      for (size_t p = 0; p < npix; ++p)
        if (r.alpha[p] > 0.3f) {
          masks.labels[p] = o;                           // layer 0: objects, backdrop elsewhere
          if (o <= 1) masks.labels[npix + p] = objects;  // layer 1: objects 0 and 1 together
        }
    }
    for (size_t p = 0; p < npix; ++p)
      if (masks.labels[p] < 0) masks.labels[p] = objects + 1;
    masks.feature_dim = D;
    for (auto& v : clip) masks.features.insert(masks.features.end(), v.begin(), v.end());

    renderer.render(g, cam);
    mapper.set_clusters(ac, K);
    mapper.compute(renderer);
    const InstanceMap im = mapper.download();
    std::vector<float> feat, alpha;
    renderer.device_feature().download(feat, npix * 3);
    renderer.device_alpha().download(alpha, npix);
    const std::vector<MaskMatch> mm = score_view(im.ids, objects, feat, alpha, masks, cfg);
    expect_same_matches(mm, ref::language_scores_reference(im.ids, objects, feat, alpha, masks, true));
    acc.add_view(mm, masks);
    for (const MaskMatch& m : mm) {
      if (m.score > cfg.min_score) ref_matches[m.cluster].push_back({m.score, m.mask});
      // Own mask: measured S 0.66-0.69 (the masks, alpha > 0.3 alone, are wider
      // than the instance maps, weight > 0.5 in the full scene: IoU ~0.7).
      if (m.mask == m.cluster) {
        EXPECT_GT(m.score, 0.5) << "view " << view << " object " << m.cluster;
      }
    }
  }
  const LanguageFeatures lf = acc.finish();
  for (int o = 0; o < objects; ++o) {
    ASSERT_GT(lf.matches[o], 0) << "object " << o;
    // Cosine to every CLIP vector: the own one is best and close to 1.
    std::vector<double> cosv;
    for (auto& v : clip) {
      double dot = 0, n = 0;
      for (int k = 0; k < D; ++k) {
        dot += lf.features[o * D + k] * v[k];
        n += double(v[k]) * v[k];
      }
      cosv.push_back(dot / std::sqrt(n));
    }
    const int best = static_cast<int>(std::max_element(cosv.begin(), cosv.end()) - cosv.begin());
    EXPECT_EQ(best, o);
    EXPECT_GT(cosv[o], 0.97) << "object " << o;
    // The formula on the recorded matches.
    std::vector<double> mean(D, 0);
    double z = 0;
    for (auto& [s, m] : ref_matches[o]) {
      const double w = std::exp(10 * s);
      z += w;
      for (int k = 0; k < D; ++k) mean[k] += w * clip[m][k];
    }
    double n = 0;
    for (double& x : mean) n += (x / z) * (x / z);
    for (int k = 0; k < D; ++k) EXPECT_NEAR(lf.features[o * D + k], mean[k] / z / std::sqrt(n), 1e-6);
  }
  std::printf("matches per object:");
  for (int o = 0; o < objects; ++o) std::printf(" %d", lf.matches[o]);
  std::printf("\n");

  // Archive round trip.
  ModelArchive ar;
  language_to_archive(ar, lf, cfg);
  const LanguageFeatures back = language_from_archive(ar, objects);
  EXPECT_EQ(back.features, lf.features);
  EXPECT_EQ(back.matches, lf.matches);
  EXPECT_EQ(back.dim, D);
  EXPECT_THROW(language_from_archive(ar, objects + 1), std::runtime_error);
  EXPECT_THROW(language_from_archive(ModelArchive{}, objects), std::runtime_error);
}

}  // namespace
}  // namespace ag2gs

namespace ag2gs {
namespace {

// attach_language on a scene from disk (data_samples/synth_small at -r 2, the
// masks' own 80x60): the driver's views, resolution and device expansion
// against a loop written here on the host path (expand_reference, the
// host render()), and its errors.
TEST(Language, AttachLanguageOnSceneMatchesHostLoop) {
  SceneOptions so;
  so.resolution = 2;
  auto scene = Scene::open(test::source_dir() + "/data_samples/synth_small", so);
  AnchorConfig ac;
  ac.top_cells = 24;
  ac.init_layer = 0;
  AnchorModel model;
  model.initialise_from_points(scene->points(), scene->colors(), VoxelGrid::from_bounds(scene->bounds(), ac), ac, 7);
  for (float& o : model.opacity_logit()) o = 2.5f;  // dense enough that clusters own pixels
  // Clusters: blocks of 3x3x3 top cells.
  Clustering cl;
  std::map<std::tuple<int, int, int>, int32_t> block;
  for (size_t a = 0; a < model.size(); ++a) {
    auto key = std::make_tuple(model.cell()[3 * a] / 3, model.cell()[3 * a + 1] / 3, model.cell()[3 * a + 2] / 3);
    auto it = block.emplace(key, static_cast<int32_t>(block.size())).first;
    cl.anchor_cluster.push_back(it->second);
  }
  cl.cluster_size.assign(block.size(), 0);
  for (int32_t c : cl.anchor_cluster) ++cl.cluster_size[c];
  const std::vector<int> views = {0, 5, 11};
  LanguageConfig cfg;
  cfg.min_score = 0.1f;
  LanguageStats st;
  const LanguageFeatures lf = attach_language(test::runtime(), model, cl, *scene, views, cfg, &st);
  EXPECT_EQ(st.views, 3);
  EXPECT_GT(st.pairs, 0u);
  std::printf("scene: %zu anchors, %d clusters, %zu pairs, %zu matches, %d clusters with language\n", model.size(),
              cl.clusters(), st.pairs, st.matches, lf.with_language());
  ASSERT_GT(lf.with_language(), 0);

  const GaussianSet g = expand_reference(model, 0);
  LanguageAccumulator acc(cl.clusters(), scene->feature_dim(), cfg);
  Renderer renderer(test::runtime());
  InstanceMapper mapper(test::runtime());
  mapper.set_clusters(cl.anchor_cluster, model.children());
  for (int v : views) {
    RenderSettings rs;
    rs.sh_degree = 0;
    const RenderOutput out = renderer.render(g, scene->views()[v].camera, rs);
    mapper.compute(renderer);
    const InstanceMap im = mapper.download();
    const size_t npix = out.alpha.size();
    std::vector<float> feat(3 * npix);
    for (size_t p = 0; p < npix; ++p)
      for (int k = 0; k < 3; ++k) feat[k * npix + p] = out.feature[3 * p + k];
    const auto masks = scene->masks(v);
    acc.add_view(score_view(im.ids, cl.clusters(), feat, out.alpha, *masks, cfg), *masks);
  }
  const LanguageFeatures ref = acc.finish();
  // Device and host expansion round differently: a match near min_score may
  // flip; every cluster matched on both sides must agree closely.
  int both = 0, differ = 0;
  double max_err = 0;
  for (int c = 0; c < cl.clusters(); ++c) {
    if (lf.matches[c] != ref.matches[c]) ++differ;
    if (lf.matches[c] == 0 || lf.matches[c] != ref.matches[c]) continue;
    ++both;
    for (int k = 0; k < lf.dim; ++k)
      max_err = std::max(max_err, double(std::abs(lf.features[c * lf.dim + k] - ref.features[c * lf.dim + k])));
  }
  std::printf("driver vs host loop: %d clusters agree (max error %.3g), %d differ in match count\n", both, max_err,
              differ);
  EXPECT_GT(both, 0);
  EXPECT_LE(differ, std::max(1, cl.clusters() / 20));
  EXPECT_LT(max_err, 1e-3);

  // Errors: a clustering of another model, a scene without CLIP features.
  Clustering wrong = cl;
  wrong.anchor_cluster.pop_back();
  EXPECT_THROW(attach_language(test::runtime(), model, wrong, *scene, views, cfg), std::invalid_argument);
  namespace fs = std::filesystem;
  const fs::path plain_dir = fs::temp_directory_path() / ("ag2gs_test_language_" + std::to_string(::getpid()));
  fs::remove_all(plain_dir);
  fs::create_directories(plain_dir);
  for (const char* sub : {"images", "sparse"})
    fs::copy(fs::path(test::source_dir()) / "data_samples/synth_small" / sub, plain_dir / sub,
             fs::copy_options::recursive);
  auto plain = Scene::open(plain_dir.string(), so);
  ASSERT_EQ(plain->semantics(), SemanticsKind::none);
  try {
    attach_language(test::runtime(), model, cl, *plain, plain->train_views(), cfg);
    ADD_FAILURE() << "expected an error";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("language_features"), std::string::npos) << e.what();
  }
  fs::remove_all(plain_dir);
}

}  // namespace
}  // namespace ag2gs
