// One row per setting of a config struct: the field, its key in the
// config's JSON, its command-line flag and help, the range it must lie in,
// and what the JSON records for a default that is a rule. A config's
// to_json, validate and (for the program) flags and --help loop over its
// table, so a setting is declared once: its default is the field's
// initialiser, everything else is its row. The training settings
// (train/train_settings.h) add the value a file written before a setting
// existed means and each preset's value; the baseline's are in
// train/baseline/free_train_settings.h. The program binds the rows to
// CLI11 options in cli/setting_options.h.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <type_traits>
#include <variant>
#include <vector>

namespace ag2gs {

template <class Config>
struct Setting {
  // The field, as an accessor of its type.
  template <class T>
  using Field = T& (*)(Config&);
  // A setting that is not one number or switch: a name (an enum, or a bool
  // spelled as two words), a vector, a pair, a value that may be unset. The
  // JSON holds what get() returns; set() takes it back; the flag's text goes
  // through parse(). set() and parse() throw std::invalid_argument naming
  // the flag for a value they refuse.
  struct Custom {
    nlohmann::json (*get)(const Config&);
    void (*set)(Config&, const nlohmann::json&);
    void (*parse)(Config&, const std::string&);
  };
  using Access =
      std::variant<Field<int>, Field<int64_t>, Field<uint64_t>, Field<float>, Field<double>, Field<bool>, Custom>;
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
  // the preset keeps the config's initialiser. Only the training settings
  // have presets.
  std::optional<double> in_default, in_paper;
  // For a default that is a rule (0 or -1 = "from the iterations"): the
  // value the rule gives, which to_json records; null: the field itself.
  int (*effective_value)(const Config&) = nullptr;
  bool takes_value = true;  // false for a boolean switch (--white-bg), true for --far-shell true|false
  // A Custom row's flag: the names it accepts (--help lists them), and the
  // type --help shows ("TEXT" when empty).
  std::vector<std::string> choices;
  std::string type_name;

  // Table-building steps.
  Setting& range(double l, double h) { return check = Check::kRange, lo = l, hi = h, *this; }
  Setting& non_negative() { return check = Check::kNonNegative, *this; }
  Setting& positive() { return check = Check::kPositive, *this; }
  Setting& seed() { return check = Check::kSeed, *this; }
  Setting& automatic(double v) { return auto_value = v, *this; }
  Setting& before(double v) { return before_value = v, *this; }
  Setting& presets(std::optional<double> d, std::optional<double> paper) {
    return in_default = d, in_paper = paper, *this;
  }
  Setting& effective(int (*f)(const Config&)) { return effective_value = f, *this; }
  Setting& with_value() { return takes_value = true, *this; }
  Setting& one_of(std::vector<std::string> names) { return choices = std::move(names), *this; }
  Setting& shown_as(std::string type) { return type_name = std::move(type), *this; }

  // A row's field from a lambda: Setting::of<float>([](C& c) -> float& { return c.x; }).
  template <class T>
  static Field<T> of(Field<T> f) {
    return f;
  }

  bool is_flag() const { return !flag.empty(); }
  bool in_a_preset() const { return in_default.has_value() || in_paper.has_value(); }
  bool is_bool() const { return std::holds_alternative<Field<bool>>(field); }

  // The key as a JSON pointer ("grow.min_seen" -> /grow/min_seen).
  nlohmann::json::json_pointer pointer() const {
    std::string p = "/" + key;
    std::replace(p.begin(), p.end(), '.', '/');
    return nlohmann::json::json_pointer(p);
  }
  // The flag's first name ("--mask-geometry" of "--mask-geometry,!--mask-features-only",
  // "--no-feature-ball" of "!--no-feature-ball").
  std::string flag_name() const {
    std::string first = flag.substr(0, flag.find(','));
    if (!first.empty() && first[0] == '!') first.erase(0, 1);
    return first;
  }
  // For a switch with two names, the one that sets v ("" when none does).
  std::string name_for(bool v) const {
    const size_t comma = flag.find(',');
    const std::string a = flag.substr(0, comma), b = comma == std::string::npos ? "" : flag.substr(comma + 1);
    for (const std::string& n : {a, b})
      if (!n.empty() && (n[0] == '!') != v) return n[0] == '!' ? n.substr(1) : n;
    return "";
  }

