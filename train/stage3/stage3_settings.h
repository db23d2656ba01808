// The stage-3 settings `ag2gs train` takes (Stage3Config, train/stage3/
// language.h) declared once, as the training settings are (host/core/
// settings.h): field, key in the run record a checkpoint keeps ("stage3"),
// flag, help and range. train's flags, the run record and a resumed run's
// adoption of it loop over this table.
#pragma once

#include <nlohmann/json.hpp>
#include <vector>

#include "host/core/settings.h"

namespace ag2gs {

struct Stage3Config;
using Stage3Setting = Setting<Stage3Config>;

// The table, in --help's order.
const std::vector<Stage3Setting>& stage3_settings();

// The settings as the run record holds them; and the inverse, for the keys
// `j` has (a record from before a setting keeps its default).
nlohmann::json stage3_to_json(const Stage3Config& c);
void stage3_from_json(const nlohmann::json& j, Stage3Config& c);

}  // namespace ag2gs
