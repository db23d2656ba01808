// Scene directories: COLMAP + images (lazy, cached under a bound, -r with
// images_N/), the --eval split, SAM masks from language_features/ or masks/,
// containment removal, robust bounds, and the clear errors for bad input.
#include <gtest/gtest.h>
#include <sys/wait.h>
#include <unistd.h>

#include <Eigen/Geometry>
#include <cmath>
#include <filesystem>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "host/io/colmap_writer.h"
#include "host/io/image_io.h"
#include "host/io/npy_io.h"
#include "host/scene/scene.h"
#include "tests/io_test_util.h"
#include "tests/test_util.h"

namespace fs = std::filesystem;
using namespace ag2gs;
using ag2gs::test::expect_error_with;
using ag2gs::test::ScratchDir;
using ag2gs::test::write_bytes;

namespace {

struct FixtureOptions {
  int views = 10;
  int width = 40;
  int height = 30;
  bool images_2 = false;
  bool language_features = false;
  bool masks_png = false;
  int mask_w = 0, mask_h = 0;  // 0 = image size
};

// The colour of pixel (x, y) of view v: distinct per view and position.
cv::Vec3b pixel_bgr(int v, int x, int y) {
  return cv::Vec3b(static_cast<uint8_t>((x * 5 + v) % 256), static_cast<uint8_t>((y * 7 + 3 * v) % 256),
                   static_cast<uint8_t>((x + y + 11 * v) % 256));
}

// The level-`l` mask id of pixel (x, y) in mask coordinates, before offsets:
// level 3 splits the image into left/right halves; level 2 into quarters.
int mask_local(int level, int x, int y, int w, int h) {
  if (level == 3) return x < w / 2 ? 0 : 1;
  if (level == 2) return (x < w / 2 ? 0 : 1) + (y < h / 2 ? 0 : 2);
  return -1;
}

std::vector<Camera> fixture_cameras(const FixtureOptions& o) {
  std::vector<Camera> cams;
  for (int v = 0; v < o.views; ++v) {
    const double a = 2 * M_PI * v / o.views;
    const Eigen::Vector3d eye(4 * std::cos(a), 4 * std::sin(a), 1.0);
    Camera c = test::look_at(eye, Eigen::Vector3d::Zero(), o.width, o.height, 0.8 * o.width);
    char name[32];
    std::snprintf(name, sizeof name, "img_%02d.png", v);
    c.name = name;
    cams.push_back(c);
  }
  return cams;
}

void make_scene(const fs::path& dir, const FixtureOptions& o) {
  const std::vector<Camera> cams = fixture_cameras(o);
  std::vector<Eigen::Vector3d> points;
  std::vector<Eigen::Vector3<uint8_t>> colors;
  for (int i = 0; i < 200; ++i) {
    points.emplace_back(std::sin(i * 1.3), std::cos(i * 0.7), 0.01 * (i % 50));
    colors.emplace_back(10, 20, 30);
  }
  points.emplace_back(1e4, -1e4, 5e3);  // one wild outlier
  colors.emplace_back(0, 0, 0);
  write_colmap_model((dir / "sparse" / "0").string(), cams, points, colors, true);
  fs::create_directories(dir / "images");
  for (int v = 0; v < o.views; ++v) {
    cv::Mat img(o.height, o.width, CV_8UC3);
    for (int y = 0; y < o.height; ++y)
      for (int x = 0; x < o.width; ++x) img.at<cv::Vec3b>(y, x) = pixel_bgr(v, x, y);
    cv::imwrite((dir / "images" / cams[v].name).string(), img);
    if (o.images_2) {
      fs::create_directories(dir / "images_2");
      cv::Mat small;
      cv::resize(img, small, cv::Size(o.width / 2, o.height / 2), 0, 0, cv::INTER_NEAREST);
      cv::imwrite((dir / "images_2" / cams[v].name).string(), small);
    }
    const int mw = o.mask_w ? o.mask_w : o.width, mh = o.mask_h ? o.mask_h : o.height;
    const std::string stem = fs::path(cams[v].name).stem().string();
    if (o.language_features) {
      // Level 0/1: no masks; level 2: 4 quarters (ids 0..3); level 3: 2 halves (ids 4..5).
      std::vector<float> s(static_cast<size_t>(4) * mh * mw, -1.f);
      for (int y = 0; y < mh; ++y) {
        for (int x = 0; x < mw; ++x) {
          s[(static_cast<size_t>(2) * mh + y) * mw + x] = static_cast<float>(mask_local(2, x, y, mw, mh));
          s[(static_cast<size_t>(3) * mh + y) * mw + x] = 4.f + static_cast<float>(mask_local(3, x, y, mw, mh));
        }
      }
      std::vector<float> f(6 * 8);
      for (int r = 0; r < 6; ++r)
        for (int d = 0; d < 8; ++d) f[r * 8 + d] = static_cast<float>(r * 10 + d);
      fs::create_directories(dir / "language_features");
      write_npy((dir / "language_features" / (stem + "_s.npy")).string(), s, {4, mh, mw});
      write_npy((dir / "language_features" / (stem + "_f.npy")).string(), f, {6, 8});
    }
    if (o.masks_png) {
      cv::Mat ids(mh, mw, CV_16U);
      for (int y = 0; y < mh; ++y)
        for (int x = 0; x < mw; ++x) ids.at<uint16_t>(y, x) = x < 3 ? 0 : static_cast<uint16_t>(1000 + (y * 3) / mh);
      fs::create_directories(dir / "masks");
      cv::imwrite((dir / "masks" / (stem + ".png")).string(), ids);
    }
  }
}

}  // namespace

