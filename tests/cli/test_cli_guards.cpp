// Nothing a user had is lost by a mistyped command: outputs that would
// replace a model, a scene or an input are refused (and the files keep their
// bytes), seeds and ranges are checked with readable bounds, and the
// temporary files of killed writers are cleaned up.
#include <gtest/gtest.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cstdio>
#include <filesystem>
#include <map>
#include <string>
#include <utility>
#include <vector>

#include "cli/run_guard.h"
#include "host/io/atomic_file.h"
#include "host/io/image_io.h"
#include "host/io/output_set.h"
#include "host/io/ply_io.h"
#include "tests/cli_test_util.h"
#include "tests/io_test_util.h"

namespace fs = std::filesystem;

namespace ag2gs {
namespace {

std::string sample_scene() {
  return test::source_path("data_samples/synth_small");
}
std::string other_scene() {
  return test::source_path("data_samples/synth_hard");
}

// Every regular file below `dir` with its bytes.
std::map<std::string, std::string> snapshot(const fs::path& dir) {
  std::map<std::string, std::string> files;
  for (const auto& e : fs::recursive_directory_iterator(dir))
    if (e.is_regular_file()) files[fs::relative(e.path(), dir).string()] = test::read_bytes(e.path().string());
  return files;
}

void expect_unchanged(const std::map<std::string, std::string>& before, const fs::path& dir, const std::string& what) {
  const std::map<std::string, std::string> after = snapshot(dir);
  EXPECT_EQ(before.size(), after.size()) << what << ": files were added or removed in " << dir;
  for (const auto& [name, bytes] : before) {
    auto it = after.find(name);
    ASSERT_NE(it, after.end()) << what << ": " << name << " was deleted";
    EXPECT_TRUE(it->second == bytes) << what << ": " << name << " was changed";
  }
}

// A pid that no process has: a child that has exited and been reaped.
long dead_pid() {
  const pid_t pid = ::fork();
  if (pid == 0) ::_exit(0);
  int status = 0;
  ::waitpid(pid, &status, 0);
  return static_cast<long>(pid);
}

const std::string kTiny = " -r 4 --iters 6 --stages 1 --log-every 0 --seed 3";

TEST(CliGuards, TrainAndBaselineRefuseAFolderThatHoldsAModel) {
  test::ScratchDir dir("guard_train");
  const std::string m = dir.file("m");
  test::CliResult r = test::run_cli("train " + sample_scene() + " -o " + m + kTiny);
  ASSERT_EQ(r.code, 0) << r.output;
  const auto before = snapshot(m);

  r = test::run_cli("train " + other_scene() + " -o " + m + kTiny);
  EXPECT_EQ(r.code, 1) << r.output;
  EXPECT_NE(r.output.find("already holds a trained model"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("--resume"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("--force"), std::string::npos) << r.output;
  expect_unchanged(before, m, "train into a model folder");

  r = test::run_cli("baseline " + other_scene() + " -o " + m + " -r 4 --iters 5 --log-every 0");
  EXPECT_EQ(r.code, 1) << r.output;
  EXPECT_NE(r.output.find("--force"), std::string::npos) << r.output;
  expect_unchanged(before, m, "baseline into a model folder");

  // --force proceeds and replaces the model.
  r = test::run_cli("train " + other_scene() + " -o " + m + kTiny + " --force");
  ASSERT_EQ(r.code, 0) << r.output;
  EXPECT_FALSE(test::read_bytes(m + "/model.ag2gs") == before.at("model.ag2gs"));
}

TEST(CliGuards, SynthRefusesAFolderThatIsNotEmpty) {
  test::ScratchDir dir("guard_synth");
  fs::copy(sample_scene(), dir.path() / "scene", fs::copy_options::recursive);
  const auto before = snapshot(dir.path() / "scene");
  test::CliResult r = test::run_cli("synth " + dir.file("scene") + " --views 4 --width 32 --height 24");
  EXPECT_EQ(r.code, 1) << r.output;
  EXPECT_NE(r.output.find("not empty"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("--force"), std::string::npos) << r.output;
  expect_unchanged(before, dir.path() / "scene", "synth into a scene");
  // An empty folder is fine.
  fs::create_directories(dir.path() / "empty");
  r = test::run_cli("synth " + dir.file("empty") + " --views 3 --width 32 --height 24 --points 50");
  EXPECT_EQ(r.code, 0) << r.output;
}

TEST(CliGuards, EvalRefusesAReportOverItsInputs) {
  test::ScratchDir dir("guard_eval");
  const std::string scene = sample_scene();
  test::write_bytes(dir.file("m/model.ag2gs"), "the user's model");
  test::write_bytes(dir.file("m/metrics.json"), "{\"final\": 1}");
  test::write_bytes(dir.file("m/point_cloud_objects.ply"), "the user's Gaussians without the sky");
  const auto before = snapshot(dir.path() / "m");
  const std::string common = "eval " + dir.file("m") + " --scene " + scene + " --labels " + scene + "/label --vocab " +
                             scene + "/vocab.json --clicks " + scene + "/clicks.json -o ";
  for (const std::string& out : {dir.file("m/model.ag2gs"), dir.file("m/./metrics.json"),
                                 dir.file("m/../m/model.ag2gs"), dir.file("m/point_cloud_objects.ply")}) {
    test::CliResult r = test::run_cli(common + out);
    EXPECT_EQ(r.code, 1) << r.output;
    EXPECT_NE(r.output.find("is the input"), std::string::npos) << r.output;
  }
  expect_unchanged(before, dir.path() / "m", "eval -o over the model");
}

// A corrupt mask file stops train and baseline before the first iteration
// (issue 42: masks were read when a view's mask step came, so 7 corrupt
// files passed `train --iters 20` and failed at iteration 120).
TEST(CliGuards, CorruptMasksAreFoundBeforeTrainingStarts) {
  test::ScratchDir dir("guard_masks");
  const fs::path scene = dir.path() / "scene";
  fs::create_directories(scene);
  for (const char* sub : {"images", "sparse", "language_features"})
    fs::copy(fs::path(sample_scene()) / sub, scene / sub, fs::copy_options::recursive);
  test::write_bytes((scene / "language_features" / "view_015_s.npy").string(), "not an npy file");
  for (const std::string cmd : {"train", "baseline"}) {
    const test::CliResult r = test::run_cli(cmd + " " + scene.string() + " -o " + dir.file(cmd) +
                                            " -r 4 --iters 2 --log-every 1" + (cmd == "train" ? " --stages 1" : ""));
    EXPECT_EQ(r.code, 1) << cmd << ": " << r.output;
    EXPECT_NE(r.output.find("view_015_s.npy"), std::string::npos) << cmd << ": " << r.output;
    EXPECT_EQ(r.output.find("it      1/"), std::string::npos) << cmd << ": training started: " << r.output;
  }
}

// A folder where a file belongs gets a message that says so (issue 42:
// std::bad_alloc for a cameras.bin folder, "read error in the header").
TEST(CliGuards, AFolderWhereAFileBelongsIsNamed) {
  test::ScratchDir dir("guard_folders");
  const fs::path scene = dir.path() / "scene";
  fs::create_directories(scene);
  fs::copy(fs::path(sample_scene()) / "images", scene / "images", fs::copy_options::recursive);
  fs::copy(fs::path(sample_scene()) / "sparse", scene / "sparse", fs::copy_options::recursive);
  fs::remove(scene / "sparse" / "0" / "cameras.bin");
  fs::create_directories(scene / "sparse" / "0" / "cameras.bin");
  fs::create_directories(dir.path() / "m" / "model.ag2gs");
  const std::vector<std::pair<std::string, std::string>> cases = {
      {"train " + scene.string() + " -o " + dir.file("o") + " --iters 1", "cameras.bin: is a folder"},
      {"info " + dir.file("m"), "model.ag2gs: is a folder, not a model file"},
      {"render --ply " + dir.file("m") + " --scene " + sample_scene() + " -o " + dir.file("r"),
       "is a folder, not a .ply file"}};
  for (const auto& [cmd, message] : cases) {
    const test::CliResult r = test::run_cli(cmd);
    EXPECT_EQ(r.code, 1) << cmd << "\n" << r.output;
    EXPECT_NE(r.output.find(message), std::string::npos) << cmd << "\n" << r.output;
  }
}

TEST(CliGuards, SeedsAndRangesAreCheckedWithReadableBounds) {
  for (const std::string cmd : {"train x -o y", "baseline x -o y", "synth y"})
    for (const std::string seed : {"-1", "1e23", "1.5", "18446744073709551616"}) {
      test::CliResult r = test::run_cli(cmd + " --seed " + seed);
      EXPECT_NE(r.code, 0) << cmd << " --seed " << seed << ": " << r.output;
      EXPECT_NE(r.output.find("--seed: must be a whole number"), std::string::npos) << r.output;
    }
  for (const std::string bad : {"--top-cells 0", "--w-prop -1", "--prop-tau nan", "--save-every -3"}) {
    test::CliResult r = test::run_cli("train x -o y " + bad);
    EXPECT_NE(r.code, 0) << bad << ": " << r.output;
    EXPECT_LT(r.output.size(), 300u) << bad << " gives an unreadable message: " << r.output;
    EXPECT_EQ(r.output.find("179769313486"), std::string::npos) << r.output;
  }
}

TEST(CliGuards, GaussianFilesWithInvalidNumbersAreRefusedByInfoAndRender) {
  test::ScratchDir dir("guard_ply");
  GaussianSet gs;
  gs.sh_degree = 0;
  gs.resize(5);
  for (size_t i = 0; i < 5; ++i) {
    gs.means[3 * i + 2] = 0.2f * i;
    for (int k = 0; k < 3; ++k) gs.scales[3 * i + k] = 0.1f;
    gs.quats[4 * i] = 1.f;
    gs.opacities[i] = 0.8f;
  }
  gs.means[3 * 2] = NAN;
  const std::string ply = dir.file("bad.ply");
  write_ply(ply, gs);
  test::CliResult r = test::run_cli("info " + ply);
  EXPECT_EQ(r.code, 1) << r.output;
  EXPECT_NE(r.output.find("1 of 5 Gaussians hold invalid numbers"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("vertex 2"), std::string::npos) << r.output;
  EXPECT_EQ(r.output.find("nan\n"), std::string::npos) << "info printed a nan statistic: " << r.output;
  const std::string render =
      "render --ply " + ply + " --scene " + sample_scene() + " --views view_000 -r 4 -o " + dir.file("out");
  r = test::run_cli(render);
  EXPECT_EQ(r.code, 1) << r.output;
  EXPECT_NE(r.output.find("--drop-invalid"), std::string::npos) << r.output;
  EXPECT_FALSE(fs::exists(dir.file("out/rgb/view_000.png")));
  r = test::run_cli(render + " --drop-invalid");
  EXPECT_EQ(r.code, 0) << r.output;
  EXPECT_NE(r.output.find("left out 1 Gaussians"), std::string::npos) << r.output;
  EXPECT_TRUE(fs::exists(dir.file("out/rgb/view_000.png")));
}

// PoCL hides its device when it cannot create its kernel cache: the error
// says so instead of "install a driver".
TEST(CliGuards, AnUnwritableCacheFolderIsNamedWhenNoDeviceIsFound) {
  const char* bin = std::getenv("AG2GS_BINARY");
  const std::string cmd =
      std::string("env -u XDG_CACHE_HOME -u POCL_CACHE_DIR HOME=/proc ") + (bin ? bin : "./ag2gs") + " devices 2>&1";
  std::string out;
  FILE* p = popen(cmd.c_str(), "r");
  ASSERT_NE(p, nullptr);
  char buf[4096];
  while (fgets(buf, sizeof buf, p)) out += buf;
  const int status = pclose(p);
  if (WIFEXITED(status) && WEXITSTATUS(status) == 0)
    GTEST_SKIP() << "a driver that needs no cache folder answered: " << out;
  EXPECT_NE(out.find("/proc is not writable"), std::string::npos) << out;
  EXPECT_NE(out.find("XDG_CACHE_HOME"), std::string::npos) << out;
}

TEST(CliGuards, StaleTemporaryFilesOfDeadProcessesAreRemoved) {
  test::ScratchDir dir("guard_tmp");
  const std::string dead = dir.file("point_cloud.ply.tmp." + std::to_string(dead_pid()));
  const std::string live = dir.file("model.ag2gs.tmp." + std::to_string(static_cast<long>(::getppid())));
  const std::string user = dir.file("notes.tmp.txt");
  const std::string user_dead = dir.file("thesis.tex.tmp." + std::to_string(dead_pid()));
  // An image is written as ".NAME.png.tmp.PID.png" (OpenCV needs the extension).
  const std::string image = dir.file(".view_000.png.tmp." + std::to_string(dead_pid()) + ".png");
  const std::string live_image = dir.file(".view_001.png.tmp." + std::to_string(::getppid()) + ".png");
  for (const std::string& f : {dead, live, user, user_dead, image, live_image}) test::write_bytes(f, "x");
  EXPECT_EQ(remove_stale_temp_files(dir.str()), 2);
  EXPECT_FALSE(fs::exists(dead));
  EXPECT_FALSE(fs::exists(image)) << "a killed run's image was left";
  EXPECT_TRUE(fs::exists(live_image));
  EXPECT_TRUE(fs::exists(live)) << "a running process's temporary file was removed";
  EXPECT_TRUE(fs::exists(user)) << "a file that is not ours was removed";
  EXPECT_TRUE(fs::exists(user_dead)) << "a file of a kind ag2gs never writes was removed";

  // The next write into the folder cleans up after a killed run.
  const std::string m = dir.file("m");
  const std::string stale = m + "/checkpoint.ag2gs.tmp." + std::to_string(dead_pid());
  test::write_bytes(stale, std::string(1 << 16, 'x'));
  test::CliResult r = test::run_cli("train " + sample_scene() + " -o " + m + kTiny);
  ASSERT_EQ(r.code, 0) << r.output;
  EXPECT_FALSE(fs::exists(stale)) << "a dead run's temporary file survived the next write";
}

// Two images with one stem in different folders (a/1.jpg, b/1.jpg) get
// their own output names in render and query (16 views wrote 15 files).
TEST(CliGuards, OutputStemsTellApartImagesSharingAStem) {
  EXPECT_EQ(cli::output_stems({"a/1.jpg", "b/1.jpg", "2.png", "c/d/3.png"}),
            (std::vector<std::string>{"a_1", "b_1", "2", "3"}));
  EXPECT_EQ(cli::output_stems({"1.jpg", "sub/1.png"}), (std::vector<std::string>{"1", "sub_1"}));
  EXPECT_EQ(cli::output_stems({}), std::vector<std::string>{});
  // Names that still collide after that are refused, naming the view.
  try {
    cli::output_stems({"a_1.jpg", "a/1.jpg", "b/1.jpg", "a_1.png"});
    ADD_FAILURE() << "no error";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("would write the same files"), std::string::npos) << e.what();
  }
}

}  // namespace
}  // namespace ag2gs

namespace ag2gs {
namespace {

// Files written under the folder of a live OutputSet stay in their temporary
// files until commit(), which puts them all in place; without commit() the
// earlier files stay and no temporary file is left.
TEST(OutputSetTest, FilesGoInPlaceTogetherOrNotAtAll) {
  test::ScratchDir dir("output_set");
  fs::create_directories(dir.file("rgb"));
  const std::string json = dir.file("report.json"), png = dir.file("rgb/view_000.png");
  test::write_bytes(json, "old");
  test::write_bytes(png, "old");
  const std::vector<float> grey(4 * 3, 0.5f);
  auto write_both = [&] {
    AtomicFile f(json);
    f.write("new");
    f.commit();
    write_rgb_png(png, grey, 2, 2);
  };
  auto temporary_files = [&] {
    int n = 0;
    for (const auto& e : fs::recursive_directory_iterator(dir.str()))
      n += e.path().filename().string().find(".tmp.") != std::string::npos;
    return n;
  };
  {
    OutputSet set(dir.str());
    write_both();
    EXPECT_EQ(set.size(), 2u);
    EXPECT_EQ(test::read_bytes(json), "old") << "a file went into place before the set's commit";
    EXPECT_EQ(test::read_bytes(png), "old");
  }  // stopped before commit()
  EXPECT_EQ(test::read_bytes(json), "old");
  EXPECT_EQ(test::read_bytes(png), "old");
  EXPECT_EQ(temporary_files(), 0);
  {
    OutputSet set(dir.str());
    write_both();
    set.remove_at_commit(dir.file("rgb/stale.png"));
    test::write_bytes(dir.file("rgb/stale.png"), "old");
    set.commit();
  }
  EXPECT_EQ(test::read_bytes(json), "new");
  EXPECT_NE(test::read_bytes(png), "old");
  EXPECT_FALSE(fs::exists(dir.file("rgb/stale.png")));
  EXPECT_EQ(temporary_files(), 0);
  EXPECT_EQ(finish_interrupted_output_sets(dir.str()), 0);
  // Outside the set's folder a write goes straight to its file.
  test::ScratchDir other("output_set_other");
  OutputSet set(dir.str());
  AtomicFile f(other.file("x.json"));
  f.write("x");
  f.commit();
  EXPECT_EQ(test::read_bytes(other.file("x.json")), "x");
  EXPECT_EQ(set.size(), 0u);
}

// A process killed during its commit left a journal: the next run into the
// folder finishes it (the new set). One killed while writing the journal left
// a ".json.tmp": the old set stands and the new files' copies are deleted.
TEST(OutputSetTest, TheNextRunFinishesAKilledCommit) {
  test::ScratchDir dir("output_set_journal");
  const long dead = dead_pid();
  const std::string t = ".tmp." + std::to_string(dead);
  fs::create_directories(dir.file("masks"));
  test::write_bytes(dir.file("selection.json"), "old");
  test::write_bytes(dir.file("masks/a.png"), "new a");  // renamed before the kill
  test::write_bytes(dir.file("selection.json" + t), "new");
  test::write_bytes(dir.file("masks/b.png"), "old b");  // stale: the journal removes it
  test::write_bytes(dir.file(".ag2gs-commit." + std::to_string(dead) + ".json"),
                    R"({"renames": [["masks/a.png)" + t + R"(", "masks/a.png"], ["selection.json)" + t +
                        R"(", "selection.json"]], "removals": ["masks/b.png"]})");
  EXPECT_EQ(finish_interrupted_output_sets(dir.str()), 1);
  EXPECT_EQ(test::read_bytes(dir.file("selection.json")), "new");
  EXPECT_EQ(test::read_bytes(dir.file("masks/a.png")), "new a");
  EXPECT_FALSE(fs::exists(dir.file("masks/b.png")));
  EXPECT_FALSE(fs::exists(dir.file(".ag2gs-commit." + std::to_string(dead) + ".json")));

