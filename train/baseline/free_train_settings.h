// Every setting of the baseline (FreeTrainConfig, train/baseline/free_trainer.h)
// declared once, as the training settings are (host/core/settings.h): its
// field, its key in the `config` that metrics.json records, its `ag2gs
// baseline` flag and help, and the range it must lie in. FreeTrainConfig's
// to_json and validate, and the program's flags and --help, loop over this
// table; the default of each field is its initialiser.
#pragma once

#include <vector>

#include "host/core/settings.h"

namespace ag2gs {

struct FreeTrainConfig;
using FreeTrainSetting = Setting<FreeTrainConfig>;

// The table, in --help's order.
const std::vector<FreeTrainSetting>& free_train_settings();

}  // namespace ag2gs