TEST(Scene, OpensViewsInNameOrderWithImagesAtCameraSize) {
  ScratchDir dir("scene");
  make_scene(dir.path(), {});
  auto scene = Scene::open(dir.str());
  ASSERT_EQ(scene->views().size(), 10u);
  for (int v = 0; v < 10; ++v) {
    const SceneView& view = scene->views()[v];
    EXPECT_EQ(view.index, v);
    EXPECT_EQ(view.stem, "img_" + std::string(v < 10 ? "0" : "") + std::to_string(v));
    auto img = scene->image(v);
    ASSERT_EQ(img->width, 40);
    ASSERT_EQ(img->height, 30);
    // Pixel (x=7, y=5) as written, converted BGR -> RGB in [0,1].
    const cv::Vec3b bgr = pixel_bgr(v, 7, 5);
    const float* px = &img->rgb[(5 * 40 + 7) * 3];
    EXPECT_FLOAT_EQ(px[0], bgr[2] / 255.f);
    EXPECT_FLOAT_EQ(px[1], bgr[1] / 255.f);
    EXPECT_FLOAT_EQ(px[2], bgr[0] / 255.f);
  }
  EXPECT_EQ(scene->semantics(), SemanticsKind::none);
  EXPECT_EQ(scene->train_views().size(), 10u);
  EXPECT_TRUE(scene->test_views().empty());
  EXPECT_EQ(scene->find_view("img_03"), 3);
  EXPECT_EQ(scene->find_view("img_03.png"), 3);
  expect_error_with<std::invalid_argument>([&] { scene->find_view("nope"); }, {"unknown view 'nope'", "img_00.png"});
}

TEST(Scene, EvalHoldsOutEvery8thImageLike3DGS) {
  ScratchDir dir("scene");
  FixtureOptions o;
  o.views = 17;
  make_scene(dir.path(), o);
  SceneOptions so;
  so.eval = true;
  auto scene = Scene::open(dir.str(), so);
  EXPECT_EQ(scene->test_views(), (std::vector<int>{0, 8, 16}));
  EXPECT_EQ(scene->train_views().size(), 14u);
}

TEST(Scene, NamedTestImagesReplaceTheEvery8thSplit) {
  ScratchDir dir("scene");
  FixtureOptions o;
  o.views = 10;
  make_scene(dir.path(), o);
  SceneOptions so;
  so.test_images = {"img_03.png", "img_07"};  // a name and a stem
  auto scene = Scene::open(dir.str(), so);
  EXPECT_EQ(scene->test_views(), (std::vector<int>{3, 7}));
  EXPECT_EQ(scene->train_views().size(), 8u);
  so.test_images = {"img_03.png", "img_99.png"};
  expect_error_with<std::runtime_error>([&] { Scene::open(dir.str(), so); },
                                        {"sparse", "held-out image 'img_99.png'", "img_00.png"});
}

