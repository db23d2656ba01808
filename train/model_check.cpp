#include "train/model_check.h"

#include <cmath>
#include <stdexcept>

#include "host/render/sky.h"
#include "train/anchors/anchor_model.h"
#include "train/graph/anchor_graph.h"
#include "train/stage3/clustering.h"
#include "train/stage3/language.h"

namespace ag2gs {

AnchorModel check_model_archive(const ModelArchive& archive) {
  AnchorModel model = AnchorModel::from_archive(archive);
  const nlohmann::json& anchors = archive.meta.at("anchors");
  if (!anchors.contains("count") || !anchors.at("count").is_number_integer() ||
      anchors.at("count").get<int64_t>() != static_cast<int64_t>(model.size()))
    throw std::runtime_error(archive.source + ": meta 'anchors' records a count of " +
                             (anchors.contains("count") ? anchors.at("count").dump() : std::string("nothing")) +
                             " where the arrays hold " + std::to_string(model.size()) +
                             " anchors; the file is damaged: train the model again");
  // A graph may be stale (built before the anchors changed; stage 3 builds
  // it again), never broken.
  if (AnchorGraph::in_archive(archive)) AnchorGraph::from_archive(archive);
  if (archive.meta.contains("clusters") || archive.has("clusters/anchor_cluster")) {
    const Clustering clustering = clustering_from_archive(archive, model.size());
    if (archive.meta.contains("language") || archive.has("clusters/language"))
      language_from_archive(archive, clustering.clusters());
  }
  sky_from_archive(archive);
  const nlohmann::json train = archive.meta.value("train", nlohmann::json::object());
  if (!train.is_object())
    throw std::runtime_error(archive.source + ": meta 'train' is not an object; the file is damaged");
  recorded_resolution(train, archive.source);
  recorded_sh_degree(train, model.config().sh_degree, archive.source);
  return model;
}

int recorded_resolution(const nlohmann::json& record, const std::string& file) {
  if (!record.contains("resolution")) return 1;
  const nlohmann::json& r = record.at("resolution");
  if (!r.is_number_integer() || r.get<int64_t>() < 1 || r.get<int64_t>() > 64)
    throw std::runtime_error(file + " records a training resolution of " + r.dump() +
                             ", which is not a whole number from 1 to 64: the file is damaged; give -r R");
  return r.get<int>();
}

int recorded_sh_degree(const nlohmann::json& train, int model_degree, const std::string& file) {
  if (!train.contains("active_sh_degree")) return model_degree;
  const nlohmann::json& d = train.at("active_sh_degree");
  if (!d.is_number_integer() || d.get<int64_t>() < 0 || d.get<int64_t>() > 3)
    throw std::runtime_error(file + " records an active SH degree of " + d.dump() +
                             ", which is not 0 to 3: the file is damaged; train the model again");
  return std::min(d.get<int>(), model_degree);
}

}  // namespace ag2gs