  // The field's value as JSON, in its own type.
  nlohmann::json get(const Config& c) const {
    Config& m = const_cast<Config&>(c);  // the accessors only read here
    return std::visit(
        [&m](auto f) {
          if constexpr (std::is_same_v<decltype(f), Custom>)
            return f.get(m);
          else
            return nlohmann::json(f(m));
        },
        field);
  }
  // What to_json records: effective_value where there is one.
  nlohmann::json recorded(const Config& c) const {
    return effective_value ? nlohmann::json(effective_value(c)) : get(c);
  }
  // Sets the field from JSON (throws nlohmann's exceptions for a mistyped
  // value) or from a number (a preset's or a missing key's value).
  void set(Config& c, const nlohmann::json& v) const {
    std::visit(
        [&](auto f) {
          if constexpr (std::is_same_v<decltype(f), Custom>) {
            f.set(c, v);
          } else {
            using T = std::decay_t<decltype(f(c))>;
            f(c) = v.get<T>();
          }
        },
        field);
  }
  void assign(Config& c, double v) const {
    std::visit(
        [&](auto f) {
          if constexpr (std::is_same_v<decltype(f), Custom>) {
            f.set(c, nlohmann::json(v));
          } else {
            using T = std::decay_t<decltype(f(c))>;
            if constexpr (std::is_same_v<T, bool>)
              f(c) = v != 0;
            else
              f(c) = static_cast<T>(v);
          }
        },
        field);
  }

  // Empty when the field's value passes `check`, else what is wrong, naming
  // the flag ("grow_min_seen (--grow-min-seen) is 1.5; it must lie in [0, 1]").
  std::string problem(const Config& c) const {
    if (check == Check::kNone || check == Check::kSeed) return {};  // every uint64 is a seed
    const nlohmann::json j = get(c);
    if (!j.is_number()) return {};  // a Custom row's name, vector or unset value: its set() checks it
    const double v = j.get<double>();
    if (auto_value && v == *auto_value) return {};
    const std::string name = key + (is_flag() ? " (" + flag_name() + ")" : "");
    const std::string is = name + " is " + j.dump();
    if (!std::isfinite(v)) return is + "; it must be a finite number";
    switch (check) {
      case Check::kRange: {
        // A float field holds the bounds as floats too (0.999 is stored as
        // 0.99900001f, which the flag's own check accepted).
        double l = lo, h = hi;
        if (std::holds_alternative<Field<float>>(field)) l = static_cast<float>(lo), h = static_cast<float>(hi);
        if (!(v >= l && v <= h)) return is + "; it must lie in [" + text(lo) + ", " + text(hi) + "]";
        break;
      }
      case Check::kNonNegative:
        if (!(v >= 0)) return is + "; it must be >= 0";
        break;
      case Check::kPositive:
        if (!(v > 0))
          return is + "; it must be > 0" + (auto_value ? " (or " + text(*auto_value) + ": from the scene)" : "");
        break;
      default:
        break;
    }
    return {};
  }

  static std::string text(double v) {
    char buf[32];
    std::snprintf(buf, sizeof buf, "%.9g", v);
    return buf;
  }
};

// Builds a table: add(field<int>(...), key, flag, help).range(...) appends a row.
template <class Config>
struct SettingRows {
  std::vector<Setting<Config>> t;
  Setting<Config>& operator()(typename Setting<Config>::Access f, const char* key, const char* flag, const char* help) {
    Setting<Config> s;
    s.field = f;
    s.key = key;
    s.flag = flag;
    s.help = help;
    s.takes_value = !std::holds_alternative<typename Setting<Config>::template Field<bool>>(f);
    t.push_back(s);
    return t.back();
  }
};

// Every row's recorded value at its key.
template <class Config>
nlohmann::json settings_to_json(const std::vector<Setting<Config>>& table, const Config& c) {
  nlohmann::json j = nlohmann::json::object();
  for (const Setting<Config>& s : table) j[s.pointer()] = s.recorded(c);
  return j;
}

// The first row's problem (Setting::problem), or "" when every value passes.
template <class Config>
std::string settings_problem(const std::vector<Setting<Config>>& table, const Config& c) {
  for (const Setting<Config>& s : table)
    if (std::string p = s.problem(c); !p.empty()) return p;
  return {};
}

}  // namespace ag2gs