TEST(Scene, ResolutionUsesImagesNWhenPresentElseDownscales) {
  for (bool with_images_2 : {false, true}) {
    ScratchDir dir("scene");
    FixtureOptions o;
    o.images_2 = with_images_2;
    make_scene(dir.path(), o);
    SceneOptions so;
    so.resolution = 2;
    auto scene = Scene::open(dir.str(), so);
    const SceneView& v = scene->views()[0];
    EXPECT_EQ(v.camera.width, 20);
    EXPECT_EQ(v.camera.height, 15);
    EXPECT_DOUBLE_EQ(v.camera.fx, v.full_camera.fx / 2);
    EXPECT_EQ(v.downscale, !with_images_2);
    EXPECT_NE(v.image_path.find(with_images_2 ? "images_2" : "images/"), std::string::npos);
    auto img = scene->image(0);
    EXPECT_EQ(img->width, 20);
    EXPECT_EQ(img->height, 15);
  }
}

TEST(Scene, CacheStaysWithinItsByteBound) {
  ScratchDir dir("scene");
  make_scene(dir.path(), {});
  SceneOptions so;
  const size_t one = 40 * 30 * 3 * sizeof(float);
  so.cache_bytes = 3 * one + one / 2;  // room for three images
  auto scene = Scene::open(dir.str(), so);
  for (int pass = 0; pass < 2; ++pass) {
    for (int v = 0; v < 10; ++v) scene->image(v);
  }
  const auto& st = scene->cache_stats();
  EXPECT_LE(st.peak_bytes, so.cache_bytes);
  EXPECT_EQ(st.misses, 20u);  // LRU over 10 views with room for 3: every access misses
  EXPECT_EQ(st.evictions, 17u);
  scene->image(9);  // most recent: a hit
  EXPECT_EQ(scene->cache_stats().hits, 1u);
  // An image held by the caller stays valid after eviction.
  auto held = scene->image(0);
  for (int v = 1; v < 10; ++v) scene->image(v);
  EXPECT_EQ(held->rgb.size(), 40u * 30u * 3u);
}

TEST(Scene, LanguageFeaturesLevel3RescaledNearestWithTheirClipRows) {
  ScratchDir dir("scene");
  FixtureOptions o;
  o.language_features = true;
  o.mask_w = 20;  // half size: rescaled to the image
  o.mask_h = 15;
  make_scene(dir.path(), o);
  auto scene = Scene::open(dir.str());
  ASSERT_EQ(scene->semantics(), SemanticsKind::language_features);
  auto m = scene->masks(2);
  ASSERT_TRUE(m);
  EXPECT_EQ(m->width, 40);
  EXPECT_EQ(m->height, 30);
  EXPECT_EQ(m->layers, 1);
  ASSERT_EQ(m->count, 2);
  EXPECT_EQ(m->feature_dim, 8);
  EXPECT_EQ(scene->feature_dim(), 8);
  // Left half -> global id 4 (first mask), right half -> id 5.
  EXPECT_EQ(m->labels[10 * 40 + 3], 0);
  EXPECT_EQ(m->labels[10 * 40 + 39], 1);
  EXPECT_EQ(m->pixels[0], 20 * 30);
  EXPECT_EQ(m->pixels[1], 20 * 30);
  EXPECT_FLOAT_EQ(m->features[0], 40.f);      // row 4
  EXPECT_FLOAT_EQ(m->features[8 + 7], 57.f);  // row 5, element 7
}

TEST(Scene, MasksContainedInAMaskOfAnotherLevelAreDropped) {
  ScratchDir dir("scene");
  FixtureOptions o;
  o.language_features = true;
  make_scene(dir.path(), o);
  SceneOptions so;
  so.sam_levels = {2, 3};
  auto scene = Scene::open(dir.str(), so);
  auto m = scene->masks(0);
  ASSERT_TRUE(m);
  // The four quarters of level 2 lie inside the halves of level 3.
  EXPECT_EQ(m->layers, 2);
  EXPECT_EQ(m->dropped_contained, 4);
  EXPECT_EQ(m->count, 2);
  EXPECT_FLOAT_EQ(m->features[0], 40.f);
  for (size_t p = 0; p < 40 * 30; ++p) EXPECT_EQ(m->labels[p], -1);  // level 2 map is empty now
}

