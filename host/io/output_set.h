// Files that replace earlier results together: while an OutputSet is alive,
// every AtomicFile and image written under its folder stays in its temporary
// file instead of being renamed into place, and commit() puts them all in
// place at the end. A run stopped before commit() (an exception, Ctrl-C,
// kill -9) leaves every earlier file as it was; one stopped during commit()
// leaves a journal that the next run into the folder completes
// (finish_interrupted_output_sets), so the folder holds either the old set
// or the new one, never a mix.
//
// The journal, "<dir>/.ag2gs-commit.<pid>.json", is written (to a temporary
// file, synced and renamed) only once every new file is complete on disk:
// {"renames": [[temporary, final], ...], "removals": [...]}, paths relative
// to <dir>.
#pragma once

#include <mutex>
#include <string>
#include <utility>
#include <vector>

namespace ag2gs {

class OutputSet {
 public:
  // Makes this the set that writes under `dir` defer to (one at a time).
  explicit OutputSet(const std::string& dir);
  // Without commit(): removes the new files' temporary copies.
  ~OutputSet();
  OutputSet(const OutputSet&) = delete;
  OutputSet& operator=(const OutputSet&) = delete;

  // Puts every new file in place; throws std::runtime_error when a rename
  // fails (the journal stays, and the next run finishes it).
  void commit();
  size_t size() const;
  // An earlier result that the new set does not replace but makes stale (a
  // mask of a view the new selection was not drawn in): deleted by commit().
  void remove_at_commit(const std::string& path);

  // For writers: when a set is alive and `final_path` lies under its folder,
  // records the completed temporary file and returns true (the caller leaves
  // it where it is); false otherwise (the caller renames it itself).
  static bool defer(const std::string& temp_path, const std::string& final_path);

 private:
  std::string dir_;
  mutable std::mutex lock_;
  std::vector<std::pair<std::string, std::string>> renames_;  // absolute paths
  std::vector<std::string> removals_;
  bool committed_ = false;
};

// Completes the commits that processes no longer running left in `dir` (their
// journals), then removes the temporary files of dead processes in `dir` and
// its subfolders one level down (those of a set stopped before its commit).
// Returns how many journals were completed. Run before writing into `dir`.
int finish_interrupted_output_sets(const std::string& dir);

}  // namespace ag2gs
