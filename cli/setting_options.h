// A config's flags from its settings table (host/core/settings.h): each row
// with a flag becomes a CLI11 option bound to its field of `c`, checked as
// the row says, with the row's help. `train` and `baseline` register their
// settings this way.
#pragma once

#include <CLI/CLI.hpp>
#include <limits>
#include <stdexcept>
#include <string>
#include <type_traits>
#include <variant>
#include <vector>

#include "cli/commands.h"
#include "host/core/settings.h"

namespace ag2gs::cli {

// The type a row's flag reads: the field's, or text for a Custom row.
template <class F>
struct SettingValue {
  using type = std::string;
};
template <class T, class Config>
struct SettingValue<T& (*)(Config&)> {
  using type = T;
};

template <class Config>
void add_setting_option(CLI::App* sub, const Setting<Config>& s, Config& c) {
  using Check = typename Setting<Config>::Check;
  using Custom = typename Setting<Config>::Custom;
  std::visit(
      [&](auto field) {
        CLI::Option* o = nullptr;
        using T = typename SettingValue<decltype(field)>::type;
        if constexpr (std::is_same_v<decltype(field), Custom>) {
          // The flag's text goes through the row's parser when CLI11 reads it.
          o = sub->add_option_function<std::string>(
              s.flag,
              [&c, parse = field.parse, name = s.flag_name()](const std::string& text) {
                try {
                  parse(c, text);
                } catch (const std::invalid_argument& e) {
                  // CLI11 prints it and exits non-zero; the message names the flag.
                  const std::string what = e.what();
                  throw what.find(name) == std::string::npos ? CLI::ValidationError(name, what)
                                                             : CLI::ValidationError(what);
                }
              },
              s.help);
          if (!s.choices.empty()) o->check(CLI::IsMember(s.choices));
          if (!s.type_name.empty()) o->type_name(s.type_name);
        } else {
          auto& ref = field(c);
          if constexpr (std::is_same_v<T, bool>) {
            if (!s.takes_value) {
              sub->add_flag(s.flag, ref, s.help);
              return;
            }
          }
          o = sub->add_option(s.flag, ref, s.help);
        }
        switch (s.check) {
          case Check::kRange:
            if constexpr (std::is_integral_v<T> && !std::is_same_v<T, bool>) {
              const T hi = s.hi >= static_cast<double>(std::numeric_limits<T>::max()) ? std::numeric_limits<T>::max()
                                                                                      : static_cast<T>(s.hi);
              o->check(CLI::Range(static_cast<T>(s.lo), hi));
            } else {
              o->check(finite_range(s.lo, s.hi));
            }
            break;
          case Check::kNonNegative:
            o->check(non_negative_number());
            break;
          case Check::kPositive:
            o->check(positive_number());
            break;
          case Check::kSeed:
            o->check(seed_number());
            break;
          case Check::kNone:
            break;
        }
      },
      s.field);
}

// Every row of `table` that has a flag, in the table's order.
template <class Config>
void add_setting_options(CLI::App* sub, const std::vector<Setting<Config>>& table, Config& c) {
  for (const Setting<Config>& s : table)
    if (s.is_flag()) add_setting_option(sub, s, c);
}

}  // namespace ag2gs::cli