TEST(Scene, DropContainedMasksKeepsTheFirstOfEqualMasksAndRenumbers) {
  ViewMasks m;
  m.width = 4;
  m.height = 1;
  m.layers = 2;
  m.count = 5;
  m.feature_dim = 1;
  m.features = {0, 1, 2, 3, 4};
  // layer 0: A A B B ; layer 1: C C D .   (mask 4 has no pixel)
  m.labels = {0, 0, 1, 1, 2, 2, 3, -1};
  drop_contained_masks(&m);
  // C equals A: A (lower index) stays, C goes. D lies inside B: D goes. 4 is empty.
  EXPECT_EQ(m.count, 2);
  EXPECT_EQ(m.dropped_contained, 2);
  EXPECT_EQ(m.dropped_empty, 1);
  EXPECT_EQ(m.features, (std::vector<float>{0, 1}));
  EXPECT_EQ(m.labels, (std::vector<int32_t>{0, 0, 1, 1, -1, -1, -1, -1}));
  EXPECT_EQ(m.pixels, (std::vector<int64_t>{2, 2}));
}

TEST(Scene, MaskPngsGiveInstanceIdsWithoutFeatures) {
  ScratchDir dir("scene");
  FixtureOptions o;
  o.masks_png = true;
  make_scene(dir.path(), o);
  auto scene = Scene::open(dir.str());
  ASSERT_EQ(scene->semantics(), SemanticsKind::mask_png);
  auto m = scene->masks(0);
  ASSERT_TRUE(m);
  EXPECT_EQ(m->count, 3);
  EXPECT_EQ(m->feature_dim, 0);
  EXPECT_EQ(m->labels[0], -1);
  EXPECT_EQ(m->labels[5], 0);
  EXPECT_EQ(m->labels[29 * 40 + 5], 2);
}

TEST(Scene, RobustBoundsIgnoreOutliers) {
  ScratchDir dir("scene");
  make_scene(dir.path(), {});
  auto scene = Scene::open(dir.str());
  const SceneBounds& b = scene->bounds();
  EXPECT_EQ(b.points_total, 201);
  EXPECT_LT(b.longest_extent(), 3.0);
  EXPECT_GT(b.longest_extent(), 1.5);
  EXPECT_NEAR(b.camera_radius, 1.1 * 4.0, 1e-9);
}

TEST(SceneErrors, MissingFoldersAndImagesNameTheFileAndTheFix) {
  ScratchDir dir("scene");
  expect_error_with<std::runtime_error>([&] { Scene::open(dir.file("none")); }, {"none", "ag2gs sfm"});
  expect_error_with<std::runtime_error>([&] { Scene::open(dir.str()); }, {"sparse/0", "ag2gs sfm"});
  make_scene(dir.path(), {});
  fs::remove(dir.path() / "images" / "img_04.png");
  fs::remove(dir.path() / "images" / "img_07.png");
  expect_error_with<std::runtime_error>([&] { Scene::open(dir.str()); },
                                        {"images", "2 of 10", "img_04.png", "img_07.png"});
  fs::remove_all(dir.path() / "images");
  expect_error_with<std::runtime_error>([&] { Scene::open(dir.str()); }, {"images", "no image folder"});
}

