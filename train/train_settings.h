// Every training setting declared once (TrainConfig, train/train_config.h):
// its field, its key in the JSON that model.ag2gs and checkpoints carry, its
// `ag2gs train` flag and help, the range it must lie in, the value a file
// written before it existed means, its value in each preset, and (for the
// few settings whose default is a rule) the value the rule gives, which is
// what the JSON records. TrainConfig's to_json, from_json, validate and
// preset, and the program's flags, --help and --preset, all loop over this
// table. The default of each field is its initialiser in TrainConfig.
#pragma once

#include <functional>
#include <optional>
#include <string>
#include <vector>

#include "host/core/settings.h"

namespace ag2gs {

struct TrainConfig;

// A training setting's row (host/core/settings.h); the training settings
// alone have presets (in_default, in_paper) and values for files written
// before them (before_value).
using TrainSetting = Setting<TrainConfig>;

// The table, in --help's order.
const std::vector<TrainSetting>& train_settings();

// The value preset `preset` gives the setting (none: TrainConfig's
// initialiser, which the preset keeps). Throws for an unknown preset.
std::optional<double> train_preset_value(const TrainSetting& s, const std::string& preset);

// The presets TrainConfig::preset accepts: "default" (also called
// "appearance") and "paper". Throws std::invalid_argument for another name.
void check_train_preset(const std::string& name);
// Sets every setting that a preset names to its value in preset `name`
// (TrainConfig's initialiser where that preset does not name it), except
// those for which keep(setting) is true (the program: flags given on the
// command line).
void apply_train_preset(TrainConfig& c, const std::string& name,
                        const std::function<bool(const TrainSetting&)>& keep = nullptr);

}  // namespace ag2gs
