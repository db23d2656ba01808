#include "apps/backdrop.h"

#include <spdlog/spdlog.h>

#include <exception>
#include <stdexcept>

namespace ag2gs {

void ObjectInModel::check(const std::string& who) const {
  if (!model || !archive || !scene) throw std::invalid_argument(who + ": no model or no scene");
  if (selected.size() != model->size())
    throw std::invalid_argument(who + ": a selection of " + std::to_string(selected.size()) +
                                " anchors for a model of " + std::to_string(model->size()));
}

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