// One rule for every subcommand: sparse/0/, else sparse/ itself when it holds
// the model; an explicit folder wins; the error names the folder and --sparse.
TEST(Scene, FindsTheModelInSparse0ElseInSparseAndAnExplicitFolderWins) {
  ScratchDir dir("scene");
  make_scene(dir.path(), {});
  EXPECT_EQ(find_colmap_model(dir.str()), dir.file("sparse/0"));
  // A model written without the 0/ level.
  for (const auto& e : fs::directory_iterator(dir.path() / "sparse" / "0"))
    fs::rename(e.path(), dir.path() / "sparse" / e.path().filename());
  fs::remove(dir.path() / "sparse" / "0");
  EXPECT_EQ(find_colmap_model(dir.str()), dir.file("sparse"));
  EXPECT_EQ(Scene::open(dir.str())->views().size(), 10u);
  // Elsewhere in the scene: only an explicit folder finds it.
  fs::rename(dir.path() / "sparse", dir.path() / "colmap");
  expect_error_with<std::runtime_error>([&] { find_colmap_model(dir.str()); },
                                        {dir.file("sparse"), "sparse/0/", "--sparse", "ag2gs sfm"});
  EXPECT_EQ(find_colmap_model(dir.str(), "colmap"), dir.file("colmap"));
  SceneOptions so;
  so.sparse = "colmap";
  EXPECT_EQ(Scene::open(dir.str(), so)->views().size(), 10u);
  expect_error_with<std::runtime_error>([&] { find_colmap_model(dir.str(), "sparse/1"); },
                                        {dir.file("sparse/1"), "no such folder", "--sparse"});
  // sparse/0/ wins over a model in sparse/.
  fs::create_directories(dir.path() / "sparse");
  fs::rename(dir.path() / "colmap", dir.path() / "sparse" / "0");
  fs::copy_file(dir.path() / "sparse" / "0" / "cameras.bin", dir.path() / "sparse" / "cameras.bin");
  EXPECT_EQ(find_colmap_model(dir.str()), dir.file("sparse/0"));
}

// A model without its photos: the missing folder is the first thing to fix,
// even when the cameras also need undistorting (which needs the photos).
TEST(SceneErrors, AMissingImageFolderIsNamedBeforeADistortedCameraModel) {
  ScratchDir dir("scene");
  make_scene(dir.path(), {});
  fs::remove(dir.path() / "sparse" / "0" / "cameras.bin");
  std::string cams = "# camera list\n";
  for (int i = 1; i <= 10; ++i) cams += std::to_string(i) + " OPENCV 40 30 32 32 20 15 0.01 0 0 0\n";
  write_bytes(dir.file("sparse/0/cameras.txt"), cams);
  fs::remove_all(dir.path() / "images");
  expect_error_with<std::runtime_error>([&] { Scene::open(dir.str()); }, {dir.file("images"), "no image folder",
                                                                          "in images/", "OPENCV", "ag2gs undistort"});
}

// A photo cut short (a failed copy) decodes with grey rows: it is refused,
// named as truncated, before training sees it.
TEST(SceneErrors, TruncatedJpegsAreNamedAsSuch) {
  cv::Mat img(30, 40, CV_8UC3);
  cv::randu(img, cv::Scalar::all(0), cv::Scalar::all(255));
  std::vector<unsigned char> jpg;
  ASSERT_TRUE(cv::imencode(".jpg", img, jpg));
  EXPECT_FALSE(jpeg_is_truncated(jpg));
  std::vector<unsigned char> cut(jpg.begin(), jpg.begin() + static_cast<std::ptrdiff_t>(jpg.size() * 6 / 10));
  EXPECT_TRUE(jpeg_is_truncated(cut));
  EXPECT_TRUE(jpeg_is_truncated(std::vector<unsigned char>(jpg.begin(), jpg.begin() + 30)));  // inside the headers
  std::vector<unsigned char> trailer = jpg;
  for (int i = 0; i < 100; ++i) trailer.push_back(static_cast<unsigned char>(i));  // a motion photo's video
  EXPECT_FALSE(jpeg_is_truncated(trailer));
  std::vector<unsigned char> png;
  ASSERT_TRUE(cv::imencode(".png", img, png));
  EXPECT_FALSE(jpeg_is_truncated(png));
  ASSERT_FALSE(cv::imdecode(cut, cv::IMREAD_COLOR).empty()) << "the decoder accepts the cut file: the check is needed";

  ScratchDir dir("scene");
  make_scene(dir.path(), {});
  write_bytes(dir.file("images/img_04.png"), std::string(cut.begin(), cut.end()));
  auto scene = Scene::open(dir.str());
  expect_error_with<std::runtime_error>([&] { scene->image(4); }, {"img_04.png", "truncated JPEG"});
  write_bytes(dir.file("images/img_04.png"), std::string(jpg.begin(), jpg.end()));
  auto again = Scene::open(dir.str());
  EXPECT_EQ(again->image(4)->width, 40);
}

