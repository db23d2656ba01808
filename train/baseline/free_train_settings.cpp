#include "train/baseline/free_train_settings.h"

#include "train/baseline/free_trainer.h"

namespace ag2gs {
namespace {

template <class T>
constexpr auto field = &FreeTrainSetting::of<T>;  // a row's field from a lambda

std::vector<FreeTrainSetting> build_table() {
  SettingRows<FreeTrainConfig> add;
  using C = FreeTrainConfig;
  add(field<int>([](C& c) -> int& { return c.iterations; }), "iterations", "--iters",
      "Training iterations (default 30000)")
      .range(1, 1e8);
  add(field<uint64_t>([](C& c) -> uint64_t& { return c.seed; }), "seed", "--seed",
      "Random seed: view order and split samples (default 0)")
      .seed();
  add(field<bool>([](C& c) -> bool& { return c.white_background; }), "white_background", "--white-bg",
      "White background instead of black");
  add(field<int>([](C& c) -> int& { return c.sh_degree; }), "sh_degree", "--sh-degree", "Highest SH degree (default 3)")
      .range(0, 3);
  add(field<int>([](C& c) -> int& { return c.sh_interval; }), "sh_interval", "--sh-interval",
      "Iterations per SH degree step (default 0 = min(1000, iters / (sh-degree + 1)), as `train`)")
      .non_negative()
      .effective([](const C& c) { return c.effective_sh_interval(); });
  add(field<float>([](C& c) -> float& { return c.lambda_ssim; }), "lambda_ssim", "--lambda-ssim",
      "Weight of 1 - SSIM in the loss (default 0.2)")
      .range(0, 1);
  add(field<float>([](C& c) -> float& { return c.init_opacity; }), "init_opacity", "",
      "Opacity of the Gaussians made from the SfM points (0.1; validate() wants it inside (0, 1))")
      .range(0, 1);
  add(field<double>([](C& c) -> double& { return c.position_lr_init; }), "position_lr_init", "--lr-position",
      "Position learning rate at the start, x extent (default 1.6e-4)")
      .range(0, 100);
  add(field<double>([](C& c) -> double& { return c.position_lr_final; }), "position_lr_final", "--lr-position-final",
      "Position learning rate at the end, x extent (1.6e-6)")
      .range(0, 100);
  add(field<double>([](C& c) -> double& { return c.sh_dc_lr; }), "sh_dc_lr", "--lr-sh",
      "SH DC learning rate (default 0.0025)")
      .range(0, 100);
  add(field<double>([](C& c) -> double& { return c.sh_rest_lr; }), "sh_rest_lr", "--lr-sh-rest",
      "Higher SH learning rate (default 0.0025 / 20)")
      .range(0, 100);
  add(field<double>([](C& c) -> double& { return c.opacity_lr; }), "opacity_lr", "--lr-opacity",
      "Opacity logit learning rate (default 0.05)")
      .range(0, 100);
  add(field<double>([](C& c) -> double& { return c.scaling_lr; }), "scaling_lr", "--lr-scaling",
      "Log-scale learning rate (default 0.005)")
      .range(0, 100);
  add(field<double>([](C& c) -> double& { return c.rotation_lr; }), "rotation_lr", "--lr-rotation",
      "Rotation learning rate (default 0.001)")
      .range(0, 100);
  add(field<double>([](C& c) -> double& { return c.adam.beta1; }), "adam.beta1", "", "").range(0, 0.999999);
  add(field<double>([](C& c) -> double& { return c.adam.beta2; }), "adam.beta2", "", "").range(0, 0.999999);
  add(field<double>([](C& c) -> double& { return c.adam.eps; }), "adam.eps", "", "").positive();
  add(field<int>([](C& c) -> int& { return c.densify_from; }), "densify.from", "--densify-from",
      "First densification iteration (default 500)")
      .non_negative();
  add(field<int>([](C& c) -> int& { return c.densify_until; }), "densify.until", "--densify-until",
      "Last densification iteration (default 0 = half of --iters)")
      .non_negative()
      .effective([](const C& c) { return c.effective_densify_until(); });
  add(field<int>([](C& c) -> int& { return c.densify_every; }), "densify.every", "--densify-every",
      "Iterations between densifications (default 100; 0 = off)")
      .non_negative();
  add(field<double>([](C& c) -> double& { return c.grad_threshold; }), "densify.grad_threshold", "--densify-threshold",
      "Mean view-space positional gradient (NDC units) above which a Gaussian is cloned or split (default 2e-4)")
      .range(1e-12, 1e6);
  add(field<double>([](C& c) -> double& { return c.percent_dense; }), "densify.percent_dense", "--percent-dense",
      "Clone when the largest scale is at most this x extent, split otherwise (default 0.01)")
      .non_negative();
  add(field<double>([](C& c) -> double& { return c.prune_opacity; }), "densify.prune_opacity", "--prune-opacity",
      "Remove Gaussians with opacity below this (default 0.005)")
      .range(0, 0.999);
  add(field<int>([](C& c) -> int& { return c.opacity_reset_every; }), "densify.opacity_reset_every",
      "--opacity-reset-every",
      "Clamp every opacity to 0.01 every N iterations until --densify-until (default 3000; 0 = off)")
      .non_negative();
  add(field<double>([](C& c) -> double& { return c.max_screen_size; }), "densify.max_screen_size", "--max-screen-size",
      "After the first opacity reset, remove Gaussians with a radius above this many pixels (default 20; 0 = off)")
      .non_negative();
  add(field<double>([](C& c) -> double& { return c.max_world_size; }), "densify.max_world_size", "--max-world-size",
      "After the first opacity reset, remove Gaussians larger than this x extent (default 0.1; 0 = off)")
      .non_negative();
  return add.t;
}

}  // namespace

const std::vector<FreeTrainSetting>& free_train_settings() {
  static const std::vector<FreeTrainSetting> table = build_table();
  return table;
}

}  // namespace ag2gs