  test::write_bytes(dir.file("selection.json" + t), "newer");
  test::write_bytes(dir.file("masks/.c.png.tmp." + std::to_string(dead) + ".png"), "newer c");
  test::write_bytes(dir.file(".ag2gs-commit." + std::to_string(dead) + ".json.tmp"), "{\"ren");
  EXPECT_EQ(finish_interrupted_output_sets(dir.str()), 0);
  EXPECT_EQ(test::read_bytes(dir.file("selection.json")), "new");
  EXPECT_FALSE(fs::exists(dir.file("selection.json" + t)));
  EXPECT_FALSE(fs::exists(dir.file("masks/.c.png.tmp." + std::to_string(dead) + ".png")));
  EXPECT_FALSE(fs::exists(dir.file(".ag2gs-commit." + std::to_string(dead) + ".json.tmp")));

  // A planted journal naming paths outside its folder moves nothing.
  test::ScratchDir outside("output_set_outside");
  test::write_bytes(outside.file("keep.txt"), "mine");
  test::write_bytes(dir.file("masks/x.png"), "x");
  const std::string planted = dir.file(".ag2gs-commit." + std::to_string(dead) + ".json");
  const std::string escape = fs::relative(outside.file("keep.txt"), dir.str()).string();
  for (const std::string& bad :
       std::vector<std::string>{"[[\"masks/x.png\", \"" + escape + "\"]]", "[[\"/etc/hostname\", \"masks/y.png\"]]",
                                "[[\"masks/x.png\"]]"}) {
    test::write_bytes(planted, "{\"renames\": " + bad + "}");
    try {
      finish_interrupted_output_sets(dir.str());
      ADD_FAILURE() << "accepted " << bad;
    } catch (const std::runtime_error& e) {
      EXPECT_NE(std::string(e.what()).find("not"), std::string::npos) << e.what();
    }
    EXPECT_EQ(test::read_bytes(outside.file("keep.txt")), "mine");
    EXPECT_EQ(test::read_bytes(dir.file("masks/x.png")), "x");
  }
}

}  // namespace
}  // namespace ag2gs
