// Per-pixel channels as colours, as `render` writes them and `view` shows them.
#pragma once

#include <cstdint>
#include <vector>

namespace ag2gs::cli {

// A cluster id as a colour: hues spread by the golden ratio, black for -1.
// Returns [N,3] in [0,1].
std::vector<float> instance_colours(const std::vector<int32_t>& ids);

// A feature vector as a colour: its direction mapped from [-1,1] to [0,1];
// black where alpha < 0.1. feature [N,3], alpha [N].
std::vector<float> feature_colours(const std::vector<float>& feature, const std::vector<float>& alpha);

}  // namespace ag2gs::cli
