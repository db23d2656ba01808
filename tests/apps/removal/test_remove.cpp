// `ag2gs remove` end to end on a small generated scene and a short stage-1
// model: the output is a complete model folder without the selected anchors,
// every kept anchor keeps its bytes, holes and targets cover every training
// view, an external inpainter's images are used as they are, and bad input is
// refused before anything is written.
#include <gtest/gtest.h>
#include <unistd.h>

#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <map>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <set>
#include <string>

#include "apps/removal/removal.h"
#include "host/io/colmap_reader.h"
#include "host/io/colmap_writer.h"
#include "host/io/image_io.h"
#include "host/io/model_io.h"
#include "tests/cli_test_util.h"
#include "tests/test_util.h"
#include "train/anchors/anchor_model.h"

namespace fs = std::filesystem;
using nlohmann::json;

namespace ag2gs {
namespace {

struct Fixture {
  fs::path root, scene, model;
};

// test::make_small_trained_model, made once per process (the sky's own path
// is SkyIsCopiedAndShownBehind).
const Fixture& fixture() {
  static const Fixture f = [] {
    Fixture x;
    x.root = fs::path(testing::TempDir()) / ("ag2gs_remove_" + std::to_string(::getpid()));
    x.scene = x.root / "scene";
    x.model = x.root / "model";
    test::make_small_trained_model(x.root);
    return x;
  }();
  return f;
}

std::string remove_cmd(const std::string& out, const std::string& extra) {
  const Fixture& f = fixture();
  return "remove " + f.model.string() + " --scene " + f.scene.string() + " -o " + out + " " + extra + " --quiet";
}

fs::path fresh(const std::string& name) {
  const fs::path p = fixture().root / name;
  fs::remove_all(p);
  return p;
}

void write_selection(const fs::path& path, const std::vector<int>& anchors) {
  std::ofstream(path) << json{{"anchors", anchors}}.dump();
}

std::vector<std::string> train_stems() {
  std::vector<std::string> stems;
  for (int i = 1; i < 8; ++i) stems.push_back("view_00" + std::to_string(i));  // view_000 is the test view
  return stems;
}

TEST(Remove, ClickWritesACompleteModelFolderWithoutTheObject) {
  const fs::path out = fresh("by_click");
  // By features, as test_simulate's fixture says why.
  const auto r = test::run_cli(remove_cmd(out.string(), "--view view_001 --click 32,30 --click-by features"));
  ASSERT_EQ(r.code, 0) << r.output;
  for (const char* f : {"model.ag2gs", "point_cloud.ply", "removal.json"}) EXPECT_TRUE(fs::exists(out / f)) << f;
  for (const std::string& s : train_stems()) {
    EXPECT_TRUE(fs::exists(out / "holes" / (s + ".png"))) << s;
    EXPECT_TRUE(fs::exists(out / "targets" / (s + ".png"))) << s;
  }
  EXPECT_FALSE(fs::exists(out / "holes" / "view_000.png")) << "the test view is not a training view";
  json rep = json::parse(std::ifstream(out / "removal.json"));
  const AnchorModel before = AnchorModel::from_archive(read_model_archive((fixture().model / "model.ag2gs").string()));
  const AnchorModel after = AnchorModel::from_archive(read_model_archive((out / "model.ag2gs").string()));
  EXPECT_GT(rep["anchors_removed"].get<size_t>(), 0u);
  EXPECT_EQ(rep["anchors_removed"].get<size_t>() + after.size(), before.size() + rep["anchors_added"].get<size_t>());
  EXPECT_EQ(rep["gaussians_kept"].get<size_t>() + rep["gaussians_added"].get<size_t>(), after.gaussians());
  EXPECT_EQ(rep["gaussians"].get<size_t>(), after.gaussians());
  EXPECT_EQ(rep["iterations"].get<int>(), 0) << "no fine-tune by default";
  EXPECT_EQ(rep["query"]["type"], "click");
  EXPECT_EQ(rep["holes"]["views"].size(), 7u);
  // Other subcommands take the folder.
  const auto info = test::run_cli("info " + out.string());
  EXPECT_EQ(info.code, 0) << info.output;
  const auto render = test::run_cli("render " + out.string() + " --scene " + fixture().scene.string() +
                                    " --views test -o " + (fixture().root / "by_click_renders").string() + " --quiet");
  EXPECT_EQ(render.code, 0) << render.output;
}

TEST(Remove, KeptAnchorsKeepTheirBytesAndHolesStayInTheObject) {
  const fs::path out = fresh("by_selection"), sel = fixture().root / "selection.json";
  const ModelArchive in = read_model_archive((fixture().model / "model.ag2gs").string());
  const AnchorModel before = AnchorModel::from_archive(in);
  std::vector<int> chosen;
  for (int a = 3; a < static_cast<int>(before.size()); a += 7) chosen.push_back(a);
  write_selection(sel, chosen);
  const auto r = test::run_cli(remove_cmd(out.string(), "--selection " + sel.string() + " --dilate 0"));
  ASSERT_EQ(r.code, 0) << r.output;
  const ModelArchive res = read_model_archive((out / "model.ag2gs").string());
  const json report = json::parse(std::ifstream(out / "removal.json"));
  // Gone: the selection and the kept anchors it hid from every photo.
  std::set<int> gone(chosen.begin(), chosen.end());
  for (const auto& h : report["hidden_anchors_removed"]) {
    EXPECT_EQ(gone.count(h.get<int>()), 0u) << "a hidden anchor is one the selection kept";
    gone.insert(h.get<int>());
  }
  const size_t added = report["anchors_added"].get<size_t>();
  std::set<std::pair<int, int>> cleared;
  for (const auto& c : report["stray_children_cleared"]) cleared.insert({c[0].get<int>(), c[1].get<int>()});
  for (const auto& [name, t] : in.arrays()) {
    if (name.rfind("anchors/", 0) != 0) continue;
    ASSERT_TRUE(res.has(name)) << name;
    const Tensor& u = res.tensor(name);
    const size_t row = t.bytes.size() / before.size();
    size_t k = 0;
    for (size_t a = 0; a < before.size(); ++a) {
      if (gone.count(static_cast<int>(a))) continue;
      if (name == "anchors/opacity_logit") {
        // Per child: a cleared stray child is fully transparent, the rest keep their bytes.
        const size_t K = before.children();
        for (size_t c = 0; c < K; ++c) {
          float x, y;
          std::memcpy(&x, &t.bytes[(a * K + c) * 4], 4);
          std::memcpy(&y, &u.bytes[(k * K + c) * 4], 4);
          if (cleared.count({static_cast<int>(k), static_cast<int>(c)}))
            EXPECT_LT(y, -20.f) << "cleared child " << k << "/" << c;
          else
            ASSERT_EQ(0, std::memcmp(&x, &y, 4)) << name << " anchor " << a << " child " << c;
        }
      } else {
        ASSERT_EQ(0, std::memcmp(&t.bytes[a * row], &u.bytes[k * row], row)) << name << " anchor " << a;
      }
      ++k;
    }
    // The fill's anchors follow the kept ones.
    EXPECT_EQ((k + added) * row, u.bytes.size()) << name;
  }
  // The report's hole counts are the masks written to holes/.
  json rep = json::parse(std::ifstream(out / "removal.json"));
  EXPECT_EQ(rep["anchors_removed"].get<size_t>(), gone.size());
  size_t total = 0;
  for (const auto& v : rep["holes"]["views"]) {
    const std::string stem = fs::path(v["view"].get<std::string>()).stem().string();
    const cv::Mat m = cv::imread((out / "holes" / (stem + ".png")).string(), cv::IMREAD_UNCHANGED);
    ASSERT_FALSE(m.empty()) << stem;
    EXPECT_EQ(static_cast<size_t>(cv::countNonZero(m)), v["hole_pixels"].get<size_t>()) << stem;
    total += v["hole_pixels"].get<size_t>();
  }
  EXPECT_EQ(rep["holes"]["pixels"].get<size_t>(), total);
}

// A model with a sky keeps it: the new model holds the same coefficients,
// and the targets (renders after deletion) show the sky where the removed
// anchors leave the rays open, not black.
TEST(Remove, SkyIsCopiedAndShownBehind) {
  const fs::path model = fresh("sky_model"), out = fresh("sky_removed"), sel = fixture().root / "selection_sky.json";
  auto r = test::run_cli("train " + fixture().scene.string() + " -o " + model.string() +
                         " --iters 150 --stages 1 --eval --seed 1 --quiet --sky-degree 3");
  ASSERT_EQ(r.code, 0) << r.output;
  const ModelArchive in = read_model_archive((model / "model.ag2gs").string());
  ASSERT_TRUE(in.has("sky/sh"));
  const AnchorModel before = AnchorModel::from_archive(in);
  std::vector<int> chosen;
  for (int a = 0; a < static_cast<int>(before.size()); a += 2) chosen.push_back(a);
  write_selection(sel, chosen);
  r = test::run_cli("remove " + model.string() + " --scene " + fixture().scene.string() + " -o " + out.string() +
                    " --selection " + sel.string() + " --inpaint none --quiet");
  ASSERT_EQ(r.code, 0) << r.output;
  const ModelArchive res = read_model_archive((out / "model.ag2gs").string());
  ASSERT_TRUE(res.has("sky/sh"));
  EXPECT_EQ(in.tensor("sky/sh").bytes, res.tensor("sky/sh").bytes);
  // Where the hole is, the target (--inpaint none: the render after
  // deletion) is the sky, which is nowhere near black on this scene.
  json rep = json::parse(std::ifstream(out / "removal.json"));
  size_t bright = 0, hole = 0;
  for (const auto& v : rep["holes"]["views"]) {
    const std::string stem = fs::path(v["view"].get<std::string>()).stem().string();
    const cv::Mat m = cv::imread((out / "holes" / (stem + ".png")).string(), cv::IMREAD_UNCHANGED);
    const cv::Mat t = cv::imread((out / "targets" / (stem + ".png")).string(), cv::IMREAD_COLOR);
    ASSERT_FALSE(m.empty() || t.empty()) << stem;
    for (int y = 0; y < m.rows; ++y)
      for (int x = 0; x < m.cols; ++x) {
        if (!m.at<uint8_t>(y, x)) continue;
        ++hole;
        const cv::Vec3b c = t.at<cv::Vec3b>(y, x);
        if (c[0] + c[1] + c[2] > 3 * 40) ++bright;
      }
  }
  ASSERT_GT(hole, 0u);
  EXPECT_GT(bright, hole * 9 / 10) << bright << " of " << hole << " hole pixels brighter than 40";
}

// "-o OUT/" is the folder OUT; the partial folder is built beside it and gone after.
TEST(Remove, TrailingSlashAndNoPartialFolderLeft) {
  const fs::path out = fresh("slash"), sel = fixture().root / "selection_slash.json";
  write_selection(sel, {2, 9});
  // What a kill -9 of an earlier run into the same folder left (issue 42):
  // pid 4194000 is past this machine's processes; the next run removes it.
  const fs::path leftover = fixture().root / "slash.partial.4194000";
  fs::create_directories(leftover / "frames");
  std::ofstream(leftover / "model.ag2gs") << "half";
  const auto r = test::run_cli(remove_cmd(out.string() + "/", "--selection " + sel.string()));
  ASSERT_EQ(r.code, 0) << r.output;
  EXPECT_FALSE(fs::exists(leftover)) << r.output;
  EXPECT_TRUE(fs::exists(out / "model.ag2gs"));
  for (const auto& e : fs::directory_iterator(fixture().root))
    EXPECT_EQ(e.path().filename().string().find(".partial."), std::string::npos) << e.path();
}

// Two training images with one stem in different folders (w1/view_005.png,
// w2/view_005.png: the fixture's view_005 and view_006 moved and renamed,
// their cameras with them) keep their own holes/, targets/ and simulate's
// frames/ files, named w1_view_005 and w2_view_005 as `render` names them
// (issue 42: one stem meant one file for two views).
TEST(Remove, ViewsSharingAStemKeepTheirOwnFiles) {
  const fs::path scene = fresh("stems_scene"), out = fresh("stems_removed"), sim = fresh("stems_simulated");
  fs::create_directories(scene / "images" / "w1");
  fs::create_directories(scene / "images" / "w2");
  ColmapModel m = read_colmap_model((fixture().scene / "sparse" / "0").string());
  for (Camera& c : m.cameras_for_images) {
    std::string name = c.name;
    if (name == "view_005.png") name = "w1/view_005.png";
    if (name == "view_006.png") name = "w2/view_005.png";
    fs::copy_file(fixture().scene / "images" / c.name, scene / "images" / name);
    c.name = name;
  }
  write_colmap_model((scene / "sparse" / "0").string(), m.cameras_for_images, m.points, m.colors);
  const fs::path sel = fixture().root / "selection_stems.json";
  write_selection(sel, {2, 9});
  auto r = test::run_cli("remove " + fixture().model.string() + " --scene " + scene.string() + " -o " + out.string() +
                         " --selection " + sel.string() + " --quiet");
  ASSERT_EQ(r.code, 0) << r.output;
  for (const char* dir : {"holes", "targets"}) {
    EXPECT_TRUE(fs::exists(out / dir / "w1_view_005.png")) << dir;
    EXPECT_TRUE(fs::exists(out / dir / "w2_view_005.png")) << dir;
    EXPECT_EQ(std::distance(fs::directory_iterator(out / dir), fs::directory_iterator()), 7) << dir;
  }
  r = test::run_cli("simulate " + fixture().model.string() + " --scene " + scene.string() + " -o " + sim.string() +
                    " --selection " + sel.string() +
                    " --frames 1 --fps 250 --grid 16 --views w1/view_005.png,w2/view_005.png --quiet");
  ASSERT_EQ(r.code, 0) << r.output;
  EXPECT_TRUE(fs::exists(sim / "frames" / "w1_view_005" / "0001.png"));
  EXPECT_TRUE(fs::exists(sim / "frames" / "w2_view_005" / "0001.png"));
}

TEST(Remove, ExternalInpaintingIsUsedAsItIs) {
  const fs::path out = fresh("external"), dir = fresh("inpainted"), sel = fixture().root / "selection_small.json";
  write_selection(sel, {1, 2, 3, 4, 5});
  fs::create_directories(dir);
  for (const std::string& s : train_stems()) {
    cv::Mat img(48, 64, CV_8UC3);
    for (int y = 0; y < 48; ++y)
      for (int x = 0; x < 64; ++x) img.at<cv::Vec3b>(y, x) = cv::Vec3b(x * 4, y * 5, (x + y + s.back()) % 256);
    cv::imwrite((dir / (s + ".png")).string(), img);
  }
  const auto r =
      test::run_cli(remove_cmd(out.string(), "--selection " + sel.string() + " --inpainted " + dir.string()));
  ASSERT_EQ(r.code, 0) << r.output;
  for (const std::string& s : train_stems()) {
    const cv::Mat a = cv::imread((dir / (s + ".png")).string()),
                  b = cv::imread((out / "targets" / (s + ".png")).string());
    ASSERT_EQ(a.size(), b.size()) << s;
    EXPECT_EQ(cv::norm(a, b, cv::NORM_INF), 0.0) << s;
  }
  // A missing image and a wrong size are named before any work.
  fs::remove(dir / "view_003.png");
  const fs::path out2 = fresh("external2");
  auto bad = test::run_cli(remove_cmd(out2.string(), "--selection " + sel.string() + " --inpainted " + dir.string()));
  EXPECT_NE(bad.code, 0);
  EXPECT_NE(bad.output.find("view_003.png is missing"), std::string::npos) << bad.output;
  cv::imwrite((dir / "view_003.png").string(), cv::Mat(10, 10, CV_8UC3, cv::Scalar(1, 2, 3)));
  bad = test::run_cli(remove_cmd(out2.string(), "--selection " + sel.string() + " --inpainted " + dir.string()));
  EXPECT_NE(bad.code, 0);
  EXPECT_NE(bad.output.find("10x10, expected 64x48"), std::string::npos) << bad.output;
  EXPECT_FALSE(fs::exists(out2));
}

// --no-fill deletes only; the fine-tune (--iters) changes only the fill and
// the kept anchors the report lists as near the holes, and gives the same
// bytes with 1 and 2 PoCL threads.
TEST(Remove, FineTuneTouchesOnlyAnchorsNearTheHoleAndIsDeterministic) {
  const fs::path sel = fixture().root / "selection_tune.json";
  const ModelArchive in = read_model_archive((fixture().model / "model.ag2gs").string());
  const AnchorModel before = AnchorModel::from_archive(in);
  std::vector<int> chosen;
  for (int a = 0; a < static_cast<int>(before.size()); a += 5) chosen.push_back(a);
  write_selection(sel, chosen);
  const fs::path del = fresh("delete_only");
  auto r = test::run_cli(remove_cmd(del.string(), "--selection " + sel.string() + " --no-fill"));
  ASSERT_EQ(r.code, 0) << r.output;
  json rep = json::parse(std::ifstream(del / "removal.json"));
  EXPECT_EQ(rep["anchors_added"].get<size_t>(), 0u);
  EXPECT_EQ(AnchorModel::from_archive(read_model_archive((del / "model.ag2gs").string())).size(),
            before.size() - chosen.size());

  std::string bytes[2];
  for (int threads = 1; threads <= 2; ++threads) {
    const fs::path out = fresh("tuned_" + std::to_string(threads));
    setenv("POCL_MAX_PTHREAD_COUNT", std::to_string(threads).c_str(), 1);
    r = test::run_cli(remove_cmd(out.string(), "--selection " + sel.string() + " --iters 12"));
    unsetenv("POCL_MAX_PTHREAD_COUNT");
    ASSERT_EQ(r.code, 0) << r.output;
    bytes[threads - 1] = test::read_file(out / "model.ag2gs");
  }
  EXPECT_EQ(bytes[0], bytes[1]) << "1 thread vs 2 threads";
  const fs::path out = fixture().root / "tuned_2";
  rep = json::parse(std::ifstream(out / "removal.json"));
  EXPECT_EQ(rep["iterations"].get<int>(), 12);
  std::set<int> tuned, cleared;
  for (const auto& v : rep["fill"]["kept_anchors_tuned_ids"]) tuned.insert(v.get<int>());
  for (const auto& c : rep["stray_children_cleared"]) cleared.insert(c[0].get<int>());
  EXPECT_EQ(tuned.size(), rep["fill"]["kept_anchors_tuned"].get<size_t>());
  ASSERT_GT(tuned.size(), 0u);
  ASSERT_LT(tuned.size(), before.size() - chosen.size()) << "some kept anchors must be far from the holes";
  const AnchorModel after = AnchorModel::from_archive(read_model_archive((out / "model.ag2gs").string()));
  std::set<int> gone(chosen.begin(), chosen.end());
  for (const auto& h : rep["hidden_anchors_removed"]) gone.insert(h.get<int>());
  size_t k = 0, changed = 0, frozen_changed = 0;
  const int K = before.children();
  for (size_t a = 0; a < before.size(); ++a) {
    if (gone.count(static_cast<int>(a))) continue;
    bool same = true;
    for (int c = 0; c < K; ++c) {
      const size_t g = a * K + c, h = k * K + c;
      same = same && before.opacity_logit()[g] == after.opacity_logit()[h];
      for (int i = 0; i < 3; ++i)
        same = same && before.offset()[3 * g + i] == after.offset()[3 * h + i] &&
               before.scale_logit()[3 * g + i] == after.scale_logit()[3 * h + i] &&
               before.sh()[g * kAnchorShCoeffs * 3 + i] == after.sh()[h * kAnchorShCoeffs * 3 + i];
    }
    if (!same) {
      ++changed;
      if (!tuned.count(static_cast<int>(k)) && !cleared.count(static_cast<int>(k))) ++frozen_changed;
    }
    ++k;
  }
  EXPECT_EQ(frozen_changed, 0u) << "a frozen anchor changed";
  EXPECT_GT(changed, 0u) << "the fine-tune changed nothing";
  // The other hole target: the filled model's own render.
  const fs::path own = fresh("tuned_own");
  r = test::run_cli(remove_cmd(own.string(), "--selection " + sel.string() + " --iters 6 --tune-targets fill"));
  ASSERT_EQ(r.code, 0) << r.output;
  EXPECT_EQ(json::parse(std::ifstream(own / "removal.json"))["iterations"].get<int>(), 6);
  EXPECT_NE(test::read_file(own / "model.ag2gs"), bytes[1]);
}

TEST(Remove, BadInputIsRefusedBeforeAnythingIsWritten) {
  const Fixture& f = fixture();
  const AnchorModel m = AnchorModel::from_archive(read_model_archive((f.model / "model.ag2gs").string()));
  const fs::path empty = f.root / "empty_sel.json", all = f.root / "all_sel.json", sel = f.root / "one_sel.json";
  write_selection(empty, {});
  std::vector<int> every(m.size());
  for (size_t a = 0; a < m.size(); ++a) every[a] = static_cast<int>(a);
  write_selection(all, every);
  write_selection(sel, {0});
  const fs::path out = fresh("refused");
  const std::string vocab = (f.scene / "vocab.json").string();
  const std::vector<std::pair<std::string, std::string>> cases = {
      {"--selection " + empty.string(), "selected no anchor"},
      {"--selection " + all.string(), "empty model"},
      {"--selection " + sel.string() + " --no-fill --iters 5", "--no-fill deletes only"},
      {"--selection " + sel.string() + " --fill-opacity 1", "--fill-opacity: must be a number in [0.0001 - 0.9999]"},
      {"--selection " + sel.string() + " --tune-targets lama", "--tune-targets"},
      {"--selection " + sel.string() + " --inpaint lama", "expected telea, ns or none"},
      {"--selection " + sel.string() + " --stray-reach 17", "--stray-reach"},
      {"--selection " + sel.string() + " --hidden-fraction 1.5", "--hidden-fraction"},
      {"--text thing --vocab " + vocab, "no clusters/language features"},
      {"", "give exactly one query"},
      {"--selection " + sel.string() + " --view view_001 --click 3,4", "not both"},
  };
  for (const auto& [extra, message] : cases) {
    const auto r = test::run_cli(remove_cmd(out.string(), extra));
    EXPECT_NE(r.code, 0) << extra;
    EXPECT_NE(r.output.find(message), std::string::npos) << extra << "\n" << r.output;
    EXPECT_FALSE(fs::exists(out)) << extra;
  }
  // Never into the model folder or below it, never over a folder with
  // something in it; the model folder's files keep their bytes.
  std::map<std::string, std::string> model_bytes;
  for (const auto& e : fs::directory_iterator(f.model))
    if (e.is_regular_file()) model_bytes[e.path().filename().string()] = test::read_file(e.path());
  auto r = test::run_cli("remove " + f.model.string() + " --scene " + f.scene.string() + " -o " + f.model.string() +
                         "/ --selection " + sel.string() + " --quiet");
  EXPECT_NE(r.code, 0);
  EXPECT_NE(r.output.find("is the model folder itself"), std::string::npos) << r.output;
  r = test::run_cli("remove " + f.model.string() + " --scene " + f.scene.string() + " -o " +
                    (f.model / "removed").string() + " --selection " + sel.string() + " --quiet");
  EXPECT_NE(r.code, 0);
  EXPECT_NE(r.output.find("lies inside the model folder"), std::string::npos) << r.output;
  r = test::run_cli(remove_cmd(out.string(), "--text \"  \" --vocab " + vocab));
  EXPECT_NE(r.code, 0);
  EXPECT_NE(r.output.find("--text: the phrase is empty"), std::string::npos) << r.output;
  for (const auto& [name, bytes] : model_bytes) EXPECT_EQ(test::read_file(f.model / name), bytes) << name;
  EXPECT_FALSE(fs::exists(f.model / "removed"));
  fs::create_directories(out);
  std::ofstream(out / "keep.txt") << "mine";
  r = test::run_cli(remove_cmd(out.string(), "--selection " + sel.string()));
  EXPECT_NE(r.code, 0);
  EXPECT_NE(r.output.find("not empty"), std::string::npos) << r.output;
  EXPECT_TRUE(fs::exists(out / "keep.txt"));
}

// Hostile files (issue 42's campaign): each used to crash or pass silently.
// A selection nested 100,000 levels deep (a stack overflow in remove and
// simulate), a model whose cluster id is out of range (a heap overrun in
// remove --click, 3 runs in 8) or whose parameters hold a NaN (copied into
// every output), and query -o into the scene (it overwrote the masks).
TEST(Remove, HostileFilesAreRefusedWithoutACrash) {
  const Fixture& f = fixture();
  const fs::path out = fresh("hostile");
  const fs::path deep = f.root / "deep_sel.json";
  {
    std::ofstream o(deep);
    o << "{\"anchors\": " << std::string(100000, '[') << std::string(100000, ']') << "}";
  }
  auto r = test::run_cli(remove_cmd(out.string(), "--selection " + deep.string()));
  EXPECT_EQ(r.code, 1) << r.output;
  EXPECT_NE(r.output.find("nested deeper than 64"), std::string::npos) << r.output;

  // A selection made on another model (its fingerprint differs) is refused;
  // query's own selections carry this model's (test_simulate uses one).
  const fs::path foreign = f.root / "foreign_sel.json";
  std::ofstream(foreign) << json{{"anchors", {1, 2, 3}}, {"anchor_fingerprint", "00000000000000ff"}}.dump();
  r = test::run_cli(remove_cmd(out.string(), "--selection " + foreign.string()));
  EXPECT_EQ(r.code, 1) << r.output;
  EXPECT_NE(r.output.find("made on another model"), std::string::npos) << r.output;
  EXPECT_FALSE(fs::exists(out));

  const ModelArchive good = read_model_archive((f.model / "model.ag2gs").string());
  const size_t anchors = good.get<float>("anchors/pos").size() / 3;
  auto write_model = [&](const std::string& name, const ModelArchive& a) {
    const fs::path dir = f.root / name;
    fs::remove_all(dir);
    fs::create_directories(dir);
    for (const char* file : {"point_cloud.ply", "metrics.json"})
      if (fs::exists(f.model / file)) fs::copy_file(f.model / file, dir / file);
    write_model_archive((dir / "model.ag2gs").string(), a);
    return dir;
  };
  ModelArchive bad_cluster = good;
  std::vector<int32_t> ids(anchors, 0);
  ids[0] = 999;
  bad_cluster.put("clusters/anchor_cluster", ids, {static_cast<int64_t>(anchors)});
  bad_cluster.put("clusters/size", std::vector<int32_t>{static_cast<int32_t>(anchors)}, {1});
  bad_cluster.meta["clusters"] = {{"components", 1}};
  ModelArchive nan_model = good;
  std::vector<float> offsets = good.get<float>("anchors/offset");
  offsets[7] = std::nanf("");
  nan_model.put("anchors/offset", offsets, good.tensor("anchors/offset").shape);
  const std::vector<std::pair<ModelArchive*, std::string>> models = {
      {&bad_cluster, "clusters/anchor_cluster[0] = 999 is outside"},
      {&nan_model, "array 'anchors/offset': element 7 is NaN"}};
  for (const auto& [archive, message] : models) {
    const fs::path dir = write_model("hostile_model", *archive);
    for (const std::string& cmd : {"remove " + dir.string() + " --scene " + f.scene.string() + " -o " + out.string() +
                                       " --view view_001 --click 32,30 --quiet",
                                   "query " + dir.string() + " --scene " + f.scene.string() + " -o " + out.string() +
                                       " --view view_001 --click 32,30 --quiet",
                                   "info " + dir.string()}) {
      r = test::run_cli(cmd);
      EXPECT_EQ(r.code, 1) << cmd << "\n" << r.output;
      EXPECT_NE(r.output.find(message), std::string::npos) << cmd << "\n" << r.output;
      EXPECT_FALSE(fs::exists(out)) << cmd;
    }
  }
  // Training records out of range (issue 42: resolution 0 or -3 and
  // sh_degree 9 were taken as given).
  for (const auto& [key, value] : std::vector<std::pair<std::string, nlohmann::json>>{
           {"resolution", 0}, {"resolution", -3}, {"resolution", "2"}, {"active_sh_degree", 9}}) {
    ModelArchive a = good;
    a.meta["train"][key] = value;
    const fs::path dir = write_model("hostile_meta", a);
    for (const std::string& cmd : {"remove " + dir.string() + " --scene " + f.scene.string() + " -o " + out.string() +
                                       " --view view_001 --click 32,30 --quiet",
                                   "query " + dir.string() + " --scene " + f.scene.string() + " -o " + out.string() +
                                       " --view view_001 --click 32,30 --quiet"}) {
      r = test::run_cli(cmd);
      EXPECT_EQ(r.code, 1) << cmd << "\n" << r.output;
      EXPECT_NE(r.output.find("the file is damaged"), std::string::npos) << key << " " << value << "\n" << r.output;
      EXPECT_FALSE(fs::exists(out)) << cmd;
    }
  }

  // query -o into the scene (or the scene itself) is refused; the scene's
  // files (masks/ among them) keep their bytes.
  std::map<std::string, std::string> scene_files;
  for (const auto& e : fs::recursive_directory_iterator(f.scene))
    if (e.is_regular_file()) scene_files[e.path().string()] = test::read_file(e.path());
  for (const fs::path& o : {f.scene, f.scene / "sel"}) {
    r = test::run_cli("query " + f.model.string() + " --scene " + f.scene.string() + " -o " + o.string() +
                      " --view view_001 --click 32,30 --views all --quiet");
    EXPECT_EQ(r.code, 1) << r.output;
    EXPECT_NE(r.output.find("lies inside the scene folder"), std::string::npos) << r.output;
  }
  EXPECT_FALSE(fs::exists(f.scene / "sel"));
  for (const auto& [path, bytes] : scene_files) EXPECT_EQ(test::read_file(path), bytes) << path;
}

// The library's entry point called directly (apps/removal/removal.h), as the
// viewer or a script would: the same model bytes and the same holes and
// targets as `ag2gs remove` with the same selection and settings, its
// views reported in order, a stop request that stops it, and requests it
// must refuse.
TEST(Remove, TheLibraryCallGivesWhatTheProgramWrites) {
  const fs::path out = fresh("library_vs_program"), sel = fixture().root / "selection_library.json";
  const ModelArchive in = read_model_archive((fixture().model / "model.ag2gs").string());
  const AnchorModel model = AnchorModel::from_archive(in);
  std::vector<int> chosen;
  std::vector<uint8_t> selected(model.size(), 0);
  for (int a = 5; a < static_cast<int>(model.size()); a += 6) {
    chosen.push_back(a);
    selected[a] = 1;
  }
  write_selection(sel, chosen);
  const auto r = test::run_cli(remove_cmd(out.string(), "--selection " + sel.string() + " --iters 12 --seed 7"));
  ASSERT_EQ(r.code, 0) << r.output;

  SceneOptions so;
  so.resolution = 1;
  so.eval = true;
  std::unique_ptr<Scene> scene = Scene::open(fixture().scene.string(), so);
  RemovalRequest req;
  req.object.model_file = (fixture().model / "model.ag2gs").string();
  req.object.archive = &in;
  req.object.model = &model;
  req.object.sh_degree = in.meta["train"].value("sh_degree", 3);
  req.object.scene = scene.get();
  req.object.selected = selected;
  req.settings.iters = 12;
  req.settings.seed = 7;
  std::vector<size_t> seen;
  req.on_view = [&](size_t i, const ViewHole& h, const std::vector<float>& target) {
    seen.push_back(i);
    const std::string stem = train_stems().at(i);
    int w = 0, hh = 0;
    const std::vector<float> written = read_rgb((out / "targets" / (stem + ".png")).string(), w, hh);
    ASSERT_EQ(written.size(), target.size());
    for (size_t k = 0; k < target.size(); ++k)  // the PNG holds the target to 1/255
      ASSERT_NEAR(written[k], target[k], 0.5 / 255 + 1e-6) << stem;
    const cv::Mat hole = cv::imread((out / "holes" / (stem + ".png")).string(), cv::IMREAD_GRAYSCALE);
    ASSERT_EQ(static_cast<size_t>(cv::countNonZero(hole)), h.hole_pixels) << stem;
  };
  Runtime& rt = test::runtime();
  const RemovalResult res = remove_object(rt, req);
  EXPECT_EQ(seen, std::vector<size_t>({0, 1, 2, 3, 4, 5, 6}));
  const fs::path mine = fixture().root / "library_model.ag2gs";
  write_model_archive(mine.string(), res.archive);
  EXPECT_EQ(test::read_file(mine), test::read_file(out / "model.ag2gs"))
      << "the library's model differs from the program's";
  const json report = json::parse(std::ifstream(out / "removal.json"));
  for (const char* key : {"anchors_removed", "anchors_kept", "anchors_added", "hidden_anchors_removed",
                          "stray_children_cleared", "fill", "holes", "iterations"})
    EXPECT_EQ(res.report.at(key), report.at(key)) << key;
  EXPECT_EQ(res.model.size(), res.kept_anchors + res.added_anchors);
  EXPECT_GT(res.report["iterations"].get<int>(), 0);

  // A stop request during the hole search ends the call at that view.
  RemovalRequest stopped = req;
  stopped.on_view = nullptr;
  int calls = 0;
  stopped.check_stop = [&](const std::string& during) {
    if (++calls == 3) throw std::runtime_error("stopped during " + during);
  };
  EXPECT_THROW(remove_object(rt, stopped), std::runtime_error);
  EXPECT_EQ(calls, 3);

  // Refused: a selection of another size, every anchor, a fine-tune without a fill.
  RemovalRequest bad = req;
  bad.on_view = nullptr;
  bad.object.selected.pop_back();
  EXPECT_THROW(remove_object(rt, bad), std::invalid_argument);
  bad.object.selected.assign(model.size(), 1);
  EXPECT_THROW(remove_object(rt, bad), std::runtime_error);
  bad.object.selected = selected;
  bad.settings.fill_holes = false;
  try {
    remove_object(rt, bad);
    ADD_FAILURE() << "a fine-tune without a fill was accepted";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("--no-fill"), std::string::npos) << e.what();
  }
}

}  // namespace
}  // namespace ag2gs
