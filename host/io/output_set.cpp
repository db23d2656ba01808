#include "host/io/output_set.h"

#include <signal.h>
#include <unistd.h>

#include <cerrno>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <nlohmann/json.hpp>
#include <stdexcept>

#include "host/io/atomic_file.h"
#include "host/io/json_input.h"

namespace ag2gs {

namespace fs = std::filesystem;

namespace {

std::mutex active_lock;
OutputSet* active = nullptr;
std::string active_dir;

fs::path normal(const std::string& p) {
  return fs::absolute(fs::path(p)).lexically_normal();
}

// `p` lies inside `dir` (both normalised).
bool inside(const fs::path& p, const fs::path& dir) {
  const fs::path rel = p.lexically_relative(dir);
  return !rel.empty() && *rel.begin() != "..";
}

bool process_gone(long pid) {
  return pid > 0 && ::kill(static_cast<pid_t>(pid), 0) != 0 && errno == ESRCH;
}

const std::string kJournalPrefix = ".ag2gs-commit.";

std::string journal_path(const std::string& dir, long pid) {
  return (fs::path(dir) / (kJournalPrefix + std::to_string(pid) + ".json")).string();
}

// Writes the journal durably: a temporary file, synced, renamed.
void write_journal(const std::string& path, const std::string& text) {
  const std::string tmp = path + ".tmp";
  std::FILE* f = std::fopen(tmp.c_str(), "wb");
  if (!f) throw std::runtime_error(path + ": cannot write the commit journal: " + std::strerror(errno));
  const bool ok =
      std::fwrite(text.data(), 1, text.size(), f) == text.size() && std::fflush(f) == 0 && ::fsync(::fileno(f)) == 0;
  if (std::fclose(f) != 0 || !ok || std::rename(tmp.c_str(), path.c_str()) != 0) {
    std::remove(tmp.c_str());
    throw std::runtime_error(path + ": cannot write the commit journal (disk full?); nothing was replaced");
  }
}

// Renames what the journal lists (those still waiting), then removes it.
void replay(const std::string& dir, const std::string& journal) {
  const nlohmann::json j = read_json_file(journal);
  // Only paths inside the folder: a planted journal must not move or delete
  // anything else.
  const fs::path root = normal(dir);
  auto within = [&](const nlohmann::json& entry) {
    const std::string rel = entry.is_string() ? entry.get<std::string>() : std::string();
    const fs::path p = (root / rel).lexically_normal();
    if (rel.empty() || fs::path(rel).is_absolute() || !inside(p, root))
      throw std::runtime_error(journal + ": lists '" + entry.dump() +
                               "', not a path inside its folder; it was not written by ag2gs: delete it");
    return p;
  };
  if (!j.is_object() || !j.contains("renames") || !j["renames"].is_array())
    throw std::runtime_error(journal + ": not a commit journal of ag2gs (no \"renames\" list): delete it");
  // Every entry checked before anything moves.
  std::vector<std::pair<fs::path, fs::path>> renames;
  for (const nlohmann::json& r : j["renames"]) {
    if (!r.is_array() || r.size() != 2)
      throw std::runtime_error(journal + ": not a commit journal of ag2gs (a rename is not a pair): delete it");
    renames.emplace_back(within(r[0]), within(r[1]));
  }
  std::vector<fs::path> removals;
  const nlohmann::json none = nlohmann::json::array();
  const nlohmann::json& listed = j.contains("removals") ? j["removals"] : none;
  if (!listed.is_array()) throw std::runtime_error(journal + ": \"removals\" is not a list; delete it");
  for (const nlohmann::json& r : listed) removals.push_back(within(r));
  for (const auto& [from, to] : renames) {
    std::error_code ec;
    if (!fs::exists(from, ec)) continue;  // renamed before the stop
    fs::rename(from, to, ec);
    if (ec)
      throw std::runtime_error(journal + ": cannot move " + from.string() + " into place: " + ec.message() +
                               "; nothing else was changed, run again to finish");
  }
  for (const fs::path& r : removals) {
    std::error_code ec;
    fs::remove(r, ec);
  }
  std::remove(journal.c_str());
}

}  // namespace

OutputSet::OutputSet(const std::string& dir) : dir_(normal(dir).string()) {
  std::lock_guard<std::mutex> hold(active_lock);
  if (active) throw std::logic_error("OutputSet: one set at a time");
  active = this;
  active_dir = dir_;
}

OutputSet::~OutputSet() {
  {
    std::lock_guard<std::mutex> hold(active_lock);
    if (active == this) active = nullptr;
  }
  if (committed_) return;
  std::lock_guard<std::mutex> hold(lock_);
  for (const auto& [temp, final_path] : renames_) std::remove(temp.c_str());
}

size_t OutputSet::size() const {
  std::lock_guard<std::mutex> hold(lock_);
  return renames_.size();
}

bool OutputSet::defer(const std::string& temp_path, const std::string& final_path) {
  std::lock_guard<std::mutex> hold(active_lock);
  if (!active || !inside(normal(final_path), fs::path(active_dir))) return false;
  std::lock_guard<std::mutex> hold_set(active->lock_);
  active->renames_.emplace_back(normal(temp_path).string(), normal(final_path).string());
  return true;
}

void OutputSet::remove_at_commit(const std::string& path) {
  std::lock_guard<std::mutex> hold(lock_);
  const fs::path p = normal(path);
  if (!inside(p, fs::path(dir_))) throw std::logic_error("OutputSet: " + path + " is outside " + dir_);
  removals_.push_back(p.string());
}

void OutputSet::commit() {
  {
    std::lock_guard<std::mutex> hold(active_lock);
    if (active == this) active = nullptr;  // later writes go straight to their files
  }
  std::lock_guard<std::mutex> hold(lock_);
  if (committed_) throw std::logic_error("OutputSet::commit twice");
  if (renames_.empty() && removals_.empty()) {
    committed_ = true;
    return;
  }
  nlohmann::json list = nlohmann::json::array();
  for (const auto& [temp, final_path] : renames_)
    list.push_back({fs::path(temp).lexically_relative(dir_).generic_string(),
                    fs::path(final_path).lexically_relative(dir_).generic_string()});
  nlohmann::json removals = nlohmann::json::array();
  for (const std::string& r : removals_) removals.push_back(fs::path(r).lexically_relative(dir_).generic_string());
  const std::string journal = journal_path(dir_, static_cast<long>(::getpid()));
  write_journal(journal, nlohmann::json{{"renames", list}, {"removals", removals}}.dump());
  committed_ = true;  // from here on the new set wins: the journal finishes it
  replay(dir_, journal);
}

int finish_interrupted_output_sets(const std::string& dir) {
  std::error_code ec;
  if (!fs::is_directory(dir, ec)) return 0;
  int finished = 0;
  std::vector<fs::path> journals;
  for (fs::directory_iterator it(dir, ec), end; !ec && it != end; it.increment(ec)) journals.push_back(it->path());
  for (const fs::path& path : journals) {
    const std::string name = path.filename().string();
    if (name.rfind(kJournalPrefix, 0) != 0) continue;
    const std::string rest = name.substr(kJournalPrefix.size());
    const size_t dot = rest.find('.');
    if (dot == std::string::npos) continue;
    const long pid = std::strtol(rest.substr(0, dot).c_str(), nullptr, 10);
    if (!process_gone(pid)) continue;
    if (rest.substr(dot) == ".json.tmp") {  // stopped while writing the journal: the old set stands
      fs::remove(path, ec);
      continue;
    }
    if (rest.substr(dot) != ".json") continue;
    replay(dir, path.string());
    ++finished;
  }
  remove_stale_temp_files(dir);
  for (fs::directory_iterator it(dir, ec), end; !ec && it != end; it.increment(ec)) {
    std::error_code sub;
    if (it->is_directory(sub) && !it->is_symlink(sub)) remove_stale_temp_files(it->path().string());
  }
  return finished;
}

}  // namespace ag2gs
