#include "train/train_config.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>

#include "host/io/json_input.h"
#include "train/train_settings.h"

namespace ag2gs {

TrainConfig TrainConfig::preset(const std::string& name) {
  TrainConfig c;
  apply_train_preset(c, name);  // the values: train/train_settings.cpp
  return c;
}

void TrainConfig::validate() const {
  auto bad = [](const std::string& what) { throw std::invalid_argument("TrainConfig: " + what); };
  // Each setting's own range (train/train_settings.cpp), then what ties
  // settings together.
  if (const std::string p = settings_problem(train_settings(), *this); !p.empty()) bad(p);
  anchors.validate();
  if (static_cast<int64_t>(iterations) + effective_prop_iters() > std::numeric_limits<int>::max())
    bad("iterations + prop_iters is too large");
  const std::pair<const char*, double> adam_values[] = {{"adam.beta1", adam.beta1}, {"adam.beta2", adam.beta2}};
  for (const auto& [name, v] : adam_values)
    if (!(v >= 0 && v < 1)) bad(std::string(name) + " must lie in [0, 1)");
  if (!(adam.eps > 0) || !std::isfinite(adam.eps)) bad("adam.eps must be finite and > 0");
  if (prune_importance_at > iterations)
    bad("prune_importance_at is " + std::to_string(prune_importance_at) + "; use 0 (from the schedule) or 1 to " +
        std::to_string(iterations) + " (the stage-1 iterations)");
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
  // (measured against a growing interval after the end: docs/benchmarks.md;
  // on a generated scene whose edges few training views see, a prune then
  // took their anchors and cost the test views 6 dB).
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
  return settings_to_json(train_settings(), *this);
}

TrainConfig TrainConfig::from_json(const nlohmann::json& j) {
  TrainConfig c;
  if (!j.is_object()) throw std::runtime_error("training config: not a JSON object");
  // Every key must be a setting's (or a group of them): a key this version
  // does not know is a file from a newer ag2gs, or a damaged one.
  const nlohmann::json known = c.to_json();
  for (const auto& [k, v] : j.items()) {
    if (!known.contains(k))
      throw std::runtime_error("training config: unknown key '" + k + "' (written by a newer ag2gs, or damaged)");
    if (known[k].is_object()) {
      if (!v.is_object()) throw std::runtime_error("training config: '" + k + "' must be an object");
      for (const auto& [k2, v2] : v.items())
        if (!known[k].contains(k2))
          throw std::runtime_error("training config: unknown key '" + k + "." + k2 +
                                   "' (written by a newer ag2gs, or damaged)");
    }
  }
  for (const TrainSetting& t : train_settings()) {
    if (j.contains(t.pointer())) {
      try {
        t.set(c, j.at(t.pointer()));
      } catch (const nlohmann::json::exception& e) {
        throw std::runtime_error("training config: '" + t.key + "': " + json_error_text(e));
      }
    } else if (t.before_value) {
      t.assign(c, *t.before_value);  // a file written before the setting existed
    } else {
      throw std::runtime_error("training config: key '" + t.key + "' is missing");
    }
  }
  return c;
}

}  // namespace ag2gs
