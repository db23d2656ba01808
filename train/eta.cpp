#include "train/eta.h"

#include <algorithm>
#include <cmath>

namespace ag2gs {

double growth_end_geometric(size_t now, size_t start, int rounds_done, int rounds_left, size_t budget) {
  double end = static_cast<double>(now);
  if (rounds_done > 0 && rounds_left > 0 && start > 0 && now > start) {
    const double factor = std::pow(static_cast<double>(now) / static_cast<double>(start), 1.0 / rounds_done);
    end *= std::pow(factor, std::min(rounds_left, 1000));
  }
  if (budget > 0) end = std::min(end, std::max(static_cast<double>(budget), static_cast<double>(now)));
  return end;
}

double growth_end_tapering(size_t now, size_t last_added, int rounds_left) {
  return static_cast<double>(now) + static_cast<double>(last_added) * std::max(rounds_left, 0) / 2.0;
}

double estimate_seconds_left(int remaining, double step_ms, size_t gaussians, int growing, double end_count) {
  if (remaining <= 0 || !(step_ms > 0) || gaussians == 0) return 0;
  const double now = static_cast<double>(gaussians);
  const double ratio_end = std::isfinite(end_count) ? std::max(end_count, now) / now : 1.0;
  growing = std::clamp(growing, 0, remaining);
  const double weighted = growing * 0.5 * (1 + ratio_end) + (remaining - growing) * ratio_end;
  return weighted * step_ms / 1000;
}

}  // namespace ag2gs
