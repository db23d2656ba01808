#include "apps/backdrop.h"

#include <spdlog/spdlog.h>

#include <exception>

namespace ag2gs {

ModelBackdrop::ModelBackdrop(Runtime& rt, const ModelArchive& archive, const std::string& name,
                             const std::string& without_config)
    : sky(rt) {
  if (archive.meta.contains("train") && archive.meta["train"].contains("config")) {
    try {
      train = TrainConfig::from_json(archive.meta["train"]["config"]);
    } catch (const std::exception& e) {
      spdlog::warn("{}: its training config cannot be read ({}); {}", name, e.what(), without_config);
    }
  }
  sky_coefficients = sky_from_archive(archive);
  if (sky_coefficients) sky.set(sky_degree_for(sky_coefficients->size()), *sky_coefficients);
  const float bg = train.white_background && !sky.enabled() ? 1.f : 0.f;
  settings.background = {bg, bg, bg};
}

}  // namespace ag2gs
