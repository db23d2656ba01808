// Wall-clock helpers for the timings the program reports.
#pragma once

#include <chrono>

namespace ag2gs {

// Milliseconds from t0 to now on the steady clock.
inline double ms_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
}

}  // namespace ag2gs
