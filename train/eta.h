// The time left in a training run, for the progress line's ETA. The step time
// follows the Gaussian count, so the estimate needs the count at the end of
// growth; the two trainers grow differently, and each has its model, checked
// against logged runs (docs/benchmarks.md, "Progress and ETA").
#pragma once

#include <cstddef>

namespace ag2gs {

// Anchor growth: every round still to come (`rounds_left`) multiplies the
// count by the mean factor of the `rounds_done` rounds that took it from
// `start` to `now`, up to `budget` (0 = none). The budget is what keeps this
// finite: without one, use growth_end_tapering.
double growth_end_geometric(size_t now, size_t start, int rounds_done, int rounds_left, size_t budget);

// Densification (the free-Gaussian baseline): the rounds still to come add
// less and less, from what the last round added (`last_added`) down to
// nothing at the end of densification. On the fox at 7000 iterations the
// rounds went from +9k to +2.5k; a geometric rule promised 2199 hours there.
double growth_end_tapering(size_t now, size_t last_added, int rounds_left);

// Seconds left: `remaining` steps at `step_ms` each while the model holds
// `gaussians`, the step time taken to follow the count. Of those steps,
// `growing` are in the growth phase, through which the count rises evenly to
// `end_count` (never taken below `gaussians`); it stays there afterwards.
double estimate_seconds_left(int remaining, double step_ms, size_t gaussians, int growing, double end_count);

}  // namespace ag2gs
