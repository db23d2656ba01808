// Device backward pass against the double-precision reference's analytic
// gradients (which tests/host/render/test_reference_gradients.cpp checks against finite
// differences), for every input, the distortion term included.
#include <cstring>

#include "host/render/importance.h"
#include "tests/reference/reference_renderer.h"
#include "tests/test_util.h"

namespace ag2gs {
namespace {

OutputGrads random_output_grads(int w, int h, uint32_t seed, bool rgb = true, bool feat = true, bool depth = true,
                                bool alpha = true, bool dist = true) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<float> u(-1.f, 1.f);
  const size_t npix = static_cast<size_t>(w) * h;
  auto fill = [&](std::vector<float>& v, size_t n, bool on) {
    if (!on) return;
    v.resize(n);
    for (auto& x : v) x = u(rng);
  };
  OutputGrads g;
  fill(g.rgb, npix * 3, rgb);
  fill(g.feature, npix * 3, feat);
  fill(g.depth, npix, depth);
  fill(g.alpha, npix, alpha);
  fill(g.distortion, npix, dist);
  if (dist)
    for (auto& x : g.distortion) x *= 100.f;  // the loss weight is ~50: exercise the term
  return g;
}

// Per array: |dev - ref| <= kAbsScale * max|ref| + kRel |ref|, measured on PoCL
// (float32 accumulation over many pixels: errors are relative to the array's
// scale, not to each element).
constexpr double kAbsScale = 5e-5, kRel = 2e-3;  // worst measured: 1.7e-5 of scale

double max_abs(const std::vector<double>& v) {
  double m = 0;
  for (double x : v) m = std::max(m, std::abs(x));
  return m;
}

void check_array(const char* what, const std::vector<float>& dev, const std::vector<double>& ref) {
  double scale = max_abs(ref);
  auto r = test::compare(dev, ref, kAbsScale * scale + 1e-12, kRel);
  std::printf("  %-10s scale %.3g  max abs %.3g (%.2g of scale)  violations %zu/%zu\n", what, scale, r.max_abs,
              scale > 0 ? r.max_abs / scale : 0.0, r.violations, r.n);
  EXPECT_EQ(r.violations, 0u) << what;
  EXPECT_EQ(r.nan_mismatch, 0u) << what;
}

// Device against reference for scene g seen by cam; returns the intersections.
size_t check_backward_on(const GaussianSet& g, const Camera& cam, const OutputGrads& og,
                         const RenderSettings& settings = {}) {
  Renderer r(test::runtime());
  r.render(g, cam, settings);
  GaussianGrads dg = r.render_backward(og);
  ref::RefGrads rg = ref::render_backward(g, cam, settings, og);
  std::printf("%dx%d, %zu Gaussians, %zu intersections\n", cam.width, cam.height, g.size(), r.stats().n_intersections);
  EXPECT_GT(max_abs(rg.means), 0.0) << "no gradient at all: the test would be vacuous";
  check_array("means", dg.means, rg.means);
  check_array("scales", dg.scales, rg.scales);
  check_array("quats", dg.quats, rg.quats);
  check_array("opacities", dg.opacities, rg.opacities);
  check_array("sh", dg.sh, rg.sh);
  check_array("features", dg.features, rg.features);
  check_array("means2d", dg.means2d, rg.means2d);
  return r.stats().n_intersections;
}

void check_backward(int w, int h, size_t n, int sh, uint32_t seed, const OutputGrads& og,
                    const RenderSettings& settings = {}) {
  test::SceneSpec spec;
  spec.n = n;
  spec.sh_degree = sh;
  spec.opacity_hi = 0.9;
  check_backward_on(test::random_scene(spec, seed), test::look_at_origin(w, h), og, settings);
}

TEST(RenderBackward, AllOutputs) {
  check_backward(64, 48, 60, 3, 11, random_output_grads(64, 48, 1));
}
TEST(RenderBackward, OddSize) {
  check_backward(37, 23, 30, 1, 12, random_output_grads(37, 23, 2));
}
TEST(RenderBackward, OnlyDistortion) {
  check_backward(48, 40, 40, 0, 13, random_output_grads(48, 40, 3, false, false, false, false, true));
}
TEST(RenderBackward, OnlyAlpha) {
  check_backward(48, 40, 40, 0, 14, random_output_grads(48, 40, 4, false, false, false, true, false));
}
TEST(RenderBackward, OnlyDepth) {
  check_backward(48, 40, 40, 1, 15, random_output_grads(48, 40, 5, false, false, true, false, false));
}
TEST(RenderBackward, BackgroundAndActiveDegree) {
  RenderSettings s;
  s.background = {1.f, 0.5f, 0.25f};
  s.sh_degree = 2;
  check_backward(40, 40, 40, 3, 16, random_output_grads(40, 40, 6), s);
}
TEST(RenderBackward, OtherLowpass) {
  RenderSettings s;
  s.lowpass = 1.2f;
  check_backward(40, 40, 40, 2, 17, random_output_grads(40, 40, 6), s);
}
// One crowded tile and five empty ones: 400 faint, small Gaussians around the
// centre of tile (1, 0) of a 48x32 image (within 7 pixels of it), so the GPU layout's forward pass
// stages more records than one batch (256) holds and its backward pass runs
// many batches, while the other tiles have no Gaussian at all.
test::SceneSpec crowded_spec(double opacity_lo, double opacity_hi) {
  test::SceneSpec spec;
  spec.n = 400;
  spec.sh_degree = 1;
  spec.extent = 0.4;
  spec.log_scale_lo = -4.5;
  spec.log_scale_hi = -3.0;
  spec.opacity_lo = opacity_lo;
  spec.opacity_hi = opacity_hi;
  return spec;
}
TEST(RenderBackward, CrowdedTileAndEmptyTiles) {
  const test::SceneSpec spec = crowded_spec(0.01, 0.05);
  Camera cam = test::look_at_origin(48, 32);
  cam.cx = 24.0;  // the origin projects to the centre of tile (1, 0)
  cam.cy = 8.0;
  const size_t m = check_backward_on(test::random_scene(spec, 21), cam, random_output_grads(48, 32, 8));
  EXPECT_EQ(m, spec.n) << "every Gaussian should touch exactly the one crowded tile";
}

TEST(RenderBackward, ThousandGaussians) {
  check_backward(160, 120, 1000, 1, 17, random_output_grads(160, 120, 7));
}

// The backward of the renderer as the environment configures it: against the
// reference, and twice bit for bit.
void check_reference_and_repeat(const GaussianSet& g, const Camera& cam, const OutputGrads& og) {
  check_backward_on(g, cam, og);
  Renderer a(test::runtime()), b(test::runtime());
  a.render(g, cam);
  b.render(g, cam);
  const GaussianGrads ga = a.render_backward(og), gb = b.render_backward(og);
  EXPECT_EQ(ga.means, gb.means);
  EXPECT_EQ(ga.opacities, gb.opacities);
  EXPECT_EQ(ga.sh, gb.sh);
}

// Every blend backward plan of the GPU layout (kernels/blend_bwd.cl: pixels
// per work-item, Gaussians per staging batch, work-items per summed value)
// against the reference, on a crowded tile that needs many batches and an odd
// image size whose edge tiles are partly outside; each plan twice, bit for bit.
// The plans sum the same partials in other orders, so they may differ from one
// another in the last bits, never from the reference.
TEST(RenderBackward, EveryBlendBwdPlanMatchesTheReference) {
  const char* old = std::getenv("AG2GS_BLEND_STAGING");
  const std::string saved = old ? old : "";
  setenv("AG2GS_BLEND_STAGING", "1", 1);
  const GaussianSet crowded = test::random_scene(crowded_spec(0.05, 0.6), 21);
  Camera cam = test::look_at_origin(37, 23);
  cam.cx = 24.0;
  cam.cy = 8.0;
  const OutputGrads og = random_output_grads(37, 23, 9);
  for (const char* plan : {"1:2:1", "1:2:8", "1:1:256", "1:3:2", "2:4:4", "2:5:128", "4:8:1", "4:8:2", "4:7:64",
                           "8:16:1", "8:1:32", "16:32:1", "16:3:16"}) {
    SCOPED_TRACE(plan);
    setenv("AG2GS_BLEND_BWD", plan, 1);
    const uint64_t local = test::runtime().info().local_mem;
    if (local > 0 && parse_blend_bwd_plan(plan).local_bytes() > local) {
      // A GPU's 48 KB hold fewer Gaussians per batch than PoCL's megabytes.
      std::printf("plan %s: needs %zu bytes of local memory, the device has %llu: refused\n", plan,
                  parse_blend_bwd_plan(plan).local_bytes(), static_cast<unsigned long long>(local));
      EXPECT_THROW(Renderer r(test::runtime()), std::invalid_argument);
      continue;
    }
    std::printf("plan %s: ", plan);
    check_reference_and_repeat(crowded, cam, og);
    EXPECT_EQ(Renderer(test::runtime()).blend_bwd_plan(), plan);
  }
  unsetenv("AG2GS_BLEND_BWD");
  if (old)
    setenv("AG2GS_BLEND_STAGING", saved.c_str(), 1);
  else
    unsetenv("AG2GS_BLEND_STAGING");
}

// The CPU layout's backward at each pixel width it may take (the device's
// native float width: 4, 8 or 16) against the reference, twice bit for bit,
// beside a forward at the runtime's own width; and the rule that picks it.
TEST(RenderBackward, EveryCpuBackwardWidthMatchesTheReference) {
  const std::string saved_vw = std::getenv("AG2GS_VECTOR_WIDTH") ? std::getenv("AG2GS_VECTOR_WIDTH") : "";
  unsetenv("AG2GS_VECTOR_WIDTH");
  DeviceInfo d = test::runtime().info();
  for (auto [native, expected] : {std::pair{0u, 16}, {4u, 4}, {8u, 8}, {16u, 16}, {32u, 16}}) {
    d.native_float_width = native;
    EXPECT_EQ(cpu_blend_bwd_vector_width(d), expected) << native;
  }
  setenv("AG2GS_BWD_VECTOR_WIDTH", "3", 1);
  try {
    (void)cpu_blend_bwd_vector_width(d);
    ADD_FAILURE() << "accepted";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("AG2GS_BWD_VECTOR_WIDTH"), std::string::npos) << e.what();
  }
  if (!blend_staging_for(test::runtime().info())) {
    const GaussianSet crowded = test::random_scene(crowded_spec(0.05, 0.6), 23);
    Camera cam = test::look_at_origin(37, 23);
    cam.cx = 24.0;
    cam.cy = 8.0;
    const OutputGrads og = random_output_grads(37, 23, 11);
    for (const char* width : {"4", "8", "16"}) {
      SCOPED_TRACE(width);
      setenv("AG2GS_BWD_VECTOR_WIDTH", width, 1);
      std::printf("CPU backward width %s: ", width);
      check_reference_and_repeat(crowded, cam, og);
    }
  }
  unsetenv("AG2GS_BWD_VECTOR_WIDTH");
  if (!saved_vw.empty()) setenv("AG2GS_VECTOR_WIDTH", saved_vw.c_str(), 1);
}

