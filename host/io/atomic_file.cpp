#include "host/io/atomic_file.h"

#include <signal.h>
#include <unistd.h>

#include <cerrno>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <mutex>
#include <set>
#include <stdexcept>

#include "host/io/output_set.h"

namespace ag2gs {

namespace fs = std::filesystem;

int remove_stale_temp_files(const std::string& dir) {
  int removed = 0;
  std::error_code ec;
  for (fs::directory_iterator it(dir.empty() ? "." : dir, ec), end; !ec && it != end; it.increment(ec)) {
    std::string name = it->path().filename().string();
    // Images are written as ".NAME.png.tmp.PID.png" (OpenCV picks the
    // encoder by the extension; the dot hides the file while it is written).
    if (name.size() > 5 && name[0] == '.' && name.compare(name.size() - 4, 4, ".png") == 0)
      name = name.substr(1, name.size() - 5);
    const size_t at = name.rfind(".tmp.");
    if (at == std::string::npos || at == 0 || at + 5 >= name.size()) continue;
    const std::string digits = name.substr(at + 5);
    if (digits.find_first_not_of("0123456789") != std::string::npos || digits.size() > 7) continue;  // pid_max
    // Only the kinds of file ag2gs writes: a user's own "x.tmp.1" stays.
    const std::string target = name.substr(0, at);
    const size_t dot = target.rfind('.');
    static const std::set<std::string> ours = {".ag2gs", ".ply", ".json", ".png", ".npy", ".bin", ".txt"};
    if (dot == std::string::npos || ours.count(target.substr(dot)) == 0) continue;
    const long pid = std::strtol(digits.c_str(), nullptr, 10);
    if (pid <= 0 || pid == static_cast<long>(::getpid())) continue;
    // kill(pid, 0) fails with ESRCH only when no such process exists.
    if (::kill(static_cast<pid_t>(pid), 0) == 0 || errno != ESRCH) continue;
    std::error_code rm;
    if (it->is_regular_file(rm) && fs::remove(it->path(), rm)) ++removed;
  }
  return removed;
}

void remove_stale_temp_files_once(const std::string& dir) {
  // Once per folder and process: a scan per file would cost O(files^2) for a
  // folder of renders.
  static std::mutex lock;
  static std::set<std::string> cleaned;
  std::lock_guard<std::mutex> hold(lock);
  if (cleaned.insert(dir).second) remove_stale_temp_files(dir);
}

AtomicFile::AtomicFile(std::string path) : path_(std::move(path)) {
  remove_stale_temp_files_once(fs::path(path_).parent_path().string());
  temp_ = path_ + ".tmp." + std::to_string(static_cast<long>(::getpid()));
  file_ = std::fopen(temp_.c_str(), "wb");
  if (!file_) {
    throw std::runtime_error(path_ + ": cannot create the temporary file '" + temp_ + "': " + std::strerror(errno) +
                             "; check that the directory exists and is writable");
  }
  created_ = true;
}

AtomicFile::~AtomicFile() {
  if (file_) std::fclose(file_);
  if (created_ && !committed_) std::remove(temp_.c_str());
}

void AtomicFile::fail(const std::string& what) {
  throw std::runtime_error(path_ + ": " + what + ": " + std::strerror(errno) +
                           "; the previous file, if any, is unchanged");
}

void AtomicFile::write(const void* data, size_t bytes) {
  if (!file_) throw std::logic_error("AtomicFile::write after commit");
  if (bytes > 0 && std::fwrite(data, 1, bytes, file_) != bytes) fail("writing '" + temp_ + "' failed (disk full?)");
}

void AtomicFile::commit() {
  if (!file_) throw std::logic_error("AtomicFile::commit twice");
  if (std::fflush(file_) != 0) fail("writing '" + temp_ + "' failed (disk full?)");
  ::fsync(::fileno(file_));  // the data must be on disk before the rename publishes it
  const int rc = std::fclose(file_);
  file_ = nullptr;
  if (rc != 0) fail("closing '" + temp_ + "' failed");
  // Part of a set replaced together (host/io/output_set.h): it moves with the others.
  if (OutputSet::defer(temp_, path_)) {
    committed_ = true;
    return;
  }
  if (std::rename(temp_.c_str(), path_.c_str()) != 0) fail("cannot move '" + temp_ + "' into place");
  committed_ = true;
}

}  // namespace ag2gs
