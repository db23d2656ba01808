// What lies behind a trained model's Gaussians in its renders: its learned
// sky when it has one, else the training background (black, or white with
// --white-bg), as training rendered them. Removal and simulation render the
// changed scene over it, so that their pictures match the model's.
#pragma once

#include <optional>
#include <string>
#include <vector>

#include "host/core/gaussians.h"
#include "host/device/cl_runtime.h"
#include "host/io/model_io.h"
#include "host/render/sky.h"
#include "stages/train_config.h"

namespace ag2gs {

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
