// Plain-loop reference of the boundary region of a mask (queries/query_eval.h,
// mask_boundary), written from its definition instead of the library's
// erosion: a mask pixel is on the boundary when some pixel within Chebyshev
// distance d lies outside the image or outside the mask. Integer output, no
// rounding.
#pragma once

#include <cstddef>
#include <cstdint>
#include <vector>

namespace ag2gs::ref {

// m: a 0/1 mask [h,w]; returns the 0/1 boundary mask [h,w].
std::vector<uint8_t> mask_boundary_reference(const std::vector<uint8_t>& m, int w, int h, int d);

}  // namespace ag2gs::ref
