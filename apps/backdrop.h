// What the applications (removal, simulation) start from: an object selected
// in a trained model, and what lies behind the model's Gaussians in its
// renders: its learned sky when it has one, else the training background
// (black, or white with --white-bg), as training rendered them. They render
// the changed scene over it, so that their pictures match the model's.
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "host/core/gaussians.h"
#include "host/device/cl_runtime.h"
#include "host/io/model_io.h"
#include "host/render/sky.h"
#include "host/scene/scene.h"
#include "train/anchors/anchor_model.h"
#include "train/train_config.h"

namespace ag2gs {

// A trained model, the scene it was trained on and an object selected in it.
struct ObjectInModel {
  std::string model_file;                 // MODEL_DIR/model.ag2gs, for messages
  const ModelArchive* archive = nullptr;  // the model's archive (its sky and training record)
  const AnchorModel* model = nullptr;
  int sh_degree = 0;              // the SH degree training reached
  Scene* scene = nullptr;         // at the resolution the application renders at
  std::vector<uint8_t> selected;  // [anchors]: 1 = the object's

  // Throws std::invalid_argument naming `who` when a pointer is missing or
  // the selection is not one entry per anchor.
  void check(const std::string& who) const;
};

struct ModelBackdrop {
  TrainConfig train;  // the config the archive records (defaults when it records none or an unreadable one)
  Sky sky;            // enabled() when the model has a sky
  std::optional<std::vector<float>> sky_coefficients;
  RenderSettings settings;  // background as training had it (black under a sky)

  // `name` names the model in the warning about an unreadable config, which
  // says `without_config` happens instead (e.g. "the fine-tune uses the
  // default rates").
  ModelBackdrop(Runtime& rt, const ModelArchive& archive, const std::string& name, const std::string& without_config);
};

}  // namespace ag2gs
