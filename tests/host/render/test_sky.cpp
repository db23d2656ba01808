// The sky (host/render/sky.h, kernels/sky.cl) against a double-precision
// reference written here from its definition, the reference's SH basis
// against orthonormality on the sphere, its gradients against central
// differences, and a training run under an open sky with and without it.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <random>

#include "host/io/colmap_reader.h"
#include "host/io/image_io.h"
#include "host/io/ply_io.h"
#include "host/render/sky.h"
#include "host/render/sky_bake.h"
#include "tests/cli_test_util.h"
#include "tests/io_test_util.h"
#include "tests/reference/reference_renderer.h"
#include "tests/reference/sky_reference.h"
#include "tests/test_util.h"

namespace ag2gs {
namespace {

using Eigen::Vector3d;

struct Planes {
  std::vector<float> rgb, alpha, grad;  // [3,H,W], [H,W], [3,H,W]
};

Planes random_planes(int w, int h, uint32_t seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<float> u(0.f, 1.f), s(-1.f, 1.f);
  Planes p;
  const size_t n = static_cast<size_t>(w) * h;
  for (size_t i = 0; i < 3 * n; ++i) p.rgb.push_back(u(rng));
  for (size_t i = 0; i < n; ++i) p.alpha.push_back(i % 7 == 0 ? 0.f : i % 11 == 0 ? 1.f : u(rng));
  for (size_t i = 0; i < 3 * n; ++i) p.grad.push_back(s(rng));
  return p;
}

std::vector<float> random_coefficients(int degree, uint32_t seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<float> s(-0.6f, 0.6f);
  std::vector<float> c(static_cast<size_t>((degree + 1) * (degree + 1)) * 3);
  for (float& v : c) v = s(rng);
  return c;
}

Camera tilted_camera(int w, int h) {
  return test::look_at(Vector3d(2.5, -1.0, 1.7), Vector3d(0.3, 0.2, -0.4), w, h, 0.9 * w);
}

TEST(Sky, ReferenceBasisIsOrthonormalOnTheSphere) {
  // Midpoint rule in (cos theta, phi): exact enough for degree-6 products.
  const int nu = 400, nphi = 800;
  double gram[16][16] = {};
  for (int i = 0; i < nu; ++i) {
    const double z = -1.0 + (i + 0.5) * 2.0 / nu, r = std::sqrt(1 - z * z);
    for (int j = 0; j < nphi; ++j) {
      const double phi = (j + 0.5) * 2 * M_PI / nphi;
      double b[16];
      ref::sh_values(3, Vector3d(r * std::cos(phi), r * std::sin(phi), z), b);
      for (int a = 0; a < 16; ++a)
        for (int c = 0; c < 16; ++c) gram[a][c] += b[a] * b[c] * (2.0 / nu) * (2 * M_PI / nphi);
    }
  }
  for (int a = 0; a < 16; ++a)
    for (int c = 0; c < 16; ++c) EXPECT_NEAR(gram[a][c], a == c ? 1.0 : 0.0, 1e-4) << a << "," << c;
}

TEST(Sky, ComposeMatchesTheDoubleReference) {
  Runtime& rt = test::runtime();
  for (int degree = 0; degree <= 3; ++degree) {
    const int w = 37, h = 23;
    const Camera cam = tilted_camera(w, h);
    const Planes p = random_planes(w, h, 3 + degree);
    const std::vector<float> coef = random_coefficients(degree, 11 + degree);
    Sky sky(rt);
    sky.set(degree, coef);
    DeviceBuffer rgb(&rt), alpha(&rt);
    rgb.upload(p.rgb);
    alpha.upload(p.alpha);
    std::vector<float> out;
    sky.compose(rgb, alpha, cam).download(out, p.rgb.size());
    const size_t n = static_cast<size_t>(w) * h;
    double worst = 0;
    for (int y = 0; y < h; ++y)
      for (int x = 0; x < w; ++x) {
        const size_t i = static_cast<size_t>(y) * w + x;
        const Vector3d s = ref::sky_radiance(degree, coef, ref::pixel_ray(cam, x, y));
        for (int c = 0; c < 3; ++c)
          worst = std::max(worst, std::abs(out[c * n + i] - (p.rgb[c * n + i] + (1.0 - p.alpha[i]) * s[c])));
      }
    EXPECT_LT(worst, 2e-6) << "degree " << degree;
  }
}

TEST(Sky, ReferenceGradientMatchesCentralDifferences) {
  const int degree = 3, w = 9, h = 7;
  const Camera cam = tilted_camera(w, h);
  const Planes p = random_planes(w, h, 5);
  const std::vector<float> coef = random_coefficients(degree, 6);
  const ref::RefSkyGrad g = ref::sky_backward_reference(degree, coef, p.grad, p.alpha, cam);
  std::vector<double> c(coef.begin(), coef.end()), a(p.alpha.begin(), p.alpha.end());
  auto loss = [&](const std::vector<double>& coef_d, const std::vector<double>& alpha_d) {
    return ref::sky_loss_reference(degree, coef_d, alpha_d, p.rgb, p.grad, cam);
  };
  const double e = 1e-6;
  for (size_t j = 0; j < c.size(); ++j) {
    std::vector<double> cp = c, cm = c;
    cp[j] += e;
    cm[j] -= e;
    const double fd = (loss(cp, a) - loss(cm, a)) / (2 * e);
    EXPECT_NEAR(g.coef[j], fd, 1e-6 * (1 + std::abs(fd))) << "coefficient " << j;
  }
  for (size_t i = 0; i < a.size(); i += 5) {
    std::vector<double> ap = a, am = a;
    ap[i] += e;
    am[i] -= e;
    const double fd = (loss(c, ap) - loss(c, am)) / (2 * e);
    EXPECT_NEAR(g.alpha[i], fd, 1e-6 * (1 + std::abs(fd))) << "alpha " << i;
  }
}

// Sizes below one chunk, a partial last chunk, and over 1024 chunks' worth;
// with a base alpha gradient to add to, also with pixel weights.
TEST(Sky, BackwardMatchesTheReferenceAndRepeatsBitForBit) {
  Runtime& rt = test::runtime();
  const std::pair<int, int> sizes[] = {{5, 3}, {37, 23}, {301, 229}};
  for (const auto& [w, h] : sizes) {
    for (bool add : {false, true}) {
      const int degree = 3;
      const Camera cam = tilted_camera(w, h);
      const Planes p = random_planes(w, h, w + h);
      const std::vector<float> coef = random_coefficients(degree, w);
      std::vector<float> weight;
      if (add)
        for (size_t i = 0; i < p.alpha.size(); ++i) weight.push_back(i % 3 == 0 ? 0.f : 0.25f * (i % 5));
      std::vector<float> base(p.alpha.size());  // the alpha gradient to add to
      for (size_t i = 0; i < base.size(); ++i) base[i] = p.alpha[i] * 0.5f;
      const ref::RefSkyGrad want =
          ref::sky_backward_reference(degree, coef, p.grad, p.alpha, cam, add ? &base : nullptr, weight);
      Sky sky(rt);
      sky.set(degree, coef);
      DeviceBuffer grad(&rt), alpha(&rt), ga(&rt), wbuf(&rt);
      grad.upload(p.grad);
      alpha.upload(p.alpha);
      if (add) wbuf.upload(weight);
      std::vector<float> got_alpha, got_coef, again;
      for (int run = 0; run < 2; ++run) {
        ga.upload(base);
        sky.backward(grad, alpha, cam, ga, add, add ? &wbuf : nullptr);
        ga.download(got_alpha, base.size());
        sky.gradient().download(run == 0 ? got_coef : again, coef.size());
      }
      EXPECT_EQ(0, std::memcmp(got_coef.data(), again.data(), got_coef.size() * sizeof(float)));
      double worst_a = 0, scale = 0, worst_c = 0;
      for (size_t i = 0; i < got_alpha.size(); ++i) worst_a = std::max(worst_a, std::abs(got_alpha[i] - want.alpha[i]));
      for (double v : want.coef) scale = std::max(scale, std::abs(v));
      for (size_t j = 0; j < got_coef.size(); ++j) worst_c = std::max(worst_c, std::abs(got_coef[j] - want.coef[j]));
      EXPECT_LT(worst_a, 5e-6) << w << "x" << h << " add " << add;
      EXPECT_LT(worst_c, 1e-5 * scale + 1e-6) << w << "x" << h << " add " << add << " (largest " << scale << ")";
    }
  }
}

// backward() takes sky(d) from the compose() before it when that was for
// the same camera and coefficients: the same bits as evaluating it afresh.
// After another camera's compose, or after the coefficients were handed to
// an optimiser and changed, it evaluates sky(d) again.
TEST(Sky, BackwardAfterComposeGivesTheBitsOfBackwardAlone) {
  Runtime& rt = test::runtime();
  const int w = 41, h = 29, degree = 3;
  const Camera cam = tilted_camera(w, h), other = tilted_camera(h, w);
  const Planes p = random_planes(w, h, 5);
  std::vector<float> weight;
  for (size_t i = 0; i < p.alpha.size(); ++i) weight.push_back(i % 4 == 0 ? 0.f : 0.5f);
  const std::vector<float> coef = random_coefficients(degree, 7), coef2 = random_coefficients(degree, 8);
  DeviceBuffer rgb(&rt), alpha(&rt), grad(&rt), ga(&rt), wbuf(&rt), rgb_other(&rt), alpha_other(&rt);
  rgb.upload(p.rgb);
  alpha.upload(p.alpha);
  grad.upload(p.grad);
  wbuf.upload(weight);
  rgb_other.upload(std::vector<float>(p.rgb.size(), 0.f));
  alpha_other.upload(std::vector<float>(p.alpha.size(), 0.f));
  auto backward = [&](Sky& sky) {
    ga.fill_zero(p.alpha.size() * sizeof(float));
    sky.backward(grad, alpha, cam, ga, false, &wbuf);
    std::vector<float> a, c;
    ga.download(a, p.alpha.size());
    sky.gradient().download(c, coef.size());
    return std::make_pair(test::hash_vec(a), test::hash_vec(c));
  };
  Sky alone(rt), composed(rt);
  alone.set(degree, coef);
  composed.set(degree, coef);
  const auto ref = backward(alone);
  composed.compose(rgb, alpha, cam);
  EXPECT_EQ(backward(composed), ref);
  composed.compose(rgb_other, alpha_other, other);  // another camera's sky colours
  EXPECT_EQ(backward(composed), ref);
  // New coefficients written through coefficients() after a compose.
  composed.compose(rgb, alpha, cam);
  composed.coefficients().upload(coef2);
  alone.set(degree, coef2);
  EXPECT_EQ(backward(composed), backward(alone));
  EXPECT_NE(backward(alone), ref);
}

TEST(Sky, ConstantStartAndArchiveRoundTrip) {
  Runtime& rt = test::runtime();
  const std::vector<float> c = sky_constant(2, {0.25f, 0.5f, 1.f});
  ASSERT_EQ(c.size(), 27u);
  EXPECT_EQ(sky_degree_for(27), 2);
  EXPECT_EQ(sky_degree_for(26), -1);
  // A constant sky composes to the colour in every direction.
  const Camera cam = tilted_camera(6, 4);
  Sky sky(rt);
  sky.set(2, c);
  DeviceBuffer rgb(&rt), alpha(&rt);
  rgb.upload(std::vector<float>(72, 0.f));
  alpha.upload(std::vector<float>(24, 0.f));
  std::vector<float> out;
  sky.compose(rgb, alpha, cam).download(out, 72);
  for (int i = 0; i < 24; ++i) {
    EXPECT_NEAR(out[i], 0.25f, 1e-6);
    EXPECT_NEAR(out[24 + i], 0.5f, 1e-6);
    EXPECT_NEAR(out[48 + i], 1.f, 1e-6);
  }
  ModelArchive a;
  EXPECT_FALSE(sky_from_archive(a).has_value());
  sky_to_archive(a, c);
  ASSERT_TRUE(sky_from_archive(a).has_value());
  EXPECT_EQ(*sky_from_archive(a), c);
  ModelArchive bad;
  bad.source = "m/model.ag2gs";
  bad.put("sky/sh", std::vector<float>(15, 0.f), {5, 3});
  try {
    sky_from_archive(bad);
    FAIL() << "a 5-coefficient sky was accepted";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("m/model.ag2gs"), std::string::npos) << e.what();
  }
  EXPECT_THROW(sky.set(4, std::vector<float>(75, 0.f)), std::invalid_argument);
  EXPECT_THROW(sky.set(1, std::vector<float>(3, 0.f)), std::invalid_argument);
}

// Photos of a sky alone, from cameras looking six ways: the fit gives back
// its coefficients (up to the small ridge).
TEST(Sky, FitRecoversAKnownSky) {
  Runtime& rt = test::runtime();
  const int degree = 3, w = 48, h = 40;
  const std::vector<float> truth = random_coefficients(degree, 21);
  Sky sky(rt);
  sky.set(degree, truth);
  DeviceBuffer rgb(&rt), alpha(&rt), photo(&rt);
  rgb.upload(std::vector<float>(3 * w * h, 0.f));
  alpha.upload(std::vector<float>(w * h, 0.f));
  const Vector3d dirs[] = {{1, 0, 0}, {-1, 0, 0}, {0, 1, 0}, {0, -1, 0}, {0, 0.1, 1}, {0, 0.1, -1}};
  Eigen::MatrixXd gram, rhs;
  Sky fit(rt);
  fit.set(degree, sky_constant(degree, {0.f, 0.f, 0.f}));
  for (const Vector3d& d : dirs) {
    const Camera cam = test::look_at(Vector3d::Zero(), d, w, h, 0.4 * w);
    std::vector<float> img;
    sky.compose(rgb, alpha, cam).download(img, 3 * w * h);
    photo.upload(img);
    fit.add_fit(photo, cam, gram, rhs);
  }
  const std::vector<float> got = Sky::solve_fit(gram, rhs);
  ASSERT_EQ(got.size(), truth.size());
  for (size_t j = 0; j < got.size(); ++j) EXPECT_NEAR(got[j], truth[j], 0.02) << "coefficient " << j;
  // Nothing seen: no sky.
  EXPECT_EQ(Sky::solve_fit(Eigen::MatrixXd::Zero(16, 16), Eigen::MatrixXd::Zero(16, 3)), std::vector<float>(48, 0.f));
}

// The fit's RMS error from its sums alone (Sky::fit_residual_rms) against
// the error computed pixel by pixel in double: photos of a known sky plus a
// fixed pattern of +-0.1 and +-0.05 (so the error is not the sky's to fit
// away), and of the sky alone (error about 0).
TEST(Sky, FitResidualMatchesThePixelError) {
  Runtime& rt = test::runtime();
  const int degree = 2, w = 40, h = 32;
  const std::vector<float> truth = random_coefficients(degree, 5);
  Sky sky(rt);
  sky.set(degree, truth);
  DeviceBuffer rgb(&rt), alpha(&rt), photo(&rt);
  rgb.upload(std::vector<float>(3 * w * h, 0.f));
  alpha.upload(std::vector<float>(w * h, 0.f));
  const Vector3d dirs[] = {{1, 0, 0}, {-1, 0.2, 0}, {0, 0.1, 1}, {0.3, -0.2, -1}};
  for (const double noise : {0.0, 1.0}) {
    Eigen::MatrixXd gram, rhs;
    Eigen::Vector3d squares = Eigen::Vector3d::Zero();
    Sky fit(rt);
    fit.set(degree, sky_constant(degree, {0.f, 0.f, 0.f}));
    std::vector<std::vector<float>> photos;
    std::vector<Camera> cams;
    for (const Vector3d& d : dirs) {
      const Camera cam = test::look_at(Vector3d::Zero(), d, w, h, 0.4 * w);
      std::vector<float> img;
      sky.compose(rgb, alpha, cam).download(img, 3 * w * h);
      for (size_t i = 0; i < img.size(); ++i)
        img[i] += static_cast<float>(noise * (i % 2 ? 0.1 : -0.05) * (i % 3 ? 1 : -1));
      photo.upload(img);
      fit.add_fit(photo, cam, gram, rhs, nullptr, &squares);
      photos.push_back(img);
      cams.push_back(cam);
    }
    const std::vector<float> got = Sky::solve_fit(gram, rhs);
    double se = 0, n = 0;
    for (size_t v = 0; v < cams.size(); ++v)
      for (int y = 0; y < h; ++y)
        for (int x = 0; x < w; ++x) {
          const Vector3d s = ref::sky_radiance(degree, got, ref::pixel_ray(cams[v], x, y));
          for (int c = 0; c < 3; ++c) {
            const double e = photos[v][static_cast<size_t>(c) * w * h + y * w + x] - s[c];
            se += e * e;
            n += 1;
          }
        }
    const double direct = std::sqrt(se / n), from_sums = Sky::fit_residual_rms(gram, rhs, squares, got);
    std::printf("  noise x%.0f: fit RMS %.5f from the sums, %.5f pixel by pixel\n", noise, from_sums, direct);
    EXPECT_NEAR(from_sums, direct, 2e-3);
    if (noise > 0)
      EXPECT_GT(direct, 0.05) << "the pattern must not be the sky's to fit";
    else
      EXPECT_LT(from_sums, 5e-3);
  }
}

// A pixel is open when no SfM point in front of the camera projects within
// the radius; block weights are the open fraction of each block.
TEST(Sky, OpenPixelsAndTheirBlockWeights) {
  const Camera cam = test::look_at(Vector3d(0, 0, -5), Vector3d::Zero(), 40, 30, 40);
  // One point at the centre of the view, one behind the camera.
  const std::vector<Vector3d> points = {Vector3d::Zero(), Vector3d(0, 0, -10)};
  EXPECT_EQ(open_sky_radius(cam), 2);
  const std::vector<uint8_t> open = open_sky_pixels(cam, points, 3);
  ASSERT_EQ(open.size(), 1200u);
  const Eigen::Vector3d c = cam.R * Vector3d::Zero() + cam.t;
  const int u = static_cast<int>(cam.fx * c.x() / c.z() + cam.cx),
            v = static_cast<int>(cam.fy * c.y() / c.z() + cam.cy);
  size_t closed = 0;
  for (int y = 0; y < 30; ++y)
    for (int x = 0; x < 40; ++x) {
      const bool near = (x - u) * (x - u) + (y - v) * (y - v) <= 9;
      EXPECT_EQ(open[y * 40 + x], near ? 0 : 1) << x << "," << y;
      closed += open[y * 40 + x] == 0;
    }
  EXPECT_GT(closed, 20u);
  EXPECT_EQ(open_sky_pixels(cam, {}, 3), std::vector<uint8_t>(1200, 1));
  std::vector<float> w;
  open_sky_weights(open, 40, 30, 4, w);
  ASSERT_EQ(w.size(), 70u);  // 40 / 4 by 30 / 4, rounded down
  for (int by = 0; by < 7; ++by)
    for (int bx = 0; bx < 10; ++bx) {
      int n = 0;
      for (int j = 0; j < 4; ++j)
        for (int i = 0; i < 4; ++i) n += open[(by * 4 + j) * 40 + bx * 4 + i];
      EXPECT_FLOAT_EQ(w[by * 10 + bx], n / 16.f);
    }
}

// The far shell's points lie on the sphere, on their pixels' rays, one per
// open pixel of the stride grid, with the photo's colour there.
TEST(Sky, FarShellPointsLieOnTheSphereAlongTheirRays) {
  const Camera cam = test::look_at(Vector3d(-5, 0.3, 0.5), Vector3d::Zero(), 40, 30, 40);
  const Vector3d centre(0.5, -0.25, 1.0);
  // 98% of these 100 points lie within 3 of the centre; two lie far out.
  std::vector<Vector3d> points;
  for (int i = 0; i < 98; ++i) points.push_back(centre + Vector3d(3.0 * i / 97.0, 0, 0));
  points.push_back(centre + Vector3d(0, 50, 0));
  points.push_back(centre + Vector3d(0, 0, 80));
  points.push_back(Vector3d(std::nan(""), 0, 0));                   // not counted
  EXPECT_NEAR(far_shell_radius(points, centre, 1.0), 50.0, 1e-12);  // index 98 of 100 sorted
  points.resize(98);
  EXPECT_NEAR(far_shell_radius(points, centre, 1.0), 3.0 * 96 / 97, 1e-12);  // index 96 of 98
  EXPECT_NEAR(far_shell_radius(points, centre, 7.5), 7.5, 1e-12) << "at least every camera";
  EXPECT_EQ(far_shell_radius({}, centre, 7.5), 7.5);

  std::vector<uint8_t> open(1200, 1);
  for (int x = 0; x < 40; ++x) open[5 * 40 + x] = 0;  // row 5 is closed
  std::vector<float> rgb(3600);
  for (size_t i = 0; i < rgb.size(); ++i) rgb[i] = static_cast<float>(i % 251) / 250.f;
  const double radius = 9.0;  // the camera (5.6 from the centre) is inside
  std::vector<Vector3d> shell;
  std::vector<Eigen::Vector3<uint8_t>> colours;
  far_shell_points(cam, open, rgb, centre, radius, 4, shell, colours);
  // Pixels x = 2, 6, ..., 38 and y = 2, 6, ..., 26 (row 5 is not on the grid).
  ASSERT_EQ(shell.size(), 10u * 7u);
  ASSERT_EQ(colours.size(), shell.size());
  size_t i = 0;
  for (int y = 2; y < 30; y += 4)
    for (int x = 2; x < 40; x += 4, ++i) {
      EXPECT_NEAR((shell[i] - centre).norm(), radius, 1e-9);
      const Vector3d c = cam.R * shell[i] + cam.t;
      ASSERT_GT(c.z(), 0) << "in front of the camera";
      EXPECT_NEAR(cam.fx * c.x() / c.z() + cam.cx, x + 0.5, 1e-6);
      EXPECT_NEAR(cam.fy * c.y() / c.z() + cam.cy, y + 0.5, 1e-6);
      const size_t p = static_cast<size_t>(y) * 40 + x;
      for (int k = 0; k < 3; ++k) EXPECT_EQ(colours[i][k], std::lround(255.0 * rgb[3 * p + k]));
    }
  // A closed grid row gives nothing: close row 6, which the grid holds.
  for (int x = 0; x < 40; ++x) open[6 * 40 + x] = 0;
  shell.clear();
  colours.clear();
  far_shell_points(cam, open, rgb, centre, radius, 4, shell, colours);
  EXPECT_EQ(shell.size(), 10u * 6u);
  EXPECT_THROW(far_shell_points(cam, std::vector<uint8_t>(10, 1), rgb, centre, radius, 4, shell, colours),
               std::invalid_argument);
}

// The ridge pulls directions nothing saw towards the start, not to 0.
TEST(Sky, RidgePullsTowardsTheStart) {
  const std::vector<float> start = sky_constant(1, {1.f, 1.f, 1.f});
  const std::vector<float> got = Sky::solve_fit(Eigen::MatrixXd::Zero(4, 4), Eigen::MatrixXd::Zero(4, 3), start, 5.0);
  EXPECT_EQ(got, start);
}

// Training with the sky gives the same model bytes with 1 and 2 PoCL
// threads: the coefficient sums run in a fixed order. (Resume with a sky:
// TrainState.ResumeIsBitExactWithASky.)
TEST(Sky, TrainingBitsDoNotDependOnThreads) {
  test::ScratchDir dir("sky_bits");
  const std::string scene = dir.file("scene");
  test::CliResult r = test::run_cli("synth " + scene + " --no-backdrop --width 48 --height 36 --views 10 --seed 3");
  ASSERT_EQ(r.code, 0) << r.output;
  const char* bin = std::getenv("AG2GS_BINARY");
  const std::string exe = bin ? bin : "./ag2gs";
  auto train = [&](int threads, const std::string& out, const std::string& extra) {
    const std::string cmd = "POCL_MAX_PTHREAD_COUNT=" + std::to_string(threads) + " " + exe + " train " + scene +
                            " -o " + dir.file(out) + " --iters 120 --stages 1 --seed 2 --sky-degree 3 --quiet " +
                            extra + " > " + dir.file(out + ".log") + " 2>&1";
    return std::system(cmd.c_str());
  };
  ASSERT_EQ(train(1, "t1", ""), 0);
  ASSERT_EQ(train(2, "t2", ""), 0);
  const std::string a = test::read_bytes(dir.file("t1/model.ag2gs"));
  ASSERT_FALSE(a.empty());
  ASSERT_TRUE(read_model_archive(dir.file("t1/model.ag2gs")).has("sky/sh"));
  EXPECT_TRUE(a == test::read_bytes(dir.file("t2/model.ag2gs"))) << "1 vs 2 PoCL threads";
}

double test_psnr(const std::string& model_dir) {
  std::ifstream f(model_dir + "/metrics.json");
  return nlohmann::json::parse(f)["final"]["psnr"].get<double>();
}

// Open sky: no SfM point lies on it. With the sky (the default chooses it
// here) the test views reach a PSNR that the fixed black background cannot
// (measured when the rule was set: 26.65 dB against 12.96 dB; with two
// seeded layers and two children, 30.91 dB against 24.68 dB).
TEST(Sky, OpenSkySceneTrainsWithTheSkyAndNotWithout) {
  test::ScratchDir dir("sky_train");
  const std::string scene = dir.file("scene");
  test::CliResult r = test::run_cli("synth " + scene + " --no-backdrop --width 96 --height 72 --views 16 --seed 2");
  ASSERT_EQ(r.code, 0) << r.output;
  const std::string common = " --iters 800 --eval --stages 1 --seed 1 --log-every 800";
  r = test::run_cli("train " + scene + " -o " + dir.file("sky") + common);
  ASSERT_EQ(r.code, 0) << r.output;
  // The default chose the sky from the scene (its open share is above 5%,
  // and a sky fits the open pixels closely): no far shell.
  EXPECT_NE(r.output.find("an open sky"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("sky: SH degree 3 (from the scene"), std::string::npos) << r.output;
  EXPECT_EQ(r.output.find("far shell:"), std::string::npos) << r.output;
  const std::string sky_log = r.output;
  r = test::run_cli("train " + scene + " -o " + dir.file("black") + common + " --sky-degree -1");
  ASSERT_EQ(r.code, 0) << r.output;
  const double with = test_psnr(dir.file("sky")), without = test_psnr(dir.file("black"));
  std::printf("  open sky, 800 iterations: test PSNR %.2f dB with the sky, %.2f dB without\n", with, without);
  EXPECT_GT(with, without + 4.0);
  // The model keeps its sky.
  const ModelArchive a = read_model_archive(dir.file("sky/model.ag2gs"));
  ASSERT_TRUE(sky_from_archive(a).has_value());
  EXPECT_EQ(sky_from_archive(a)->size(), 48u);
  EXPECT_FALSE(sky_from_archive(read_model_archive(dir.file("black/model.ag2gs"))).has_value());

  // render draws rgb over the model's sky unless --bg asks for a fixed one;
  // over the sky the test view is close to its photo, over black it is not.
  r = test::run_cli("render " + dir.file("sky") + " --scene " + scene + " -o " + dir.file("r_sky") +
                    " --views view_000.png");
  ASSERT_EQ(r.code, 0) << r.output;
  EXPECT_NE(r.output.find("learned sky"), std::string::npos) << r.output;
  r = test::run_cli("render " + dir.file("sky") + " --scene " + scene + " -o " + dir.file("r_black") +
                    " --views view_000.png --bg 0,0,0");
  ASSERT_EQ(r.code, 0) << r.output;
  int w = 0, h = 0;
  const std::vector<float> photo = read_rgb(scene + "/images/view_000.png", w, h);
  auto mean_error = [&](const std::string& file) {
    int rw = 0, rh = 0;
    const std::vector<float> img = read_rgb(file, rw, rh);
    EXPECT_EQ(rw, w);
    EXPECT_EQ(rh, h);
    double e = 0;
    for (size_t i = 0; i < img.size() && i < photo.size(); ++i) e += std::abs(img[i] - photo[i]);
    return e / static_cast<double>(photo.size());
  };
  const double err_sky = mean_error(dir.file("r_sky/rgb/view_000.png"));
  const double err_black = mean_error(dir.file("r_black/rgb/view_000.png"));
  std::printf("  render of view_000: mean |error| %.4f over the sky, %.4f over black\n", err_sky, err_black);
  EXPECT_LT(err_sky, 0.06);
  EXPECT_GT(err_black, 2 * err_sky);

  // point_cloud.ply holds the sky baked into Gaussians, so a standard 3DGS
  // renderer of the file draws the model's picture: ours (render --ply) and
  // the double-precision reference, against `render MODEL_DIR` (the
  // Gaussians alone from point_cloud_objects.ply, over the sky).
  EXPECT_NE(sky_log.find("point_cloud_objects.ply holds"), std::string::npos) << "the log says what the .ply holds";
  EXPECT_FALSE(std::filesystem::exists(dir.file("black/point_cloud_objects.ply"))) << "no sky, one .ply";
  const GaussianSet objects = read_ply(dir.file("sky/point_cloud_objects.ply"));
  const GaussianSet full = read_ply(dir.file("sky/point_cloud.ply"));
  EXPECT_EQ(full.size(), objects.size() + static_cast<size_t>(sky_bake_count(3)));
  r = test::run_cli("render --ply " + dir.file("sky/point_cloud.ply") + " --scene " + scene + " -o " +
                    dir.file("r_ply") + " --views test");
  ASSERT_EQ(r.code, 0) << r.output;
  r = test::run_cli("render " + dir.file("sky") + " --scene " + scene + " -o " + dir.file("r_model") + " --views test");
  ASSERT_EQ(r.code, 0) << r.output;
  const ColmapModel cm = read_colmap_model(scene + "/sparse/0");
  for (const Camera& cam : cm.cameras_for_images) {
    const std::string stem = cam.name.substr(0, cam.name.rfind('.'));
    if (!std::filesystem::exists(dir.file("r_model/rgb/" + stem + ".png"))) continue;  // a training view
    int mw = 0, mh = 0, pw = 0, ph = 0;
    const std::vector<float> model_img = read_rgb(dir.file("r_model/rgb/" + stem + ".png"), mw, mh);
    const std::vector<float> ply_img = read_rgb(dir.file("r_ply/rgb/" + stem + ".png"), pw, ph);
    ASSERT_EQ(model_img.size(), ply_img.size());
    const ref::RefImages ref_img = ref::render(full, cam, {});
    double se_ply = 0, se_ref = 0;
    for (size_t i = 0; i < model_img.size(); ++i) {
      se_ply += std::pow(ply_img[i] - model_img[i], 2);
      se_ref += std::pow(std::clamp(ref_img.rgb[i], 0.0, 1.0) - model_img[i], 2);
    }
    const double n = static_cast<double>(model_img.size());
    const double psnr_ply = -10 * std::log10(std::max(se_ply / n, 1e-12));
    const double psnr_ref = -10 * std::log10(std::max(se_ref / n, 1e-12));
    std::printf("  %s: point_cloud.ply against the model's render: %.1f dB (render --ply), %.1f dB (reference)\n",
                stem.c_str(), psnr_ply, psnr_ref);
    EXPECT_GT(psnr_ply, 35.0);
    EXPECT_GT(psnr_ref, 35.0);
  }
}

// A far textured wall without SfM points (the backdrop's wall, its points
// left out): the pixels without points are no sky (a sky fits them badly),
// so the far shell seeds anchors from them, and the wall is reconstructed
// far better than by the sky alone (measured when the rule was set, 160x120
// at 2000 iterations: 32.36 / 31.57 dB with the sky alone, 34.29 / 34.76
// with the shell and the sky, seeds 1 / 2; here 28.10 against 30.39).
TEST(Sky, FarWallWithoutPointsGetsTheFarShellNotAnOpenSky) {
  test::ScratchDir dir("sky_wall");
  const std::string scene = dir.file("scene");
  test::CliResult r = test::run_cli("synth " + scene + " --no-wall-points --width 96 --height 72 --views 16 --seed 2");
  ASSERT_EQ(r.code, 0) << r.output;
  const std::string common = " --iters 800 --eval --stages 1 --seed 1 --log-every 800";
  r = test::run_cli("train " + scene + " -o " + dir.file("shell") + common);
  ASSERT_EQ(r.code, 0) << r.output;
  EXPECT_NE(r.output.find("surfaces without SfM points"), std::string::npos) << r.output;
  EXPECT_EQ(r.output.find("an open sky"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("far shell: "), std::string::npos) << r.output;
  r = test::run_cli("train " + scene + " -o " + dir.file("sky") + common + " --far-shell false");
  ASSERT_EQ(r.code, 0) << r.output;
  EXPECT_EQ(r.output.find("far shell: "), std::string::npos) << r.output;
  const double shell = test_psnr(dir.file("shell")), sky = test_psnr(dir.file("sky"));
  std::printf("  far wall without points, 800 iterations: test PSNR %.2f dB with the far shell, %.2f dB without\n",
              shell, sky);
  EXPECT_GT(shell, sky + 1.0);
}

}  // namespace
}  // namespace ag2gs
