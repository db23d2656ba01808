// The anchor trainer's two small per-row kernels
// (kernels/anchor_regularisers.cl): the offset regulariser L_in and the
// projection of the semantic features into the unit ball.
#pragma once

#include <cstddef>

#include "host/device/cl_runtime.h"

namespace ag2gs {

// L_in = mean over the n offsets (voxel units) of exp(relu(|o|^2 - 1)):
// writes each row's term to value[n] and adds weight / n * dterm/do to
// grad[n, 3]. One work-item per row, no atomics.
void enqueue_offset_regulariser(Runtime& rt, size_t n, float weight, const DeviceBuffer& offset, DeviceBuffer& grad,
                                DeviceBuffer& value);

// f <- f / max(1, |f|) for the anchors' features [anchors, 3], in place.
void enqueue_feature_ball(Runtime& rt, size_t anchors, DeviceBuffer& feature);

}  // namespace ag2gs
