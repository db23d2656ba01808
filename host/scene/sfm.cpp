#include "host/scene/sfm.h"

#include <poll.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <cctype>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <deque>
#include <filesystem>
#include <fstream>
#include <map>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <regex>
#include <sstream>
#include <stdexcept>
#include <thread>

#include "host/io/colmap_reader.h"
#include "host/scene/scene.h"

namespace ag2gs {
namespace {

namespace fs = std::filesystem;

constexpr const char* kInstallHint =
    "install COLMAP (Debian/Ubuntu: `sudo apt-get install colmap`), or pass its path with --colmap PATH "
    "(or set AG2GS_COLMAP)";

void say(const SfmOptions& o, const std::string& line) {
  if (o.progress) o.progress(line);
}

// run_logged's status for a program that stopped making progress and was killed.
constexpr int kStalled = -2;

// Seconds without output and without CPU time after which a COLMAP step
// counts as hung (AG2GS_SFM_STALL_SECONDS overrides; the tests use 2). A
// working step prints or computes; COLMAP's feature extractor has been seen
// to deadlock at 0% CPU on a busy 2-core machine, which would wait forever.
int stall_seconds() {
  if (const char* env = std::getenv("AG2GS_SFM_STALL_SECONDS"); env && *env) {
    const int v = std::atoi(env);
    if (v > 0) return v;
  }
  return 300;
}

// The CPU time so far, in clock ticks (user + system, /proc/PID/stat), of
// `root` and every process below it (a wrapper script's colmap counts), and
// their ids in *tree; -1 when /proc cannot be read.
long long tree_cpu_ticks(pid_t root, std::vector<pid_t>* tree) {
  struct Proc {
    pid_t ppid;
    long long ticks;
  };
  std::map<pid_t, Proc> procs;
  std::error_code ec;
  for (const auto& entry : fs::directory_iterator("/proc", ec)) {
    const std::string name = entry.path().filename().string();
    if (name.empty() || !std::isdigit(static_cast<unsigned char>(name[0]))) continue;
    std::ifstream f(entry.path() / "stat");
    std::string stat;
    if (!std::getline(f, stat)) continue;
    const size_t close = stat.rfind(')');  // the command name may hold spaces
    if (close == std::string::npos) continue;
    std::istringstream rest(stat.substr(close + 1));
    std::string field;
    long long ppid = -1, utime = -1, stime = -1;
    for (int k = 3; rest >> field; ++k) {  // field 3 is the state
      if (k == 4) ppid = std::atoll(field.c_str());
      if (k == 14) utime = std::atoll(field.c_str());
      if (k == 15) {
        stime = std::atoll(field.c_str());
        break;
      }
    }
    if (ppid >= 0 && utime >= 0 && stime >= 0)
      procs[static_cast<pid_t>(std::atol(name.c_str()))] = {static_cast<pid_t>(ppid), utime + stime};
  }
  if (!procs.count(root)) return -1;
  tree->assign(1, root);
  long long total = 0;
  for (size_t k = 0; k < tree->size(); ++k) {
    total += procs[(*tree)[k]].ticks;
    for (const auto& [id, proc] : procs)
      if (proc.ppid == (*tree)[k]) tree->push_back(id);
  }
  return total;
}

// Runs argv[0] with its arguments, appending stdout+stderr to `log`; `on_line`
// sees every output line. Returns the exit status (-1 when it could not run,
// kStalled when it printed nothing and used no CPU time for stall_seconds()
// and was killed with the processes it started). It stays in our process
// group, so that Ctrl-C stops it with us.
int run_logged(const std::vector<std::string>& argv, std::ofstream& log, std::deque<std::string>& tail,
               const std::function<void(const std::string&)>& on_line) {
  log << "$";
  for (const std::string& a : argv) log << " " << a;
  log << "\n";
  log.flush();
  int fds[2];
  if (::pipe(fds) != 0) return -1;
  const pid_t pid = ::fork();
  if (pid < 0) {
    ::close(fds[0]);
    ::close(fds[1]);
    return -1;
  }
  if (pid == 0) {
    ::dup2(fds[1], 1);
    ::dup2(fds[1], 2);
    ::close(fds[0]);
    ::close(fds[1]);
    std::vector<char*> args;
    for (const std::string& a : argv) args.push_back(const_cast<char*>(a.c_str()));
    args.push_back(nullptr);
    // COLMAP is a Qt program; keep it off any display.
    ::setenv("QT_QPA_PLATFORM", "offscreen", 1);
    ::execvp(args[0], args.data());
    std::fprintf(stderr, "cannot run %s: %s\n", args[0], std::strerror(errno));
    ::_exit(127);
  }
  ::close(fds[1]);
  std::string pending;
  char buf[4096];
  using Clock = std::chrono::steady_clock;
  const auto limit = std::chrono::seconds(stall_seconds());
  auto active = Clock::now();
  std::vector<pid_t> tree;
  long long ticks = tree_cpu_ticks(pid, &tree);
  const bool watch = ticks >= 0;  // without /proc, no watchdog
  bool stalled = false, reaped = false;
  int status = 0;
  for (;;) {
    pollfd pfd{fds[0], POLLIN, 0};
    const int ready = ::poll(&pfd, 1, 1000);
    if (ready < 0 && errno == EINTR) continue;
    if (ready == 0) {
      if (::waitpid(pid, &status, WNOHANG) == pid) {  // gone; something else holds the pipe
        reaped = true;
        break;
      }
      if (!watch) continue;
      const long long now_ticks = tree_cpu_ticks(pid, &tree);
      if (now_ticks != ticks) {
        ticks = now_ticks;
        active = Clock::now();
      } else if (Clock::now() - active > limit) {
        for (pid_t p : tree) ::kill(p, SIGKILL);
        stalled = true;
        break;
      }
      continue;
    }
    const ssize_t n = ::read(fds[0], buf, sizeof buf);
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) break;
    active = Clock::now();
    log.write(buf, n);
    pending.append(buf, static_cast<size_t>(n));
    size_t pos;
    while ((pos = pending.find_first_of("\r\n")) != std::string::npos) {
      std::string line = pending.substr(0, pos);
      pending.erase(0, pos + 1);
      if (line.empty()) continue;
      tail.push_back(line);
      if (tail.size() > 15) tail.pop_front();
      if (on_line) on_line(line);
    }
  }
  ::close(fds[0]);
  log.flush();
  while (!reaped && ::waitpid(pid, &status, 0) < 0 && errno == EINTR) {
  }
  if (stalled) {
    log << "[ag2gs] no output and no CPU time for " << stall_seconds() << " s: stopped\n";
    log.flush();
    return kStalled;
  }
  if (WIFEXITED(status)) return WEXITSTATUS(status);
  return -1;
}

// A temporary sibling of `target` that replaces it only on success.
class StagingDir {
 public:
  StagingDir(const fs::path& target, bool force) : target_(fs::absolute(target)) {
    if (fs::exists(target_) && !(fs::is_directory(target_) && fs::is_empty(target_)) && !force) {
      throw std::runtime_error(target_.string() +
                               ": already exists and is not empty; choose a new output folder or pass --force to "
                               "replace it (it is replaced only when the new scene is complete)");
    }
    fs::create_directories(target_.parent_path());
    path_ =
        target_.parent_path() / (target_.filename().string() + ".tmp." + std::to_string(static_cast<long>(::getpid())));
    fs::remove_all(path_);
    fs::create_directories(path_);
  }
  ~StagingDir() {
    std::error_code ec;
    if (!committed_) fs::remove_all(path_, ec);
  }
  const fs::path& path() const { return path_; }
  const fs::path& target() const { return target_; }
  void commit() {
    const fs::path old = target_.string() + ".old." + std::to_string(static_cast<long>(::getpid()));
    std::error_code ec;
    if (fs::exists(target_)) fs::rename(target_, old);
    fs::rename(path_, target_);
    fs::remove_all(old, ec);
    committed_ = true;
  }

