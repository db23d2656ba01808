// A config's flags from its settings table (host/core/settings.h): each row
// with a flag becomes a CLI11 option bound to its field of `c`, checked as
// the row says, with the row's help. `train` and `baseline` register their
// settings this way.
#pragma once

#include <CLI/CLI.hpp>
#include <limits>
#include <type_traits>
#include <variant>
#include <vector>

#include "cli/commands.h"
#include "host/core/settings.h"

namespace ag2gs::cli {

template <class Config>
void add_setting_option(CLI::App* sub, const Setting<Config>& s, Config& c) {
  using Check = typename Setting<Config>::Check;
  std::visit(
      [&](auto field) {
        auto& ref = field(c);
        using T = std::decay_t<decltype(ref)>;
        if constexpr (std::is_same_v<T, bool>) {
          if (!s.takes_value) {
            sub->add_flag(s.flag, ref, s.help);
            return;
          }
        }
        CLI::Option* o = sub->add_option(s.flag, ref, s.help);
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
