// Every training setting declared once (TrainConfig, train/train_config.h):
// its field, its key in the JSON that model.ag2gs and checkpoints carry, its
// `ag2gs train` flag and help, the range it must lie in, the value a file
// written before it existed means, its value in each preset, and (for the
// few settings whose default is a rule) the value the rule gives, which is
// what the JSON records. TrainConfig's to_json, from_json, validate and
// preset, and the program's flags, --help and --preset, all loop over this
// table. The default of each field is its initialiser in TrainConfig.
#pragma once

#include <cstdint>
#include <functional>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <variant>
#include <vector>

namespace ag2gs {

struct TrainConfig;

struct TrainSetting {
  // The field, as an accessor of its type.
  template <class T>
  using Field = T& (*)(TrainConfig&);
  using Access = std::variant<Field<int>, Field<int64_t>, Field<uint64_t>, Field<float>, Field<double>, Field<bool>>;
  // How a value is checked, by validate() and by the flag's parser.
  enum class Check {
    kNone,         // booleans, and the settings without a flag
    kRange,        // lo <= v <= hi (a whole number for integer fields)
    kNonNegative,  // a finite number >= 0
    kPositive,     // a finite number > 0
    kSeed,         // 0 to 2^64 - 1, in digits
  };

  Access field;
  std::string key;   // JSON path: "iterations", "grow.min_seen", "anchors.children"
  std::string flag;  // the flag's CLI11 names ("--grow-min-seen", "!--no-feature-ball",
                     // "--mask-geometry,!--mask-features-only"); empty: no flag
  std::string help;  // --help's text
  Check check = Check::kNone;
  double lo = 0, hi = 0;  // kRange
  // The value that means "from the scene / the iterations" where the flag
  // itself does not take it (0 top cells, -1 Gaussians): validate() accepts
  // it besides the checked range.
  std::optional<double> auto_value;
  // The value a file without the key means (written before the setting
  // existed); none: the key is required.
  std::optional<double> before_value;
  // The value in the presets ("default" = "appearance", and "paper"); none:
  // the preset keeps TrainConfig's initialiser.
  std::optional<double> in_default, in_paper;
  // For a default that is a rule (0 or -1 = "from the iterations"): the
  // value the rule gives, which to_json records; null: the field itself.
  int (*effective_value)(const TrainConfig&) = nullptr;
  bool takes_value = true;  // false for a boolean switch (--white-bg), true for --far-shell true|false

  // Table-building steps.
  TrainSetting& range(double l, double h) { return check = Check::kRange, lo = l, hi = h, *this; }
  TrainSetting& non_negative() { return check = Check::kNonNegative, *this; }
  TrainSetting& positive() { return check = Check::kPositive, *this; }
  TrainSetting& seed() { return check = Check::kSeed, *this; }
  TrainSetting& automatic(double v) { return auto_value = v, *this; }
  TrainSetting& before(double v) { return before_value = v, *this; }
  TrainSetting& presets(std::optional<double> d, std::optional<double> paper) {
    return in_default = d, in_paper = paper, *this;
  }
  TrainSetting& effective(int (*f)(const TrainConfig&)) { return effective_value = f, *this; }
  TrainSetting& with_value() { return takes_value = true, *this; }

  bool is_flag() const { return !flag.empty(); }
  bool in_a_preset() const { return in_default.has_value() || in_paper.has_value(); }
  bool is_bool() const { return std::holds_alternative<Field<bool>>(field); }
  // The key as a JSON pointer ("grow.min_seen" -> /grow/min_seen).
  nlohmann::json::json_pointer pointer() const;
  // The flag's first name ("--mask-geometry" of "--mask-geometry,!--mask-features-only",
  // "--no-feature-ball" of "!--no-feature-ball"); for a switch with two
  // names, name_for(v) is the one that sets v.
  std::string flag_name() const;
  std::string name_for(bool v) const;

  // The field's value as JSON, in its own type (to_json records
  // effective_value where there is one).
  nlohmann::json get(const TrainConfig& c) const;
  nlohmann::json recorded(const TrainConfig& c) const;
  // Sets the field from JSON (throws nlohmann's exceptions for a mistyped
  // value) or from a number (a preset's or a missing key's value).
  void set(TrainConfig& c, const nlohmann::json& v) const;
  void assign(TrainConfig& c, double v) const;
  // Empty when the field's value passes `check`, else what is wrong, naming
  // the flag ("grow_min_seen (--grow-min-seen) is 1.5; it must lie in [0, 1]").
  std::string problem(const TrainConfig& c) const;
  // The value the named preset gives the field (TrainConfig's initialiser
  // when the preset does not name it).
  std::optional<double> preset_value(const std::string& preset) const;
};

// The table, in --help's order.
const std::vector<TrainSetting>& train_settings();

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