// A plan the kernel cannot run is refused naming the variable.
TEST(RenderBackward, BadBlendBwdPlanIsRefused) {
  for (const char* bad : {"", "1:2", "3:2:1", "1:0:1", "1:2:3", "1:2:512", "32:2:1", "a:b:c", "1:2:1:4", "1:200:1"}) {
    SCOPED_TRACE(bad);
    if (!*bad) {
      EXPECT_THROW(parse_blend_bwd_plan(bad), std::invalid_argument);
      continue;
    }
    setenv("AG2GS_BLEND_BWD", bad, 1);
    try {
      (void)blend_bwd_plan_for(test::runtime().info());
      ADD_FAILURE() << "accepted";
    } catch (const std::invalid_argument& e) {
      EXPECT_NE(std::string(e.what()).find("AG2GS_BLEND_BWD"), std::string::npos) << e.what();
    }
  }
  unsetenv("AG2GS_BLEND_BWD");
  EXPECT_EQ(parse_blend_bwd_plan("4:8:2").describe(), "4:8:2");
}

// blend_weights stages more records per batch than blend_bwd where local
// memory allows (BlendWeightsEqualTheFeatureBackwardBitForBit checks that its
// bits do not depend on it), and falls back towards blend_bwd's batch on a
// device with little local memory.
TEST(RenderBackward, WeightsBatchFitsLocalMemory) {
  unsetenv("AG2GS_BLEND_BWD");
  DeviceInfo big;
  big.name = "a device with 48 KB of local memory";
  big.local_mem = 48 * 1024;
  const BlendBwdPlan p = blend_bwd_plan_for(big);
  EXPECT_EQ(p.weights_batch, 32);
  EXPECT_GT(p.weights_batch, p.batch);
  EXPECT_LE(p.weights_local_bytes(), big.local_mem);
  for (uint64_t local : {uint64_t{32768}, uint64_t{16384}, uint64_t{8192}}) {
    DeviceInfo small = big;
    small.local_mem = local;
    const BlendBwdPlan q = blend_bwd_plan_for(small);
    SCOPED_TRACE(std::to_string(local) + " bytes, plan " + q.describe());
    EXPECT_GE(q.weights_batch, q.batch);
    if (q.weights_batch > q.batch) EXPECT_LE(q.weights_local_bytes(), local);
  }
}

}  // namespace
// The device-gradient entry point (used by the trainer, whose losses run on
// the device) computes exactly what the host entry point computes.
TEST(RenderBackward, DeviceGradientsMatchHostGradientsBitForBit) {
  const int w = 45, h = 29;
  test::SceneSpec spec;
  spec.n = 300;
  spec.sh_degree = 2;
  spec.opacity_hi = 0.9;
  const GaussianSet g = test::random_scene(spec, 11);
  const Camera cam = test::look_at_origin(w, h);
  for (bool all : {true, false}) {
    const OutputGrads og = random_output_grads(w, h, 12, true, all, all, all, true);
    Renderer host(test::runtime());
    host.render(g, cam);
    const GaussianGrads a = host.render_backward(og);

    Renderer dev(test::runtime());
    DeviceGaussians dg(test::runtime());
    dg.upload(g);
    dev.forward(dg, cam, {});
    const size_t npix = static_cast<size_t>(w) * h;
    auto planar = [&](const std::vector<float>& hwc, int c) {
      std::vector<float> out(hwc.size());
      for (size_t p = 0; p < npix; ++p)
        for (int k = 0; k < c; ++k) out[k * npix + p] = hwc[p * c + k];
      return out;
    };
    DeviceBuffer rgb(&test::runtime()), feat(&test::runtime()), depth(&test::runtime()), alpha(&test::runtime()),
        dist(&test::runtime());
    Renderer::DeviceOutputGrads dog;
    rgb.upload(planar(og.rgb, 3));
    dog.rgb = &rgb;
    dist.upload(og.distortion);
    dog.distortion = &dist;
    if (all) {
      feat.upload(planar(og.feature, 3));
      depth.upload(og.depth);
      alpha.upload(og.alpha);
      dog.feature = &feat;
      dog.depth = &depth;
      dog.alpha = &alpha;
    }
    dev.backward(dog);
    const GaussianGrads b = dev.download_grads();
    EXPECT_EQ(a.means, b.means);
    EXPECT_EQ(a.scales, b.scales);
    EXPECT_EQ(a.quats, b.quats);
    EXPECT_EQ(a.opacities, b.opacities);
    EXPECT_EQ(a.sh, b.sh);
    EXPECT_EQ(a.features, b.features);
    EXPECT_EQ(a.means2d, b.means2d);
  }
  // A device gradient smaller than the frame is refused.
  Renderer dev(test::runtime());
  dev.render(g, cam);
  DeviceBuffer small(&test::runtime());
  small.upload(std::vector<float>(10, 0.f));
  Renderer::DeviceOutputGrads dog;
  dog.rgb = &small;
  EXPECT_THROW(dev.backward(dog), std::invalid_argument);
}

