// The q-quantile of a sample by selection: element floor(q n) (the last for
// q = 1) of the sorted values, NaN for an empty sample. One definition for
// every robust statistic the host takes (medians, 90th percentiles).
#pragma once

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <vector>

namespace ag2gs {

// The rank that definition picks in a sample of n > 0 values.
inline size_t quantile_rank(size_t n, double q) {
  return std::min(n - 1, static_cast<size_t>(q * static_cast<double>(n)));
}

inline double quantile(std::vector<double> v, double q) {
  if (v.empty()) return NAN;
  const size_t k = quantile_rank(v.size(), q);
  std::nth_element(v.begin(), v.begin() + static_cast<std::ptrdiff_t>(k), v.end());
  return v[k];
}

}  // namespace ag2gs
