// Plain references of the language attachment (train/stage3/language.h), from
// its definition rather than the library's single pass over the pixels:
//  - the scores of one view: for every (cluster, mask) pair, one scan of the
//    image counting the intersection and union and summing G = F (or F /
//    alpha where alpha >= 0.1, the quotient rounded to float as the library
//    does; featureless elsewhere) over each side in double, then
//    S = IoU (1 - |Gbar_c - Gbar_M|_1), and feature_l1 NaN (S 0) when a side
//    has no pixel with a feature;
//  - a cluster's feature: the softmax(s S)-weighted mean of its matches' CLIP
//    vectors, L2-normalised, in double.
#pragma once

#include <cstdint>
#include <utility>
#include <vector>

#include "host/scene/scene.h"
#include "train/stage3/language.h"

namespace ag2gs::ref {

// Every pair sharing a pixel, by (cluster, mask): the layout of score_view().
// ids [H,W], feat [3,H,W], alpha [H,W] (read only when by_alpha).
std::vector<MaskMatch> language_scores_reference(const std::vector<int32_t>& ids, int clusters,
                                                 const std::vector<float>& feat, const std::vector<float>& alpha,
                                                 const ViewMasks& masks, bool by_alpha);

// matches: (S, CLIP vector [dim]) of every match of one cluster, at least one;
// returns its [dim] feature.
std::vector<double> language_feature_reference(const std::vector<std::pair<double, std::vector<double>>>& matches,
                                               int dim, double softmax_scale);

}  // namespace ag2gs::ref