// blend_weight_sums (the importance prune's measure, read from the blend
// backward) against its definition computed another way: the double
// reference's forward render of a scene where only Gaussian i carries a
// feature (1, 0, 0), summed over the pixels, is Gaussian i's weights summed.
// Two cameras of different sizes; every Gaussian, seen or not.
TEST(RenderBackward, BlendWeightSumsAreEachGaussiansWeightsSummedOverThePixels) {
  test::SceneSpec spec;
  spec.n = 60;
  spec.sh_degree = 1;
  const GaussianSet g = test::random_scene(spec, 71);
  const std::vector<Camera> cams = {test::look_at_origin(40, 30), test::look_at(Eigen::Vector3d(1.5, -3.0, 2.5),
                                                                                Eigen::Vector3d::Zero(), 33, 27, 30.0)};
  Runtime& rt = test::runtime();
  DeviceGaussians dg(rt);
  dg.upload(g);
  Renderer r(rt);
  RenderSettings settings;
  const std::vector<double> sums = blend_weight_sums(r, dg, cams, settings);
  ASSERT_EQ(sums.size(), g.size());
  ref::RefGaussians one = ref::to_double(g);
  std::vector<double> expected(g.size(), 0.0);
  for (size_t i = 0; i < g.size(); ++i) {
    std::fill(one.features.begin(), one.features.end(), 0.0);
    one.features[3 * i] = 1.0;
    for (const Camera& cam : cams) {
      const ref::RefImages im = ref::render(one, cam, settings);
      for (size_t p = 0; p < im.feature.size(); p += 3) expected[i] += im.feature[p];
    }
  }
  double largest = 0;
  size_t seen = 0;
  for (double e : expected) {
    largest = std::max(largest, e);
    seen += e > 0.5;
  }
  EXPECT_GT(seen, g.size() / 4) << "most Gaussians should draw something for the test to mean anything";
  // The float blend against double: measured 5e-7 relative, 3.3e-6 px.
  test::expect_close("weight sums", test::compare(sums, expected, 1e-4 * largest, 1e-4));
  // Twice: the same bits.
  EXPECT_EQ(blend_weight_sums(r, dg, cams, settings), sums);
}

