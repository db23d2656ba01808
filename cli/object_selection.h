// What the commands that act on one selected object (remove, simulate)
// share: the selection, by a query exactly as `ag2gs query` makes it or from
// its selection.json, and the new output folder they write.
#pragma once

#include <cstdint>
#include <filesystem>
#include <memory>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "apps/backdrop.h"
#include "cli/commands.h"

namespace ag2gs::cli {

// OUT_DIR as an absolute, normalised path ("out/", "out/." and "out" are one
// folder). Refused (std::invalid_argument, nothing written) when it is the
// model folder or inside it, or exists and is not empty.
std::filesystem::path check_new_output_folder(const std::string& out, const std::string& model_dir);

// A new output folder built beside OUT_DIR as OUT_DIR.partial.<pid> and
// renamed into place only when complete. Whatever stops the command first
// (an exception, or Ctrl-C / SIGTERM seen by stop_if_interrupted) leaves
// neither folder behind. Needs an InterruptGuard alive around it.
class StagedFolder {
 public:
  // `out`: check_new_output_folder's path; `out_arg`: -o as given (messages).
  StagedFolder(const std::filesystem::path& out, const std::string& out_arg);
  ~StagedFolder();  // removes the partial folder unless committed
  StagedFolder(const StagedFolder&) = delete;
  StagedFolder& operator=(const StagedFolder&) = delete;

  const std::filesystem::path& path() const { return tmp_; }
  // After a signal: removes the partial folder, says that nothing was
  // written and exits with the signal's status.
  void stop_if_interrupted(const std::string& during);
  // Checks for a signal once more, then puts the folder in place of OUT_DIR
  // (nothing, or the empty folder check_new_output_folder allowed).
  void commit();

 private:
  std::filesystem::path out_, tmp_;
  std::string out_arg_;
  bool committed_ = false;
};

// The anchors listed in a `query` selection.json; throws naming the file
// when it cannot be read, lists an id outside the model's anchors, or
// carries the fingerprint of another model (files without one are read).
std::vector<int32_t> read_selection_file(const std::string& path, const AnchorModel& model);

// Either --selection FILE or a click / text query, with nothing of the
// other kind; throws std::invalid_argument naming the flags.
void check_selection_request(const QueryRequest& request, const std::string& selection_file);

struct SelectedObject {
  std::vector<uint8_t> anchors;  // [A] 1 = selected
  size_t count = 0;              // selected anchors
  double query_ms = 0;
};

// The arguments remove and simulate share, and their options: the model
// folder, --scene, -o, the object (a click, a phrase or --selection), -r and
// --sparse, and the query's settings. `verb` ("Remove", "Simulate") starts
// --selection's help; `out_help` is -o's.
struct ObjectArgs {
  QueryRequest request;
  QueryConfig config;
  std::string model, scene, selection, out, sparse;
  int resolution = 0;  // 0: the model's training -r
};
void add_object_options(CLI::App* cmd, ObjectArgs& a, const std::string& verb, const std::string& out_help);

// What remove and simulate open before selecting: the model (with stage 3's
// clusters and language features for a text query), the scene it was
// trained on at -r `resolution` (0: the model's training -r, and `resolution`
// is set to it) with the model's train/test split, and a text query's
// embedding. Each refusal names the file or flag and the fix.
struct OpenedModel {
  TrainedModel tm;
  std::unique_ptr<Scene> scene;
  std::vector<float> embedding;  // a text query's (not by a selection file)
};
OpenedModel open_model_and_scene(const std::string& model_dir, const std::string& scene_dir, int& resolution,
                                 const std::string& sparse, const QueryRequest& request,
                                 const std::string& selection_file);
// The anchors `a` selects in `opened` (a query, or --selection's file).
// `report` records the model, the scene, the resolution and how the anchors
// were selected ("query"); an empty selection is refused, saying that there
// is nothing to `action`.
SelectedObject select_object(Runtime& rt, const OpenedModel& opened, const ObjectArgs& a, nlohmann::json& report,
                             const std::string& action);
// The model, its scene and the selection as the applications take them
// (apps/backdrop.h); `opened` must outlive the result.
ObjectInModel object_in_model(const OpenedModel& opened, const SelectedObject& sel);

}  // namespace ag2gs::cli
