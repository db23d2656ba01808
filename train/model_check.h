// One verdict on a model file before any command uses it: every section the
// file holds is checked, whether or not the command reads it, so `info`,
// `render`, `query`, `remove`, `simulate`, `eval`, the viewer and stage 3
// accept and refuse the same files (a damaged graph passed `render` and
// `query`, which do not read it, while `info` refused it).
#pragma once

#include <nlohmann/json.hpp>
#include <string>

#include "host/io/model_io.h"
#include "train/anchors/anchor_model.h"

namespace ag2gs {

// Throws std::runtime_error naming archive.source and what is wrong: the
// anchors (finite parameters, cells, the recorded count), the stage-2 graph
// (its CSR rows and ids), the stage-3 clusters and language features (ids,
// sizes, finite features), the sky (finite coefficients of a degree 0..3)
// and the training record (resolution, SH degree). Returns the anchors it
// read, so a caller need not read them again.
AnchorModel check_model_archive(const ModelArchive& archive);

// What a model file (or metrics.json) records of its training, checked: the
// -r it was trained at (1 when not recorded) and the SH degree it reached
// (at most the model's). A value out of range or of another type throws
// std::runtime_error naming `file` and the flag that replaces it.
int recorded_resolution(const nlohmann::json& record, const std::string& file);
int recorded_sh_degree(const nlohmann::json& train, int model_degree, const std::string& file);

}  // namespace ag2gs
