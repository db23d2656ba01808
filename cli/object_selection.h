// What the commands that act on one selected object (remove, simulate)
// share: the selection, by a query exactly as `ag2gs query` makes it or from
// its selection.json, and the new output folder they write.
#pragma once

#include <cstdint>
#include <filesystem>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "cli/commands.h"

namespace ag2gs::cli {

// OUT_DIR as an absolute, normalised path ("out/", "out/." and "out" are one
// folder). Refused (std::invalid_argument, nothing written) when it is the
// model folder or inside it, or exists and is not empty.
std::filesystem::path check_new_output_folder(const std::string& out, const std::string& model_dir);

// The anchors listed in a `query` selection.json; throws naming the file
// when it cannot be read or lists an id outside the model's `anchors`.
std::vector<int32_t> read_selection_file(const std::string& path, size_t anchors);

// Either --selection FILE or a click / text query, with nothing of the
// other kind; throws std::invalid_argument naming the flags.
void check_selection_request(const QueryRequest& request, const std::string& selection_file);

struct SelectedObject {
  std::vector<uint8_t> anchors;  // [A] 1 = selected
  size_t count = 0;              // selected anchors
  double query_ms = 0;
};
// The selected anchors (report["query"] etc. record how); refuses an empty
// selection, saying that there is nothing to `action`.
SelectedObject select_object(Runtime& rt, const TrainedModel& tm, const Scene& scene, const QueryRequest& request,
                             const std::string& selection_file, const QueryConfig& config,
                             const std::vector<float>& embedding, int resolution, nlohmann::json& report,
                             const std::string& action);

}  // namespace ag2gs::cli
