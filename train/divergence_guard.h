// Watches a training run for the two ways an anchor model fails on a real
// capture, and says so once, with the flag that helps, instead of letting a
// run end as a silent 7 dB model:
//
//  - PSNR below its start: the mean training PSNR of the last `window`
//    steps is below the mean of the first `start_steps` steps (a model that
//    got worse at what it sees).
//  - Runaway growth: a growing round multiplies the Gaussian count by more
//    than `growth_factor` while the mean loss since that round's predecessor
//    did not improve on the round before it.
//
// Pure bookkeeping on numbers the trainer already reports (no device work).
#pragma once

#include <cstddef>
#include <deque>
#include <optional>
#include <string>

namespace ag2gs {

struct DivergenceGuardConfig {
  int start_steps = 50;        // steps whose mean PSNR is the start value
  int window = 300;            // a warning needs this many steps below the start
  double growth_factor = 1.5;  // a round growing the count by more than this ...
};

class DivergenceGuard {
 public:
  explicit DivergenceGuard(const DivergenceGuardConfig& config = {}) : config_(config) {}

  // One training step (1-based iteration, its PSNR and loss). Returns the
  // PSNR warning the first time it applies.
  std::optional<std::string> step(int iteration, double psnr, double loss);
  // A growing round after `iteration` took the model from `before` to
  // `after` Gaussians. Returns the growth warning the first time it applies.
  std::optional<std::string> round(int iteration, size_t before, size_t after);

  bool warned() const { return warned_psnr_ || warned_growth_; }
  double start_psnr() const { return start_count_ ? start_sum_ / start_count_ : 0.0; }

 private:
  DivergenceGuardConfig config_;
  double start_sum_ = 0;
  int start_count_ = 0;
  std::deque<double> recent_;  // the last `window` PSNRs
  double recent_sum_ = 0;
  double round_loss_sum_ = 0;  // since the last round
  int round_loss_count_ = 0;
  double previous_round_loss_ = -1;  // mean loss of the round before; < 0 = none yet
  bool warned_psnr_ = false, warned_growth_ = false;
};

}  // namespace ag2gs
