#include "train/divergence_guard.h"

#include <spdlog/fmt/fmt.h>

#include <cmath>

namespace ag2gs {

std::optional<std::string> DivergenceGuard::step(int iteration, double psnr, double loss) {
  if (!std::isfinite(psnr) || !std::isfinite(loss)) return std::nullopt;
  round_loss_sum_ += loss;
  ++round_loss_count_;
  if (start_count_ < config_.start_steps) {
    start_sum_ += psnr;
    ++start_count_;
    return std::nullopt;
  }
  recent_.push_back(psnr);
  recent_sum_ += psnr;
  if (static_cast<int>(recent_.size()) > config_.window) {
    recent_sum_ -= recent_.front();
    recent_.pop_front();
  }
  if (warned_psnr_ || static_cast<int>(recent_.size()) < config_.window) return std::nullopt;
  const double mean = recent_sum_ / static_cast<double>(recent_.size());
  if (!(mean < start_psnr())) return std::nullopt;
  warned_psnr_ = true;
  return fmt::format(
      "training PSNR {:.2f} dB over iterations {}-{} is below its start ({:.2f} dB): the model is getting worse. "
      "Usual causes: voxels too fine for the scene (coarser: --voxel-size, or --top-cells with fewer cells), too "
      "many Gaussians (--max-gaussians), or learning rates too high (--preset paper, --lr-offset)",
      mean, iteration - config_.window + 1, iteration, start_psnr());
}

std::optional<std::string> DivergenceGuard::round(int iteration, size_t before, size_t after) {
  const double loss = round_loss_count_ ? round_loss_sum_ / round_loss_count_ : -1;
  const double previous = previous_round_loss_;
  previous_round_loss_ = loss;
  round_loss_sum_ = 0;
  round_loss_count_ = 0;
  if (warned_growth_ || before == 0 || previous < 0 || loss < 0) return std::nullopt;
  if (!(static_cast<double>(after) > config_.growth_factor * static_cast<double>(before)) || loss < previous)
    return std::nullopt;
  warned_growth_ = true;
  return fmt::format(
      "iteration {}: growing took the model from {} to {} Gaussians while the loss did not improve ({:.5f} -> "
      "{:.5f}): growth is not following content. Limit it with --max-gaussians or --grow-budget, or raise "
      "--grow-threshold",
      iteration, before, after, previous, loss);
}

}  // namespace ag2gs