 private:
  fs::path target_, path_;
  bool committed_ = false;
};

struct Step {
  std::string name;
  std::vector<std::string> argv;
};

// "42 s", "3m05s", "1h17m".
std::string duration_str(double s) {
  char buf[32];
  const long t = std::lround(std::max(s, 0.0));
  if (t < 60)
    std::snprintf(buf, sizeof buf, "%ld s", t);
  else if (t < 3600)
    std::snprintf(buf, sizeof buf, "%ldm%02lds", t / 60, t % 60);
  else
    std::snprintf(buf, sizeof buf, "%ldh%02ldm", t / 3600, (t % 3600) / 60);
  return buf;
}

// Runs one COLMAP step. Progress lines (see parse_colmap_progress) are shown
// with the elapsed time and a linear ETA: the first one, then one per 10% or
// per 10 s, whichever comes first; `images` (when known) completes the
// mapper's "registered k of n".
void run_step(const Step& step, std::ofstream& log, const std::string& log_path, const SfmOptions& o, int images = 0) {
  using Clock = std::chrono::steady_clock;
  const auto t0 = Clock::now();
  say(o, step.name + " ...");
  std::deque<std::string> tail;
  static const std::regex registering(R"(Registering image #(\d+) \((\d+)\))");
  auto last = t0;
  int last_decile = -1, shown = 0;
  auto on_line = [&](const std::string& line) {
    const auto now = Clock::now();
    const double el = std::chrono::duration<double>(now - t0).count();
    const bool due = shown == 0 || now - last >= std::chrono::seconds(10);
    ColmapProgress p;
    std::smatch m;
    std::string update;
    if (parse_colmap_progress(line, &p) && p.total > 0 && p.done < p.total) {
      const int decile = 10 * p.done / p.total;
      if (!due && decile <= last_decile) return;
      last_decile = decile;
      update = "  " + p.unit + " " + std::to_string(p.done) + "/" + std::to_string(p.total) + " (" +
               std::to_string(100 * p.done / p.total) + "%), " + duration_str(el) + " elapsed";
      if (p.done > 0) update += ", about " + duration_str(el / p.done * (p.total - p.done)) + " left";
    } else if (std::regex_search(line, m, registering)) {
      if (!due) return;
      update = "  registered " + m[2].str() + (images > 0 ? " of " + std::to_string(images) : "") + " images, " +
               duration_str(el) + " elapsed";
    } else {
      return;
    }
    say(o, update);
    last = now;
    ++shown;
  };
  int rc = run_logged(step.argv, log, tail, on_line);
  if (rc == kStalled) {
    // A hang is not the input's fault: one more try.
    say(o, step.name + ": colmap printed nothing and used no CPU time for " + std::to_string(stall_seconds()) +
               " s; stopped it, trying the step once more");
    rc = run_logged(step.argv, log, tail, on_line);
  }
  const double s = std::chrono::duration<double>(Clock::now() - t0).count();
  if (rc == kStalled)
    throw std::runtime_error(step.name + " hung twice (colmap printed nothing and used no CPU time for " +
                             std::to_string(stall_seconds()) + " s each time, and was stopped); full log: " + log_path);
  if (rc != 0) {
    std::string msg = step.name + " failed (colmap exit status " + std::to_string(rc) + ")";
    if (rc == 127) msg += "; could not run " + step.argv[0] + ": " + kInstallHint;
    msg += ". Last lines:\n";
    for (const std::string& l : tail) msg += "    " + l + "\n";
    msg += "  full log: " + log_path;
    throw std::runtime_error(msg);
  }
  char buf[64];
  std::snprintf(buf, sizeof buf, " done in %.1f s", s);
  say(o, step.name + buf);
}

int count_images(const fs::path& sparse) {
  try {
    return static_cast<int>(read_colmap_model(sparse.string(), true).cameras_for_images.size());
  } catch (const std::exception&) {
    return 0;
  }
}

// Moves undistorter output (images/, sparse/*.bin) into the 3DGS layout.
SfmResult finish_scene(const fs::path& undistorted, StagingDir& staging, std::ofstream& log, const SfmOptions& o) {
  const fs::path scene = staging.path();
  fs::rename(undistorted / "images", scene / "images");
  fs::create_directories(scene / "sparse" / "0");
  for (const auto& e : fs::directory_iterator(undistorted / "sparse")) {
    if (e.is_regular_file()) fs::rename(e.path(), scene / "sparse" / "0" / e.path().filename());
  }
  const ColmapModel model = read_colmap_model((scene / "sparse" / "0").string());
  SfmResult r;
  r.images_registered = static_cast<int>(model.cameras_for_images.size());
  r.points = static_cast<int>(model.points.size());
  if (o.downscaled_copies) {
    for (int f : {2, 4, 8}) {
      const fs::path dir = scene / ("images_" + std::to_string(f));
      fs::create_directories(dir);
      for (const Camera& cam : model.cameras_for_images) {
        const Camera small = scale_camera(cam, f);
        cv::Mat img = cv::imread((scene / "images" / cam.name).string(), cv::IMREAD_UNCHANGED);
        if (img.empty()) continue;
        cv::resize(img, img, cv::Size(small.width, small.height), 0, 0, cv::INTER_AREA);
        fs::create_directories((dir / cam.name).parent_path());
        cv::imwrite((dir / cam.name).string(), img);
      }
      say(o, "wrote " + dir.filename().string() + "/");
    }
  }
  log.close();
  return r;
}

}  // namespace

