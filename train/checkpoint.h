// Checkpoints: MODEL_DIR/checkpoint.ag2gs holds a trainer's model, every
// optimiser group's moments and step count (train/param_groups.h), the
// growth statistics, the iteration, the config and a fingerprint of the
// scene. A resumed run compares the fingerprint and the config with its own
// and names every field that differs (config_differences). Trainer's
// save_checkpoint, resume and save are in train/checkpoint.cpp.
#pragma once

#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "host/scene/scene.h"

namespace ag2gs {

// The leaves ("a.b.c") where two JSON objects differ, as "key (a vs b)".
std::vector<std::string> config_differences(const nlohmann::json& a, const nlohmann::json& b);

// A fingerprint of what a trainer reads from the scene: view names, cameras
// at the loaded resolution, split, SfM points (`train_views`: the number of
// training views).
nlohmann::json scene_fingerprint(const Scene& scene, size_t train_views);

// Creates `dir` if needed and checks that a file can be written in it;
// throws std::runtime_error naming the directory otherwise. The trainer's
// caller runs this before training so a long run cannot fail at the end.
void check_model_dir_writable(const std::string& dir);

// A JSON document written atomically (host/io/atomic_file.h).
void write_json_atomic(const std::string& path, const nlohmann::json& doc);

}  // namespace ag2gs
