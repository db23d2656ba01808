// Double-precision reference of the anchor growth statistics
// (train/densify/anchor_growth.h, kernels/anchor_growth.cl), written from
// their definition, one view at a time. Per child g visible in the view
// (radii[g] > 0):
//   grad_sum[g]  += |(gx sx, gy sy)|, the norm in double of the float
//                   gradient scaled by (W/2, H/2) with ndc, (1, 1) without;
//                   a non-finite norm, or |gy sy| >= 1e29 (a float product
//                   that overflows to inf on the device), adds nothing
//   count[g]     += 1, finite or not
//   last_seen[g]  = the view's step (1, 2, ...)
#pragma once

#include <cstddef>
#include <vector>

namespace ag2gs::ref {

struct RefGrowthStats {
  int step = 0;                  // views accumulated (last_seen's clock)
  std::vector<double> grad_sum;  // [N]
  std::vector<int> count;        // [N]
  std::vector<int> last_seen;    // [N] 0 for never seen
};

// Statistics of n children, all zero.
RefGrowthStats growth_stats_reference(size_t n);

// One view: v_px [N,2] dL/d(u, v) in pixels, radii [N], the view's size.
void accumulate_growth_stats(RefGrowthStats& s, const std::vector<float>& v_px, const std::vector<int>& radii,
                             int width, int height, bool ndc);

}  // namespace ag2gs::ref