std::vector<std::string> list_image_files(const std::string& dir) {
  static const char* kExt[] = {".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".webp", ".ppm", ".pgm", ".exr"};
  std::vector<std::string> files;
  if (!fs::is_directory(dir)) return files;
  for (const auto& e : fs::directory_iterator(dir)) {
    if (!e.is_regular_file()) continue;
    std::string ext = e.path().extension().string();
    std::transform(ext.begin(), ext.end(), ext.begin(), [](unsigned char c) { return std::tolower(c); });
    if (std::find_if(std::begin(kExt), std::end(kExt), [&](const char* x) { return ext == x; }) != std::end(kExt)) {
      files.push_back(e.path().filename().string());
    }
  }
  std::sort(files.begin(), files.end());
  return files;
}

MatcherChoice choose_matcher(const std::vector<std::string>& names) {
  const size_t n = names.size();
  const std::string pairs = std::to_string(n * (n - (n > 0)) / 2) + " pairs";
  if (n <= static_cast<size_t>(kSequentialMinImages)) {
    return {"exhaustive", std::to_string(n) + " photos, few enough to match all " + pairs};
  }
  std::vector<std::string> sorted = names;
  std::sort(sorted.begin(), sorted.end());  // the order COLMAP's sequential matcher pairs them in
  // Each name as <pattern> + <number>: the last run of digits in its stem.
  std::vector<long long> numbers;
  std::string pattern0;
  for (const std::string& name : sorted) {
    const std::string stem = fs::path(name).stem().string();
    const size_t end = stem.find_last_of("0123456789");
    if (end == std::string::npos) {
      return {"exhaustive",
              "the names carry no frame numbers (" + name + "), so the photos are not an ordered sequence"};
    }
    size_t begin = end;
    while (begin > 0 && std::isdigit(static_cast<unsigned char>(stem[begin - 1]))) --begin;
    if (end - begin + 1 > 15) return {"exhaustive", "the number in " + name + " is too long to be a frame number"};
    std::string pattern = stem.substr(0, begin) + "#" + stem.substr(end + 1) + fs::path(name).extension().string();
    std::transform(pattern.begin(), pattern.end(), pattern.begin(), [](unsigned char c) { return std::tolower(c); });
    if (numbers.empty()) pattern0 = pattern;
    if (pattern != pattern0) {
      return {"exhaustive", "the names follow more than one pattern (" + sorted.front() + ", " + name +
                                "), so the photos are not one ordered sequence"};
    }
    numbers.push_back(std::stoll(stem.substr(begin, end - begin + 1)));
  }
  // Steps between neighbours in name order: most must equal the common step,
  // the rest be a few steps (dropped frames); none may go backwards.
  std::map<long long, int> steps;
  for (size_t i = 1; i < n; ++i) {
    const long long d = numbers[i] - numbers[i - 1];
    if (d <= 0) {
      return {"exhaustive", "the frame numbers do not increase in name order (" + sorted[i - 1] + " then " + sorted[i] +
                                "; numbers without leading zeros?), and COLMAP's sequential matcher "
                                "pairs neighbours in name order"};
    }
    ++steps[d];
  }
  const auto common =
      std::max_element(steps.begin(), steps.end(), [](const auto& a, const auto& b) { return a.second < b.second; });
  const long long step = common->first;
  size_t off = 0;
  for (const auto& [d, count] : steps) {
    if (d == step) continue;
    if (d % step != 0 || d > 5 * step) {
      return {"exhaustive", "the frame numbers do not step evenly (" + std::to_string(step) + " between most, " +
                                std::to_string(d) + " between others), so the photos are not an ordered sequence"};
    }
    off += static_cast<size_t>(count);
  }
  if (off * 10 > n - 1) {
    return {"exhaustive", "the frame numbers skip too often (" + std::to_string(off) + " of " + std::to_string(n - 1) +
                              " steps are not " + std::to_string(step) + ") to be an ordered sequence"};
  }
  return {"sequential", std::to_string(n) + " photos named as an ordered sequence (" + sorted.front() + " .. " +
                            sorted.back() + ", step " + std::to_string(step) +
                            "): each is matched with its neighbours in name order instead of all " + pairs +
                            " (--matcher exhaustive for all)"};
}

bool parse_colmap_progress(const std::string& line, ColmapProgress* p) {
  static const std::regex processed(R"(Processed file \[(\d+)/(\d+)\])");
  static const std::regex block(R"(Matching block \[(\d+)/(\d+), (\d+)/(\d+)\])");
  static const std::regex image(R"(Matching image \[(\d+)/(\d+)\])");
  static const std::regex finished(R"(\] in [0-9.]+s)");
  std::smatch m;
  if (std::regex_search(line, m, processed)) {
    *p = {"image", std::stoi(m[1]), std::stoi(m[2])};
    return true;
  }
  const bool done = std::regex_search(line, finished);
  if (std::regex_search(line, m, block)) {
    const int i = std::stoi(m[1]), n = std::stoi(m[2]), j = std::stoi(m[3]), k = std::stoi(m[4]);
    *p = {"block", (i - 1) * k + j - (done ? 0 : 1), n * k};
    return true;
  }
  if (std::regex_search(line, m, image)) {
    *p = {"image", std::stoi(m[1]) - (done ? 0 : 1), std::stoi(m[2])};
    return true;
  }
  return false;
}

std::string find_colmap(const std::string& name) {
  std::string prog = name;
  const char* env = std::getenv("AG2GS_COLMAP");
  if (name == "colmap" && env && *env) prog = env;
  if (prog.find('/') != std::string::npos) {
    if (::access(prog.c_str(), X_OK) == 0) return prog;
    throw std::runtime_error("COLMAP program '" + prog + "' does not exist or is not executable; " + kInstallHint);
  }
  const char* path = std::getenv("PATH");
  std::string p = path ? path : "";
  size_t start = 0;
  while (start <= p.size()) {
    const size_t end = std::min(p.find(':', start), p.size());
    const std::string dir = p.substr(start, end - start);
    const fs::path cand = fs::path(dir.empty() ? "." : dir) / prog;
    if (::access(cand.c_str(), X_OK) == 0 && !fs::is_directory(cand)) return cand.string();
    start = end + 1;
  }
  throw std::runtime_error("the `" + prog + "` program (COLMAP) is not on PATH; " + kInstallHint);
}

SfmResult run_sfm(const std::string& images_dir, const std::string& scene_dir, const SfmOptions& o) {
  const auto t0 = std::chrono::steady_clock::now();
  if (!fs::is_directory(images_dir)) {
    throw std::runtime_error(images_dir + ": no such folder; pass the folder that holds the photos");
  }
  const std::vector<std::string> photos = list_image_files(images_dir);
  if (photos.size() < 2) {
    throw std::runtime_error(images_dir + ": found " + std::to_string(photos.size()) +
                             " image file(s); structure from motion needs at least 2 overlapping photos "
                             "(.jpg, .png, ...) directly in this folder");
  }
  if (o.matcher != "auto" && o.matcher != "exhaustive" && o.matcher != "sequential") {
    throw std::invalid_argument("matcher '" + o.matcher + "' is unknown; use auto, exhaustive or sequential");
  }
  const std::string colmap = find_colmap(o.colmap);
  StagingDir staging(scene_dir, o.force);
  const fs::path work = staging.path() / "colmap_work";
  fs::create_directories(work / "sparse");
  // The log lives beside the output until the scene is complete, so a failed
  // run leaves it behind for the user to read.
  const std::string log_path = staging.target().string() + ".sfm_log.txt";
  std::ofstream log(log_path);
  const std::string db = (work / "database.db").string();
  const std::string images = fs::absolute(images_dir).string();
  const std::string threads = std::to_string(o.threads);
  say(o, std::to_string(photos.size()) + " photos in " + images_dir);
  MatcherChoice choice{o.matcher, "as --matcher says"};
  if (o.matcher == "auto") choice = choose_matcher(photos);
  std::string size_note = "SIFT on at most " + std::to_string(o.max_image_size) + " px (--max-image-size)";
  const cv::Mat first = cv::imread((fs::path(images_dir) / photos.front()).string(), cv::IMREAD_UNCHANGED);
  if (!first.empty()) {
    const bool reduced = std::max(first.cols, first.rows) > o.max_image_size;
    size_note = "SIFT on " + std::to_string(first.cols) + "x" + std::to_string(first.rows) + " photos " +
                (reduced ? "reduced to " : "at their size, up to ") + std::to_string(o.max_image_size) +
                " px on the longest side (--max-image-size)";
  }
  say(o, "matcher: " + choice.matcher + ", " + choice.reason + "; " + size_note);
  // Exhaustive matching reports one line per block of image pairs: blocks of
  // about a quarter of the photos (COLMAP's 50 at most) give 16 or more.
  const int block = std::clamp(static_cast<int>((photos.size() + 3) / 4), 2, 50);
  std::vector<std::string> match_args = {colmap,
                                         choice.matcher + "_matcher",
                                         "--database_path",
                                         db,
                                         "--SiftMatching.use_gpu",
                                         "0",
                                         "--SiftMatching.num_threads",
                                         threads,
                                         "--log_to_stderr",
                                         "1"};
  if (choice.matcher == "exhaustive")
    match_args.insert(match_args.end(), {"--ExhaustiveMatching.block_size", std::to_string(block)});

  run_step({"feature extraction (SIFT, CPU)",
            {colmap, "feature_extractor", "--database_path", db, "--image_path", images, "--ImageReader.camera_model",
             o.camera_model, "--ImageReader.single_camera", o.single_camera ? "1" : "0", "--SiftExtraction.use_gpu",
             "0", "--SiftExtraction.num_threads", threads, "--SiftExtraction.max_image_size",
             std::to_string(o.max_image_size), "--log_to_stderr", "1"}},
           log, log_path, o);
  run_step({"matching (" + choice.matcher + ")", match_args}, log, log_path, o);
  run_step({"mapping",
            {colmap, "mapper", "--database_path", db, "--image_path", images, "--output_path",
             (work / "sparse").string(), "--Mapper.num_threads", threads, "--Mapper.ba_global_function_tolerance",
             "0.000001", "--Mapper.init_min_num_inliers", std::to_string(o.init_min_inliers),
             "--Mapper.abs_pose_min_num_inliers", std::to_string(o.abs_pose_min_inliers), "--log_to_stderr", "1"}},
           log, log_path, o, static_cast<int>(photos.size()));

  // The mapper may leave several models (disconnected groups); keep the largest.
  fs::path best;
  int best_n = 0;
  for (const auto& e : fs::directory_iterator(work / "sparse")) {
    const int n = e.is_directory() ? count_images(e.path()) : 0;
    if (n > best_n) {
      best_n = n;
      best = e.path();
    }
  }
  if (best_n < 2) {
    throw std::runtime_error("mapping registered no usable model (" + std::to_string(best_n) +
                             " images): the photos may not overlap enough or lack texture. Take more photos with "
                             "overlap, or try --matcher exhaustive. Full log: " +
                             log_path);
  }
  run_step({"undistortion",
            {colmap, "image_undistorter", "--image_path", images, "--input_path", best.string(), "--output_path",
             (work / "undistorted").string(), "--output_type", "COLMAP", "--log_to_stderr", "1"}},
           log, log_path, o);
  SfmResult r = finish_scene(work / "undistorted", staging, log, o);
  fs::remove_all(work);
  r.images_in = static_cast<int>(photos.size());
  staging.commit();
  r.log_path = (staging.target() / "sfm_log.txt").string();
  fs::rename(log_path, r.log_path);
  r.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return r;
}

SfmResult undistort_scene(const std::string& scene_dir, const std::string& out_dir, const SfmOptions& o) {
  const auto t0 = std::chrono::steady_clock::now();
  const fs::path scene(scene_dir);
  const fs::path sparse = find_colmap_model(scene_dir);
  const ColmapModel model = read_colmap_model(sparse.string(), true);  // validates before COLMAP runs
  if (!fs::is_directory(scene / "images")) {
    throw std::runtime_error((scene / "images").string() + ": no image folder to undistort");
  }
  const std::string colmap = find_colmap(o.colmap);
  StagingDir staging(out_dir, o.force);
  const fs::path work = staging.path() / "colmap_work";
  fs::create_directories(work);
  // The log lives beside the output until the scene is complete, so a failed
  // run leaves it behind for the user to read.
  const std::string log_path = staging.target().string() + ".sfm_log.txt";
  std::ofstream log(log_path);
  run_step({"undistortion",
            {colmap, "image_undistorter", "--image_path", fs::absolute(scene / "images").string(), "--input_path",
             fs::absolute(sparse).string(), "--output_path", (work / "undistorted").string(), "--output_type", "COLMAP",
             "--log_to_stderr", "1"}},
           log, log_path, o);
  SfmResult r = finish_scene(work / "undistorted", staging, log, o);
  fs::remove_all(work);
  r.images_in = static_cast<int>(model.cameras_for_images.size());
  staging.commit();
  r.log_path = (staging.target() / "sfm_log.txt").string();
  fs::rename(log_path, r.log_path);
  r.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return r;
}

}  // namespace ag2gs
