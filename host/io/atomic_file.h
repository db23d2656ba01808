// Writing a file so that a reader never sees it half written: the bytes go to
// "<path>.tmp.<pid>", which is flushed, synced and renamed over `path` only by
// commit(). Until then an existing `path` is untouched; a writer destroyed
// without commit() (an exception, a failed write) removes its temporary file,
// and never a path it did not create itself. Temporary files that dead
// processes left in the folder are removed before the first write there.
#pragma once

#include <cstddef>
#include <cstdio>
#include <string>

namespace ag2gs {

// Deletes "<name>.tmp.<pid>" files in `dir` whose process no longer runs
// (left by a kill -9 or a power cut during a write), for the kinds of file
// ag2gs writes (.ag2gs, .ply, .json, .png, .npy, .bin, .txt); returns how
// many.
// Temporary files of live processes are left alone. AtomicFile calls it
// once per folder and process, before its first write there.
int remove_stale_temp_files(const std::string& dir);
// The same, at most once per folder and process (what every writer of
// ag2gs's files calls before its first write into a folder).
void remove_stale_temp_files_once(const std::string& dir);

class AtomicFile {
 public:
  // Opens the temporary file; throws std::runtime_error naming `path` when it
  // cannot be created (missing folder, no permission).
  explicit AtomicFile(std::string path);
  ~AtomicFile();
  AtomicFile(const AtomicFile&) = delete;
  AtomicFile& operator=(const AtomicFile&) = delete;

  // Appends bytes; throws std::runtime_error (disk full, I/O error).
  void write(const void* data, size_t bytes);
  void write(const std::string& s) { write(s.data(), s.size()); }
  // Flushes, syncs, closes and renames into place; throws on failure.
  void commit();

  const std::string& path() const { return path_; }
  const std::string& temp_path() const { return temp_; }

 private:
  [[noreturn]] void fail(const std::string& what);

  std::string path_, temp_;
  std::FILE* file_ = nullptr;
  bool created_ = false, committed_ = false;
};

}  // namespace ag2gs
