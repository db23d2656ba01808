#include "stages/train_config.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>

#include "host/io/json_input.h"

namespace ag2gs {

TrainConfig TrainConfig::preset(const std::string& name) {
  TrainConfig c;
  if (name == "paper") {
    c.anchors.top_cells = 200;
    c.grow_budget = 0.0;
    c.anchors.init_layers = 1;
    c.max_gaussians = 0;
    c.downscales = 0;
    c.sky_degree = -1;
    return c;
  }
  if (name != "default" && name != "appearance")
    throw std::invalid_argument("preset '" + name + "': choose default (also called appearance) or paper");
  c.anchors.scale_cap = 64.f;
  c.anchors.children = 2;
  c.anchors.init_layers = 2;
  c.grow_budget = 0.1;
  c.anchors.init_children_at_points = true;
  c.recycle_opacity = 0.02;
  c.final_prune_opacity = 0.015;
  c.prune_importance = 0.01;
  c.offset_lr_init = 1e-2;
  c.scaling_lr = 0.01;
  c.grow_min_seen = 0.1;
  c.grow_split = 4.0;
  c.far_shell = true;
  return c;
}

void TrainConfig::validate() const {
  auto bad = [](const std::string& what) { throw std::invalid_argument("TrainConfig: " + what); };
  anchors.validate();
  if (iterations < 1) bad("iterations is " + std::to_string(iterations) + "; it must be at least 1");
  if (sh_interval < 0) bad("sh_interval is " + std::to_string(sh_interval) + "; use 0 (automatic) or more");
  if (!(lambda_ssim >= 0 && lambda_ssim <= 1)) bad("lambda_ssim must be in [0, 1]");
  if (!(w_offset >= 0) || !std::isfinite(w_offset)) bad("w_offset must be finite and >= 0");
  if (!(w_distortion >= 0) || !std::isfinite(w_distortion)) bad("w_distortion must be finite and >= 0");
  if (distortion_from < 0) bad("distortion_from must be >= 0");
  if (!(w_is >= 0) || !std::isfinite(w_is)) bad("w_is must be finite and >= 0");
  if (!(w_ic >= 0) || !std::isfinite(w_ic)) bad("w_ic must be finite and >= 0");
  if (mask_from < -1) bad("mask_from must be -1 (iterations / 6) or >= 0");
  if (prop_iters < -1) bad("prop_iters must be -1 (iterations / 6), 0 (no stage 2) or more");
  if (static_cast<int64_t>(iterations) + effective_prop_iters() > std::numeric_limits<int>::max())
    bad("iterations + prop_iters is too large");
  if (!(w_prop >= 0) || !std::isfinite(w_prop)) bad("w_prop must be finite and >= 0");
  if (!(prop_tau > 0) || !std::isfinite(prop_tau)) bad("prop_tau must be finite and > 0");
  const std::pair<const char*, double> rates[] = {
      {"offset_lr_init", offset_lr_init}, {"offset_lr_final", offset_lr_final},
      {"feature_lr", feature_lr},         {"sh_dc_lr", sh_dc_lr},
      {"sh_rest_lr", sh_rest_lr},         {"opacity_lr", opacity_lr},
      {"scaling_lr", scaling_lr},         {"rotation_lr", rotation_lr},
      {"sky_lr", sky_lr}};
  for (const auto& [name, v] : rates)
    if (!(v >= 0) || !std::isfinite(v)) bad(std::string(name) + " must be finite and >= 0");
  if (sky_degree < kSkyAuto || sky_degree > 3)
    bad("sky_degree is " + std::to_string(sky_degree) + "; use -2 (from the scene), -1 (no sky) or 0 to 3");
  if (!(prune_opacity >= 0 && prune_opacity < 1)) bad("prune_opacity must be in [0, 1)");
  if (!(recycle_opacity >= 0 && recycle_opacity < 1)) bad("recycle_opacity must be in [0, 1)");
  if (!(final_prune_opacity >= 0 && final_prune_opacity < 1)) bad("final_prune_opacity must be in [0, 1)");
  if (!(prune_importance >= 0 && prune_importance < 1))
    bad("prune_importance must be in [0, 1) (a share of what the training views show; 0 = off)");
  if (prune_importance_at < 0 || prune_importance_at > iterations)
    bad("prune_importance_at is " + std::to_string(prune_importance_at) + "; use 0 (from the schedule) or 1 to " +
        std::to_string(iterations) + " (the stage-1 iterations)");
  if (downscales < -1 || downscales > 6)
    bad("downscales is " + std::to_string(downscales) + "; use -1 (from the images), 0 (off) or 1 to 6");
  if (res_schedule < 0) bad("res_schedule must be 0 (from the iterations) or at least 1 iteration");
  if (!(coarse_lowpass > 0 && coarse_lowpass <= 1)) bad("coarse_lowpass must be in (0, 1]");
  if (grow_every < 0 || grow_from < 0 || grow_until < 0 || !(grow_min_seen >= 0 && grow_min_seen <= 1))
    bad("grow_every, grow_from and grow_until must be >= 0 and grow_min_seen in [0, 1]");
  if (!(grow_split >= 0) || !std::isfinite(grow_split)) bad("grow_split must be finite and >= 0 (0 = off)");
  if (!(grow_threshold > 0) || !std::isfinite(grow_threshold)) bad("grow_threshold must be finite and > 0");
  if (prune_unseen_window < -1)
    bad("prune_unseen_window is " + std::to_string(prune_unseen_window) +
        "; use -1 (off), 0 (2 x training views) or a number of views");
  if (opacity_reset_every < 0 || opacity_reset_pause < 0)
    bad("opacity_reset_every and opacity_reset_pause must be >= 0 (opacity_reset_every 0 = no reset)");
  if (!(grow_budget >= 0) || !std::isfinite(grow_budget))
    bad("grow_budget must be finite and >= 0 (a fraction of the anchors per round; 0 = no limit)");
  if (max_gaussians < -1) bad("max_gaussians must be -1 (from the scene), 0 (no limit) or a count");
  if (offset_lr_init > 0 && !(offset_lr_final > 0))
    bad("offset_lr_final must be > 0 when offset_lr_init is (exponential decay)");
}

int TrainConfig::effective_sh_interval() const {
  if (sh_interval > 0) return sh_interval;
  return std::max(1, std::min(1000, iterations / (anchors.sh_degree + 1)));
}

int TrainConfig::effective_mask_from() const {
  return mask_from >= 0 ? mask_from : iterations / 6;
}

int TrainConfig::effective_grow_until() const {
  return grow_until > 0 ? grow_until : static_cast<int>(static_cast<int64_t>(iterations) * 2 / 3);
}

int TrainConfig::effective_prune_importance_at() const {
  if (prune_importance_at > 0) return prune_importance_at;
  // Halfway between the end of growing and the end of stage 1: the last
  // round's anchors have had time to show what they draw, and the
  // neighbours of the removed ones have the other half to take over
  // (measured against a growing interval after the end: docs/benchmarks.md).
  return std::max(1, std::min(iterations, (effective_grow_until() + iterations) / 2));
}

GrowthConfig TrainConfig::growth_config(size_t train_views) const {
  GrowthConfig g;
  g.grad_threshold = static_cast<float>(grow_threshold);
  g.layer_factor = 2.f;
  g.start = grow_from;
  g.stop = effective_grow_until();
  g.every = grow_every;
  g.min_observations = 1;
  g.min_seen_fraction = static_cast<float>(grow_min_seen);
  g.prune_opacity = static_cast<float>(prune_opacity);
  g.prune_unseen = prune_unseen_window >= 0;
  const size_t two_epochs = std::min<size_t>(2 * train_views, static_cast<size_t>(std::numeric_limits<int>::max()));
  g.unseen_window = prune_unseen_window > 0 ? prune_unseen_window : static_cast<int>(two_epochs);
  g.ndc = true;
  g.same_layer = grow_same_layer;
  g.recycle_opacity = static_cast<float>(recycle_opacity);
  g.round_growth = static_cast<float>(grow_budget);
  g.split_voxels = static_cast<float>(grow_split);
  return g;
}

int TrainConfig::auto_downscales(int min_side) {
  int levels = 0;
  while (levels < 3 && (min_side >> (levels + 1)) >= kCoarseMinSide) ++levels;
  return levels;
}

int TrainConfig::auto_res_schedule(int iterations, int downscales) {
  if (downscales <= 0) return 1;
  const int per_level = static_cast<int>(kFullResolutionFrom * iterations / downscales);
  return std::max(1, std::min(per_level, 3000));
}

size_t TrainConfig::effective_max_gaussians(size_t view_pixels, size_t initial) const {
  if (max_gaussians >= 0) return static_cast<size_t>(max_gaussians);
  return std::max(view_pixels, 2 * initial);
}

nlohmann::json TrainConfig::to_json() const {
  nlohmann::json a = {
      {"children", anchors.children},         {"layers", anchors.layers},
      {"top_cells", anchors.top_cells},       {"voxel_size", anchors.voxel_size},
      {"layer_ratio", anchors.layer_ratio},   {"init_layer", anchors.init_layer},
      {"init_layers", anchors.init_layers},
      {"init_opacity", anchors.init_opacity}, {"init_children_at_points", anchors.init_children_at_points},
      {"init_scale", anchors.init_scale},     {"init_feature", anchors.init_feature},
      {"scale_cap", anchors.scale_cap},       {"scale_cap_layers", anchors.scale_cap_layers},
      {"sh_degree", anchors.sh_degree}};
  return {{"iterations", iterations},
          {"seed", seed},
          {"anchors", a},
          {"sh_interval", effective_sh_interval()},
          {"lambda_ssim", lambda_ssim},
          {"w_offset", w_offset},
          {"w_distortion", w_distortion},
          {"distortion_from", distortion_from},
          {"w_is", w_is},
          {"w_ic", w_ic},
          {"mask_from", effective_mask_from()},
          {"mask_alpha_normalise", mask_alpha_normalise},
          {"mask_geometry", mask_geometry},
          {"mask_unmasked_group", mask_unmasked_group},
          {"feature_ball", feature_ball},
          {"grow_same_layer", grow_same_layer},
          {"recycle_opacity", recycle_opacity},
          {"final_prune_opacity", final_prune_opacity},
          {"prune_importance", prune_importance},
          {"prune_importance_at", effective_prune_importance_at()},
          {"grow_budget", grow_budget},
          {"max_gaussians", max_gaussians},
          {"prop_iters", effective_prop_iters()},
          {"w_prop", w_prop},
          {"prop_tau", prop_tau},
          {"offset_lr_init", offset_lr_init},
          {"offset_lr_final", offset_lr_final},
          {"offset_lr_extent", offset_lr_extent},
          {"feature_lr", feature_lr},
          {"sh_dc_lr", sh_dc_lr},
          {"sh_rest_lr", sh_rest_lr},
          {"opacity_lr", opacity_lr},
          {"scaling_lr", scaling_lr},
          {"rotation_lr", rotation_lr},
          {"adam", {{"beta1", adam.beta1}, {"beta2", adam.beta2}, {"eps", adam.eps}}},
          {"white_background", white_background},
          {"sky_degree", sky_degree},
          {"sky_lr", sky_lr},
          {"far_shell", far_shell},
          {"grow",
           {{"from", grow_from},
            {"until", effective_grow_until()},
            {"every", grow_every},
            {"threshold", grow_threshold},
            {"min_seen", grow_min_seen},
            {"split", grow_split}}},
          {"prune_opacity", prune_opacity},
          {"prune_unseen_window", prune_unseen_window},
          {"opacity_reset_every", opacity_reset_every},
          {"opacity_reset_pause", opacity_reset_pause},
          {"downscales", downscales},
          {"res_schedule", res_schedule},
          {"coarse_lowpass", coarse_lowpass}};
}

TrainConfig TrainConfig::from_json(const nlohmann::json& j) {
  TrainConfig c;
  try {
    const nlohmann::json& a = j.at("anchors");
    c.anchors.children = a.at("children").get<int>();
    c.anchors.layers = a.at("layers").get<int>();
    c.anchors.top_cells = a.at("top_cells").get<int>();
    c.anchors.voxel_size = a.value("voxel_size", 0.0);
    c.anchors.layer_ratio = a.at("layer_ratio").get<int>();
    c.anchors.init_layer = a.at("init_layer").get<int>();
    c.anchors.init_layers = a.value("init_layers", 1);
    c.anchors.init_children_at_points = a.value("init_children_at_points", false);
    c.anchors.init_opacity = a.at("init_opacity").get<float>();
    c.anchors.init_scale = a.at("init_scale").get<float>();
    c.anchors.scale_cap = a.value("scale_cap", 1.f);
    c.anchors.scale_cap_layers = a.value("scale_cap_layers", kMaxLayers);
    c.anchors.init_feature = a.at("init_feature").get<float>();
    c.anchors.sh_degree = a.at("sh_degree").get<int>();
    c.iterations = j.at("iterations").get<int>();
    c.seed = j.at("seed").get<uint64_t>();
    c.sh_interval = j.at("sh_interval").get<int>();
    c.lambda_ssim = j.at("lambda_ssim").get<float>();
    c.w_offset = j.at("w_offset").get<float>();
    c.w_distortion = j.at("w_distortion").get<float>();
    c.distortion_from = j.at("distortion_from").get<int>();
    c.w_is = j.at("w_is").get<float>();
    c.w_ic = j.at("w_ic").get<float>();
    c.mask_from = j.at("mask_from").get<int>();
    c.mask_alpha_normalise = j.at("mask_alpha_normalise").get<bool>();
    c.mask_geometry = j.at("mask_geometry").get<bool>();
    c.mask_unmasked_group = j.value("mask_unmasked_group", false);  // written before the option
    c.feature_ball = j.value("feature_ball", false);
    c.grow_same_layer = j.value("grow_same_layer", false);
    c.recycle_opacity = j.value("recycle_opacity", 0.0);
    c.final_prune_opacity = j.value("final_prune_opacity", 0.0);  // written before the option
    c.prune_importance = j.value("prune_importance", 0.0);
    c.prune_importance_at = j.value("prune_importance_at", 0);
    // Checkpoints from before the budgets grew without limit.
    c.grow_budget = j.value("grow_budget", 0.0);
    c.max_gaussians = j.value("max_gaussians", int64_t{0});
    // Written before stage 2 existed: stage 1 only.
    c.prop_iters = j.value("prop_iters", 0);
    c.w_prop = j.value("w_prop", 0.01f);  // the default of that time
    c.prop_tau = j.value("prop_tau", kPropagationTau);
    c.offset_lr_init = j.at("offset_lr_init").get<double>();
    c.offset_lr_final = j.at("offset_lr_final").get<double>();
    c.offset_lr_extent = j.at("offset_lr_extent").get<bool>();
    c.feature_lr = j.at("feature_lr").get<double>();
    c.sh_dc_lr = j.at("sh_dc_lr").get<double>();
    c.sh_rest_lr = j.at("sh_rest_lr").get<double>();
    c.opacity_lr = j.at("opacity_lr").get<double>();
    c.scaling_lr = j.at("scaling_lr").get<double>();
    c.rotation_lr = j.at("rotation_lr").get<double>();
    c.adam.beta1 = j.at("adam").at("beta1").get<double>();
    c.adam.beta2 = j.at("adam").at("beta2").get<double>();
    c.adam.eps = j.at("adam").at("eps").get<double>();
    c.white_background = j.at("white_background").get<bool>();
    c.sky_degree = j.value("sky_degree", -1);  // written before the sky existed
    c.sky_lr = j.value("sky_lr", 0.01);
    c.far_shell = j.value("far_shell", false);  // written before the far shell: none
    const nlohmann::json& g = j.at("grow");
    c.grow_from = g.at("from").get<int>();
    c.grow_until = g.at("until").get<int>();
    c.grow_every = g.at("every").get<int>();
    c.grow_threshold = g.at("threshold").get<double>();
    c.grow_min_seen = g.at("min_seen").get<double>();
    c.grow_split = g.value("split", 0.0);  // written before split growth: off
    c.prune_opacity = j.at("prune_opacity").get<double>();
    c.prune_unseen_window = j.at("prune_unseen_window").get<int>();
    c.opacity_reset_every = j.at("opacity_reset_every").get<int>();
    c.opacity_reset_pause = j.at("opacity_reset_pause").get<int>();
    c.downscales = j.value("downscales", 0);  // written before the option: full resolution throughout
    c.res_schedule = j.value("res_schedule", 250);
    c.coarse_lowpass = j.value("coarse_lowpass", 1.0);  // written before the option: 0.3 px at every level
  } catch (const nlohmann::json::exception& e) {
    throw std::runtime_error(std::string("training config: ") + json_error_text(e));
  }
  return c;
}

}  // namespace ag2gs