// Renderer::blend_weights (one walk, no forward pass) against the backward of
// an upstream gradient of 1 on feature channel 0, which it replaces in the
// importance prune: equal bit for bit, in the layout this run uses and in
// several GPU-layout plans (batches, segments, pixels per work-item). Opaque
// Gaussians, so pixels stop (T below T_MIN) inside and across batches, on an
// odd-sized image whose edge tiles are partly outside.
TEST(RenderBackward, BlendWeightsEqualTheFeatureBackwardBitForBit) {
  const GaussianSet dense = test::random_scene(crowded_spec(0.3, 0.99), 23);
  test::SceneSpec spread;
  spread.n = 300;
  spread.sh_degree = 1;
  spread.opacity_lo = 0.2;
  spread.opacity_hi = 0.99;
  const GaussianSet wide = test::random_scene(spread, 24);
  Camera cam = test::look_at_origin(37, 23);
  cam.cx = 24.0;
  cam.cy = 8.0;
  const std::vector<Camera> cams = {cam, test::look_at_origin(53, 41)};
  auto check = [&](const char* layout) {
    SCOPED_TRACE(layout);
    Runtime& rt = test::runtime();
    size_t opaque = 0;
    for (const GaussianSet* g : {&dense, &wide}) {
      DeviceGaussians dg(rt);
      dg.upload(*g);
      Renderer r(rt);
      RenderSettings settings;
      for (const Camera& c : cams) {
        r.forward(dg, c, settings);
        const size_t npix = static_cast<size_t>(c.width) * c.height;
        std::vector<float> up(3 * npix, 0.f);
        std::fill(up.begin(), up.begin() + static_cast<std::ptrdiff_t>(npix), 1.f);
        DeviceBuffer upstream(&rt);
        upstream.upload(up);
        Renderer::DeviceOutputGrads og;
        og.feature = &upstream;
        r.backward(og);
        std::vector<float> via_backward, via_walk;
        r.device_grads().features->download(via_backward, 3 * g->size());
        r.bin(dg, c, settings);
        r.blend_weights();
        r.device_weight_sums().download(via_walk, g->size());
        size_t drawn = 0;
        for (size_t i = 0; i < g->size(); ++i) {
          ASSERT_EQ(0, std::memcmp(&via_walk[i], &via_backward[3 * i], 4))
              << "Gaussian " << i << " at " << c.width << "x" << c.height << ": " << via_walk[i] << " vs "
              << via_backward[3 * i];
          drawn += via_walk[i] > 0.5f;
        }
        EXPECT_GT(drawn, g->size() / 10) << "the scene should draw for the test to mean anything";
        // With an upstream plane (pixels at 0, 1 and 0.37, as the removal's
        // view checks count some pixels only), the sums are that plane's
        // feature gradient.
        std::vector<float> plane(npix);
        for (size_t p = 0; p < npix; ++p) plane[p] = p % 3 == 0 ? 0.f : p % 3 == 1 ? 1.f : 0.37f;
        std::copy(plane.begin(), plane.end(), up.begin());
        upstream.upload(up);
        r.forward(dg, c, settings);
        r.backward(og);
        r.device_grads().features->download(via_backward, 3 * g->size());
        r.bin(dg, c, settings);
        r.blend_weights(plane);
        r.device_weight_sums().download(via_walk, g->size());
        for (size_t i = 0; i < g->size(); ++i)
          ASSERT_EQ(0, std::memcmp(&via_walk[i], &via_backward[3 * i], 4))
              << "Gaussian " << i << " with the upstream plane: " << via_walk[i] << " vs " << via_backward[3 * i];
        // Pixels nearly opaque (T < 1e-3, ten times T_MIN): where the stop rule acts.
        const RenderOutput out = r.render(*g, c, settings);
        opaque +=
            static_cast<size_t>(std::count_if(out.alpha.begin(), out.alpha.end(), [](float a) { return a > 0.999f; }));
      }
    }
    EXPECT_GT(opaque, 20u) << "too few nearly opaque pixels to test where pixels stop";
  };
  check("this run's layout");
  const char* old = std::getenv("AG2GS_BLEND_STAGING");
  const std::string saved = old ? old : "";
  setenv("AG2GS_BLEND_STAGING", "1", 1);
  const uint64_t local = test::runtime().info().local_mem;
  for (const char* plan : {"1:2:1", "1:3:2", "4:8:2", "4:7:64", "8:1:32", "16:3:16"}) {
    if (local > 0 && parse_blend_bwd_plan(plan).local_bytes() > local) continue;  // refused on this device
    setenv("AG2GS_BLEND_BWD", plan, 1);
    check(plan);
  }
  unsetenv("AG2GS_BLEND_BWD");
  if (old)
    setenv("AG2GS_BLEND_STAGING", saved.c_str(), 1);
  else
    unsetenv("AG2GS_BLEND_STAGING");
}

}  // namespace ag2gs
