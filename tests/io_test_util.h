// Helpers shared by the I/O tests: temporary folders, raw file bytes and
// checks on the exception messages users read.
#pragma once

#include <gtest/gtest.h>
#include <unistd.h>

#include <algorithm>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <functional>
#include <sstream>
#include <string>
#include <vector>

namespace ag2gs::test {

inline std::string source_path(const std::string& rel) {
  const char* env = std::getenv("AG2GS_SOURCE_DIR");
  return std::string(env && *env ? env : ".") + "/" + rel;
}

// A fresh directory under the system temp folder, removed with its contents.
class ScratchDir {
 public:
  explicit ScratchDir(const std::string& tag = "scratch") {
    static int counter = 0;
    path_ = std::filesystem::temp_directory_path() /
            ("ag2gs_" + tag + "_" + std::to_string(::getpid()) + "_" + std::to_string(counter++));
    std::filesystem::remove_all(path_);
    std::filesystem::create_directories(path_);
  }
  ~ScratchDir() {
    // Tests make parts read-only to provoke write failures: give access back first.
    namespace fs = std::filesystem;
    std::error_code ec;
    fs::permissions(path_, fs::perms::owner_all, fs::perm_options::add, ec);
    for (const auto& e : fs::recursive_directory_iterator(path_, ec)) {
      fs::permissions(e.path(), fs::perms::owner_all, fs::perm_options::add, ec);
    }
    fs::remove_all(path_, ec);
  }
  std::string file(const std::string& name) const { return (path_ / name).string(); }
  const std::filesystem::path& path() const { return path_; }
  std::string str() const { return path_.string(); }
  // Names of the entries directly inside (or inside `sub`), sorted.
  std::vector<std::string> entries(const std::string& sub = "") const {
    std::vector<std::string> names;
    for (const auto& e : std::filesystem::directory_iterator(path_ / sub))
      names.push_back(e.path().filename().string());
    std::sort(names.begin(), names.end());
    return names;
  }

 private:
  std::filesystem::path path_;
};

inline void write_bytes(const std::string& path, const std::string& bytes) {
  std::filesystem::create_directories(std::filesystem::path(path).parent_path());
  std::ofstream out(path, std::ios::binary);
  out.write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
}

inline std::string read_bytes(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  std::ostringstream ss;
  ss << in.rdbuf();
  return ss.str();
}

// Expects model.ag2gs, point_cloud.ply and checkpoint.ag2gs of two model
// folders to be byte-identical (and present); `what` names the two runs.
inline void expect_same_model_files(const std::string& dir_a, const std::string& dir_b, const std::string& what) {
  for (const char* f : {"model.ag2gs", "point_cloud.ply", "checkpoint.ag2gs"}) {
    const std::string a = read_bytes(dir_a + "/" + f);
    const std::string b = read_bytes(dir_b + "/" + f);
    ASSERT_FALSE(a.empty()) << dir_a << "/" << f;
    EXPECT_TRUE(a == b) << f << " differs between " << what;
  }
}

// Runs fn and expects an exception of type E whose message holds every needle.
template <class E>
void expect_error_with(const std::function<void()>& fn, const std::vector<std::string>& needles) {
  try {
    fn();
    ADD_FAILURE() << "no exception; expected one mentioning '" << needles.front() << "'";
  } catch (const E& e) {
    const std::string msg = e.what();
    for (const std::string& n : needles) {
      EXPECT_NE(msg.find(n), std::string::npos) << "message lacks '" << n << "': " << msg;
    }
  } catch (const std::exception& e) {
    ADD_FAILURE() << "wrong exception type: " << e.what();
  }
}

}  // namespace ag2gs::test