// A photo the user may not read is named as such (with the system's reason),
// not called corrupt. Root reads any file, so as root the read runs in a
// child process that has given up its privileges.
TEST(SceneErrors, UnreadableImagesAreNamedWithTheReason) {
  ScratchDir dir("scene");
  make_scene(dir.path(), {});
  namespace fs = std::filesystem;
  fs::permissions(dir.path(), fs::perms::all, fs::perm_options::add);  // traversable by anyone
  fs::permissions(dir.path() / "images", fs::perms::all, fs::perm_options::add);
  fs::permissions(dir.file("images/img_04.png"), fs::perms::none);
  auto scene = Scene::open(dir.str());
  auto message_of_failed_read = [&]() -> std::string {
    try {
      scene->image(4);
    } catch (const std::runtime_error& e) {
      return e.what();
    }
    return "(no error)";
  };
  if (::geteuid() != 0) {
    const std::string m = message_of_failed_read();
    for (const char* part : {"img_04.png", "cannot be read", "Permission denied", "permissions"})
      EXPECT_NE(m.find(part), std::string::npos) << m;
    return;
  }
  int fds[2];
  ASSERT_EQ(::pipe(fds), 0);
  const pid_t child = ::fork();
  ASSERT_GE(child, 0);
  if (child == 0) {
    ::close(fds[0]);
    std::string m = "could not drop privileges";
    if (::setgid(65534) == 0 && ::setuid(65534) == 0) m = message_of_failed_read();
    const ssize_t written = ::write(fds[1], m.data(), m.size());
    ::_exit(written == static_cast<ssize_t>(m.size()) ? 0 : 1);
  }
  ::close(fds[1]);
  std::string m;
  char buf[512];
  for (ssize_t n; (n = ::read(fds[0], buf, sizeof buf)) > 0;) m.append(buf, static_cast<size_t>(n));
  ::close(fds[0]);
  int status = 0;
  ASSERT_EQ(::waitpid(child, &status, 0), child);
  ASSERT_TRUE(WIFEXITED(status) && WEXITSTATUS(status) == 0) << m;
  for (const char* part : {"img_04.png", "cannot be read", "Permission denied", "permissions"})
    EXPECT_NE(m.find(part), std::string::npos) << m;
  fs::permissions(dir.file("images/img_04.png"), fs::perms::owner_all);
  EXPECT_EQ(scene->image(4)->width, 40);
}

TEST(SceneErrors, CorruptOrWrongSizedImages) {
  ScratchDir dir("scene");
  make_scene(dir.path(), {});
  write_bytes(dir.file("images/img_01.png"), "\x89PNG\r\n\x1a\nthis is not really a png");
  cv::imwrite(dir.file("images/img_02.png"), cv::Mat(30, 41, CV_8UC3, cv::Scalar(1, 2, 3)));
  cv::imwrite(dir.file("images/img_03.png"), cv::Mat(15, 20, CV_8UC3, cv::Scalar(1, 2, 3)));
  auto scene = Scene::open(dir.str());
  expect_error_with<std::runtime_error>([&] { scene->image(1); }, {"img_01.png", "cannot be decoded"});
  expect_error_with<std::runtime_error>([&] { scene->image(2); }, {"img_02.png", "41x30", "expects 40x30"});
  expect_error_with<std::runtime_error>([&] { scene->image(3); }, {"img_03.png", "downscaled", "images_N"});
  expect_error_with<std::runtime_error>([&] { scene->check_all(); }, {"img_01.png"});
}

