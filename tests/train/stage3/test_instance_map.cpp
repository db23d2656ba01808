// Instance maps (train/stage3/instance_map.h, kernels/instance_map.cl) against a
// double-precision CPU reference that accumulates every cluster's blending
// weight per pixel exactly, on random scenes, deep stacks and near-0.5 ties;
// plus agreement with the rendered alpha and determinism.
#include <algorithm>
#include <cstring>
#include <random>

#include "tests/reference/instance_map_reference.h"
#include "tests/test_util.h"
#include "train/stage3/instance_map.h"

namespace ag2gs {
namespace {

struct Comparison {
  size_t pixels = 0, positive = 0;  // pixels, reference ids >= 0
  size_t near_half = 0;             // mismatches where the reference is within `band` of 0.5
  size_t other_mismatch = 0;        // mismatches elsewhere (float/double threshold flips)
  double max_weight_err = 0;        // |device weight - reference W_id| where both agree on id >= 0
  size_t weight_outliers = 0;       // of those, errors above 1e-4
};

Comparison compare(const InstanceMap& m, const ref::RefInstance& r, double band = 1e-4) {
  Comparison c;
  c.pixels = m.ids.size();
  for (size_t p = 0; p < m.ids.size(); ++p) {
    c.positive += r.id[p] >= 0;
    if (m.ids[p] == r.id[p]) {
      if (r.id[p] >= 0) {
        const double err = std::abs(m.weight[p] - r.W[p].at(r.id[p]));
        if (err > 1e-4)
          ++c.weight_outliers;
        else
          c.max_weight_err = std::max(c.max_weight_err, err);
      }
      // -1 on both sides: the device weight is some cluster's weight <= 0.5.
      else
        EXPECT_LE(m.weight[p], 0.5f + 1e-4f) << "pixel " << p;
    } else if (std::abs(r.best[p] - 0.5) < band) {
      ++c.near_half;
    } else {
      ++c.other_mismatch;
    }
  }
  return c;
}

InstanceMap run_map(const GaussianSet& set, const Camera& cam, const std::vector<int32_t>& anchor_cluster, int K,
                    RenderOutput* out = nullptr) {
  Renderer renderer(test::runtime());
  RenderOutput o = renderer.render(set, cam);
  if (out) *out = o;
  InstanceMapper mapper(test::runtime());
  mapper.set_clusters(anchor_cluster, K);
  mapper.compute(renderer);
  return mapper.download();
}

// Random scene whose K children of an anchor sit close together; anchors are
// clustered by position (x bands), some unclustered.
GaussianSet clustered_scene(int anchors, int K, uint32_t seed, std::vector<int32_t>& anchor_cluster) {
  test::SceneSpec spec;
  spec.n = static_cast<size_t>(anchors) * K;
  spec.sh_degree = 0;
  spec.log_scale_lo = -3.0;
  spec.log_scale_hi = -1.2;
  GaussianSet g = test::random_scene(spec, seed);
  std::mt19937 rng(seed + 100);
  std::normal_distribution<float> nrm(0.f, 0.08f);
  anchor_cluster.assign(anchors, -1);
  for (int a = 0; a < anchors; ++a) {
    const float* m0 = &g.means[3 * static_cast<size_t>(a) * K];
    for (int i = 1; i < K; ++i)
      for (int k = 0; k < 3; ++k) g.means[3 * (static_cast<size_t>(a) * K + i) + k] = m0[k] + nrm(rng);
    const int band = std::clamp(static_cast<int>((m0[0] + 1.f) * 3.f), 0, 5);
    anchor_cluster[a] = (a % 9 == 0) ? -1 : band;
  }
  return g;
}

TEST(InstanceMap, MatchesDoubleReferenceOnRandomScenes) {
  size_t total = 0, positive = 0, near = 0, other = 0, outliers = 0;
  double max_err = 0;
  for (uint32_t seed = 1; seed <= 4; ++seed) {
    std::vector<int32_t> ac;
    const int K = 1 + static_cast<int>(seed % 3) * 2;  // 3, 5, 1, 3
    const GaussianSet g = clustered_scene(360 / K, K, seed, ac);
    const Camera cam = test::look_at_origin(70 + 3 * seed, 45 + 2 * seed);  // not multiples of 16
    const InstanceMap m = run_map(g, cam, ac, K);
    ASSERT_EQ(m.width, cam.width);
    const Comparison c = compare(m, ref::instance_map_reference(g, cam, ac, K));
    total += c.pixels;
    positive += c.positive;
    near += c.near_half;
    other += c.other_mismatch;
    outliers += c.weight_outliers;
    max_err = std::max(max_err, c.max_weight_err);
  }
  std::printf(
      "random scenes: %zu pixels, %zu with a cluster, mismatches %zu near 0.5 + %zu other, "
      "max weight error %.3g, %zu weight outliers\n",
      total, positive, near, other, max_err, outliers);
  EXPECT_GT(positive, total / 10);  // the maps are not trivially empty
  EXPECT_LT(positive, total);
  EXPECT_LE(other, total / 2000);  // float/double flips of the 1/255 or 1e-4 decisions only
  EXPECT_LE(outliers, total / 2000);
  EXPECT_LT(max_err, 2e-6);
}

// Many low-opacity Gaussians stacked along the view axis, three interleaved
// clusters with unequal shares: transmittance saturates, the weights of a
// cluster come from hundreds of Gaussians and cross 0.5 somewhere in the image.
TEST(InstanceMap, DeepStacks) {
  const int n = 400;
  GaussianSet g;
  g.sh_degree = 0;
  g.resize(n);
  std::mt19937 rng(5);
  std::uniform_real_distribution<float> u(0.f, 1.f);
  std::vector<int32_t> ac(n);
  for (int i = 0; i < n; ++i) {
    g.means[3 * i] = 0.4f * (u(rng) - 0.5f);
    g.means[3 * i + 1] = 0.4f * (u(rng) - 0.5f);
    g.means[3 * i + 2] = 3.f + 0.01f * i;
    for (int k = 0; k < 3; ++k) g.scales[3 * i + k] = 0.3f + 0.3f * u(rng);
    g.quats[4 * i] = 1.f;
    g.opacities[i] = 0.01f + 0.06f * u(rng);
    const float r = u(rng);
    ac[i] = r < 0.62f ? 0 : (r < 0.85f ? 1 : (r < 0.95f ? 2 : -1));
  }
  Camera cam;
  cam.width = 64;
  cam.height = 40;
  cam.fx = cam.fy = 50;
  cam.cx = 32.3;
  cam.cy = 19.8;
  const InstanceMap m = run_map(g, cam, ac, 1);
  const ref::RefInstance r = ref::instance_map_reference(g, cam, ac, 1);
  const Comparison c = compare(m, r);
  size_t crossing = 0;  // pixels whose best weight is within 0.05 of 0.5
  for (double b : r.best) crossing += std::abs(b - 0.5) < 0.05;
  std::printf(
      "deep stacks: %zu pixels, %zu with a cluster, %zu within 0.05 of 0.5, mismatches %zu near + %zu "
      "other, max weight error %.3g\n",
      c.pixels, c.positive, crossing, c.near_half, c.other_mismatch, c.max_weight_err);
  EXPECT_GT(c.positive, 0u);
  EXPECT_LT(c.positive, c.pixels);
  EXPECT_GT(crossing, 0u);
  EXPECT_LE(c.other_mismatch, c.pixels / 500);
  EXPECT_EQ(c.weight_outliers, 0u);
  EXPECT_LT(c.max_weight_err, 2e-5);
}

// Two broad Gaussians, one per cluster: front opacity 0.5 (weight 0.5 G at
// most, never above 0.5), back 0.99: near the centre both carry ~0.5 (the
// vote must not invent a winner), outwards the back one wins, then nobody.
TEST(InstanceMap, NearHalfTies) {
  GaussianSet g;
  g.sh_degree = 0;
  g.resize(3);
  g.means = {0.f, 0.f, 3.f, 0.05f, -0.03f, 3.5f, 0.f, 0.f, 4.f};
  g.scales = {0.6f, 0.5f, 0.5f, 0.4f, 0.45f, 0.4f, 0.2f, 0.2f, 0.2f};
  g.quats = {1, 0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0};
  g.opacities = {0.5f, 0.99f, 0.99f};
  std::vector<int32_t> ac = {0, 1, 1};
  Camera cam;
  cam.width = 48;
  cam.height = 48;
  cam.fx = cam.fy = 40;
  cam.cx = cam.cy = 24;
  const InstanceMap m = run_map(g, cam, ac, 1);
  const ref::RefInstance r = ref::instance_map_reference(g, cam, ac, 1);
  const Comparison c = compare(m, r);
  size_t ones = 0, none = 0, zeros = 0;
  for (int id : m.ids) (id == 1 ? ones : id == 0 ? zeros : none)++;
  std::printf("ties: cluster 1 %zu, cluster 0 %zu, none %zu, mismatches %zu near + %zu other\n", ones, zeros, none,
              c.near_half, c.other_mismatch);
  EXPECT_EQ(zeros, 0u);  // cluster 0 never exceeds 0.5
  EXPECT_GT(ones, 0u);
  EXPECT_GT(none, 0u);
  EXPECT_EQ(c.other_mismatch, 0u);
  EXPECT_EQ(c.weight_outliers, 0u);
}

// One cluster holding every Gaussian: its weight is the rendered alpha.
TEST(InstanceMap, SingleClusterWeightIsRenderedAlpha) {
  std::vector<int32_t> ac;
  const int K = 3;
  GaussianSet g = clustered_scene(150, K, 9, ac);
  std::fill(ac.begin(), ac.end(), 0);
  const Camera cam = test::look_at_origin(67, 51);
  RenderOutput out;
  const InstanceMap m = run_map(g, cam, ac, K, &out);
  double max_err = 0;
  size_t mismatched = 0;
  for (size_t p = 0; p < m.ids.size(); ++p) {
    max_err = std::max(max_err, static_cast<double>(std::abs(m.weight[p] - out.alpha[p])));
    const int expect = out.alpha[p] > 0.5f ? 0 : -1;
    if (m.ids[p] != expect && std::abs(out.alpha[p] - 0.5f) > 1e-5f) ++mismatched;
  }
  std::printf("one cluster: max |weight - alpha| = %.3g\n", max_err);
  EXPECT_LT(max_err, 2e-6);
  EXPECT_EQ(mismatched, 0u);
}

// The scene squeezed towards the view axis with opacities 0.3-0.9: an opaque
// stack whose pixels stop early (T < T_MIN).
void squeeze_into_opaque_stack(GaussianSet& g) {
  for (size_t i = 0; i < g.size(); ++i) {
    g.means[3 * i] *= 0.2f;
    g.means[3 * i + 1] *= 0.2f;
    g.opacities[i] = 0.3f + 0.6f * static_cast<float>(i % 7) / 6.f;
  }
}

// Stage 3's one pass: after Renderer::bin() (no blend), compute_with_images()
// writes the ids and weights of compute() after a whole forward pass, and the
// feature planes and alpha that forward pass blended, bit for bit: on random
// clustered scenes and on an opaque stack whose pixels stop early (T < T_MIN).
TEST(InstanceMap, OneWalkGivesTheForwardPassFeatureAndAlphaBitForBit) {
  auto same_bits = [](const std::vector<float>& a, const std::vector<float>& b) {
    return a.size() == b.size() && std::memcmp(a.data(), b.data(), a.size() * 4) == 0;
  };
  for (int scene = 0; scene < 3; ++scene) {
    std::vector<int32_t> ac;
    const int K = scene == 2 ? 1 : 3;
    GaussianSet g = clustered_scene(scene == 2 ? 300 : 120, K, 5 + scene, ac);
    if (scene == 2) squeeze_into_opaque_stack(g);
    const Camera cam = test::look_at_origin(61 + 4 * scene, 37 + 3 * scene);
    const size_t npix = static_cast<size_t>(cam.width) * cam.height;
    DeviceGaussians dg(test::runtime());
    dg.upload(g);
    RenderSettings settings;
    settings.sh_degree = 0;
    Renderer full(test::runtime()), binned(test::runtime());
    InstanceMapper a(test::runtime()), b(test::runtime());
    a.set_clusters(ac, K);
    b.set_clusters(ac, K);
    full.forward(dg, cam, settings);
    a.compute(full);
    binned.bin(dg, cam, settings);
    EXPECT_THROW(binned.download_output(), std::logic_error);
    b.compute_with_images(binned);
    const InstanceMap ma = a.download(), mb = b.download();
    std::vector<float> fa, fb, aa, ab;
    full.device_feature().download(fa, npix * 3);
    full.device_alpha().download(aa, npix);
    b.device_feature().download(fb, npix * 3);
    b.device_alpha().download(ab, npix);
    const size_t saturated = std::count_if(aa.begin(), aa.end(), [](float x) { return x > 1.f - 2e-4f; });
    std::printf("scene %d: %zu pixels, %zu with a cluster, %zu saturated\n", scene, npix,
                static_cast<size_t>(std::count_if(ma.ids.begin(), ma.ids.end(), [](int v) { return v >= 0; })),
                saturated);
    EXPECT_EQ(ma.ids, mb.ids);
    EXPECT_TRUE(same_bits(ma.weight, mb.weight));
    EXPECT_TRUE(same_bits(fa, fb));
    EXPECT_TRUE(same_bits(aa, ab));
    EXPECT_GT(*std::max_element(fa.begin(), fa.end()), 0.f);  // features were blended at all
    EXPECT_GT(saturated, 0u);                                 // some pixels stop early
  }
}

// A pixel that no other cluster voted on takes its vote's surplus as the
// candidate's weight instead of walking its list again: the same sum, bit for
// bit. Checked through the feature planes of the same walk: with channel 0 = 1
// on cluster c's Gaussians and 0 elsewhere, the blended channel 0 is c's
// weights summed in blending order (w * 1 = w; w * 0 = 0 adds nothing), so at
// every pixel whose id is c the map's weight equals it. Channel 1 = 1 on the
// other clusters' Gaussians tells the contested pixels (another cluster drew
// there, walk 2 runs) from the rest (it does not); both must occur.
TEST(InstanceMap, WeightIsTheWinnersBlendedShareBitForBit) {
  size_t contested = 0, alone = 0;
  for (int scene = 0; scene < 3; ++scene) {
    std::vector<int32_t> ac;
    const int K = 2;
    GaussianSet g = clustered_scene(150, K, 31 + scene, ac);
    if (scene == 2) squeeze_into_opaque_stack(g);
    const Camera cam = test::look_at_origin(53 + 4 * scene, 41 + 3 * scene);
    const size_t npix = static_cast<size_t>(cam.width) * cam.height;
    for (int c = 0; c < 6; ++c) {
      for (size_t i = 0; i < g.size(); ++i) {
        const int k = ac[i / K];
        g.features[3 * i] = k == c ? 1.f : 0.f;
        g.features[3 * i + 1] = k >= 0 && k != c ? 1.f : 0.f;
        g.features[3 * i + 2] = 0.f;
      }
      DeviceGaussians dg(test::runtime());
      dg.upload(g);
      RenderSettings settings;
      settings.sh_degree = 0;
      Renderer r(test::runtime());
      r.bin(dg, cam, settings);
      InstanceMapper mapper(test::runtime());
      mapper.set_clusters(ac, K);
      mapper.compute_with_images(r);
      const InstanceMap m = mapper.download();
      std::vector<float> f;
      mapper.device_feature().download(f, npix * 3);
      for (size_t p = 0; p < npix; ++p) {
        if (m.ids[p] != c) continue;
        ASSERT_EQ(0, std::memcmp(&m.weight[p], &f[p], 4))
            << "scene " << scene << " cluster " << c << " pixel " << p << ": " << m.weight[p] << " vs " << f[p];
        (f[npix + p] > 0.f ? contested : alone) += 1;
      }
    }
  }
  std::printf("pixels with an id: %zu contested, %zu with one cluster only\n", contested, alone);
  EXPECT_GT(contested, 50u);
  EXPECT_GT(alone, 50u);
}

TEST(InstanceMap, DeterministicAndValidated) {
  std::vector<int32_t> ac;
  const GaussianSet g = clustered_scene(100, 3, 2, ac);
  const Camera cam = test::look_at_origin(50, 40);
  const InstanceMap a = run_map(g, cam, ac, 3), b = run_map(g, cam, ac, 3);
  EXPECT_EQ(a.ids, b.ids);
  EXPECT_EQ(0, std::memcmp(a.weight.data(), b.weight.data(), a.weight.size() * 4));
  // Cluster ids of the wrong length, bad ids and thresholds are refused.
  Renderer renderer(test::runtime());
  renderer.render(g, cam);
  InstanceMapper mapper(test::runtime());
  EXPECT_THROW(mapper.compute(renderer), std::logic_error);
  mapper.set_clusters(std::vector<int32_t>(99, 0), 3);
  EXPECT_THROW(mapper.compute(renderer), std::invalid_argument);
  EXPECT_THROW(mapper.set_clusters(std::vector<int32_t>(100, -2), 3), std::invalid_argument);
  EXPECT_THROW(mapper.set_clusters(ac, 3, 0.4f), std::invalid_argument);
  // Hidden clusters: with every anchor unclustered the map is empty.
  const InstanceMap e = run_map(g, cam, std::vector<int32_t>(100, -1), 3);
  EXPECT_TRUE(std::all_of(e.ids.begin(), e.ids.end(), [](int v) { return v == -1; }));
  EXPECT_TRUE(std::all_of(e.weight.begin(), e.weight.end(), [](float v) { return v == 0.f; }));
}

}  // namespace
}  // namespace ag2gs