TEST(SceneErrors, BadLanguageFeatures) {
  ScratchDir dir("scene");
  FixtureOptions o;
  o.language_features = true;
  o.views = 3;
  make_scene(dir.path(), o);
  const std::string lf = dir.file("language_features/");
  // NaN in a feature row.
  std::vector<float> f(6 * 8, 0.5f);
  f[3 * 8 + 2] = std::nanf("");
  write_npy(lf + "img_00_f.npy", f, {6, 8});
  // Too few rows for the ids.
  write_npy(lf + "img_01_f.npy", std::vector<float>(5 * 8, 0.5f), {5, 8});
  // Another feature dimension than view 0... and a truncated file.
  write_npy(lf + "img_02_f.npy", std::vector<float>(6 * 4, 0.5f), {6, 4});
  auto scene = Scene::open(dir.str());
  expect_error_with<std::runtime_error>([&] { scene->masks(0); }, {"img_00_f.npy", "row 3", "non-finite"});
  expect_error_with<std::runtime_error>([&] { scene->masks(1); }, {"img_01_s.npy", "mask id 5", "img_01_f.npy"});
  SceneOptions bad_level;
  bad_level.sam_levels = {5};
  EXPECT_THROW(Scene::open(dir.str(), bad_level), std::invalid_argument);
  // A missing partner file is found at open.
  fs::remove(dir.path() / "language_features" / "img_02_f.npy");
  expect_error_with<std::runtime_error>([&] { Scene::open(dir.str()); }, {"img_02_f.npy", "missing"});
  // Truncated mask ids.
  write_npy(lf + "img_02_f.npy", std::vector<float>(6 * 8, 0.5f), {6, 8});
  const std::string s = ag2gs::test::read_bytes(lf + "img_02_s.npy");
  write_bytes(lf + "img_02_s.npy", s.substr(0, s.size() / 2));
  auto again = Scene::open(dir.str());
  expect_error_with<std::runtime_error>([&] { again->masks(2); }, {"img_02_s.npy"});
}

TEST(SceneErrors, DistortedCamerasSayHowToUndistort) {
  ScratchDir dir("scene");
  make_scene(dir.path(), {});
  fs::remove(dir.path() / "sparse" / "0" / "cameras.bin");
  std::string cams = "# camera list\n";
  for (int i = 1; i <= 10; ++i) cams += std::to_string(i) + " SIMPLE_RADIAL 40 30 32 20 15 0.01\n";
  write_bytes(dir.file("sparse/0/cameras.txt"), cams);
  expect_error_with<std::runtime_error>([&] { Scene::open(dir.str()); }, {"SIMPLE_RADIAL", "ag2gs undistort"});
}

// Non-finite SfM points are left out at load with a count (a note info
// prints), not dropped silently; huge finite ones stay (the robust bounds
// ignore them).
TEST(SceneErrors, NonFinitePointsAreLeftOutAndCounted) {
  ScratchDir dir("scene");
  FixtureOptions o;
  make_scene(dir.path(), o);
  std::vector<Eigen::Vector3d> pts;
  std::vector<Eigen::Vector3<uint8_t>> cols;
  for (int i = 0; i < 20; ++i) {
    pts.emplace_back(0.1 * i, 0.05 * i, 0.0);
    cols.emplace_back(static_cast<uint8_t>(i), 0, 0);
  }
  pts[3].x() = std::nan("");
  pts[7].z() = INFINITY;
  pts[11].y() = 1e30;
  write_colmap_model(dir.file("sparse/0"), fixture_cameras(o), pts, cols, true);
  auto scene = Scene::open(dir.str());
  ASSERT_EQ(scene->points().size(), 18u);
  ASSERT_EQ(scene->colors().size(), 18u);
  EXPECT_EQ(scene->colors()[3].x(), 4) << "colours must follow their points";
  bool noted = false;
  for (const std::string& n : scene->notes())
    noted = noted || (n.find("left out 2 of 20 points with non-finite coordinates") != std::string::npos &&
                      n.find("points3D.bin") != std::string::npos);
  EXPECT_TRUE(noted) << "no note naming the file and the count";
}

TEST(SceneErrors, EmptyPointCloudIsReportedByRequirePoints) {
  ScratchDir dir("scene");
  FixtureOptions o;
  make_scene(dir.path(), o);
  write_colmap_model(dir.file("sparse/0"), fixture_cameras(o), {}, {}, true);
  auto scene = Scene::open(dir.str());
  EXPECT_TRUE(scene->points().empty());
  expect_error_with<std::runtime_error>([&] { scene->require_points(); }, {"points3D.bin", "no 3D points"});
}
