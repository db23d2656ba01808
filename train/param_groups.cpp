#include "train/param_groups.h"

#include <spdlog/spdlog.h>

#include <cmath>
#include <stdexcept>

namespace ag2gs {

ParamGroups::ParamGroups(Runtime& rt, std::vector<ParamGroupSpec> specs, size_t rows, size_t anchor_rows)
    : specs_(std::move(specs)) {
  for (const ParamGroupSpec& s : specs_)
    groups_.push_back(std::make_unique<AdamGroup>(rt, s.name,
                                                  s.fixed_rows > 0 ? s.fixed_rows
                                                  : s.per_anchor   ? anchor_rows
                                                                   : rows,
                                                  s.row_size));
}

AdamGroup& ParamGroups::named(const std::string& name) const {
  std::string names;
  for (const auto& g : groups_) {
    if (g->name() == name) return *g;
    names += (names.empty() ? "" : ", ") + g->name();
  }
  throw std::invalid_argument("no optimiser group '" + name + "' (" + names + ")");
}

void ParamGroups::gather(const std::vector<int>& rows, const std::vector<int>& anchor_rows) {
  for (size_t i = 0; i < groups_.size(); ++i)
    if (specs_[i].fixed_rows == 0) groups_[i]->gather(specs_[i].per_anchor ? anchor_rows : rows);
}

void ParamGroups::park() {
  for (auto& g : groups_) g->park();
}

void ParamGroups::unpark() {
  for (auto& g : groups_) g->unpark();
}

uint64_t ParamGroups::count_nonfinite(Adam& adam, const std::vector<GroupStep>& steps) const {
  adam.clear_nonfinite();
  for (const GroupStep& s : steps) {
    const AdamGroup& g = *groups_[s.index];
    if (s.cols >= 0)
      adam.accumulate_nonfinite_cols(*s.grad, g.rows(), g.row_size(), s.cols);
    else
      adam.accumulate_nonfinite(*s.grad, g.size());
  }
  return adam.read_nonfinite();
}

void ParamGroups::step(Adam& adam, const std::vector<GroupStep>& steps) const {
  for (const GroupStep& s : steps) {
    if (s.rows_on && s.cols >= 0)
      throw std::invalid_argument("adam: group '" + groups_[s.index]->name() +
                                  "' steps both some rows and some columns");
    if (s.rows_on)
      adam.step_visible(*groups_[s.index], *s.param, *s.grad, s.lr, *s.rows_on);
    else if (s.cols >= 0)
      adam.step_cols(*groups_[s.index], *s.param, *s.grad, s.lr, s.cols);
    else
      adam.step(*groups_[s.index], *s.param, *s.grad, s.lr);
  }
}

nlohmann::json ParamGroups::to_archive(ModelArchive& archive) const {
  nlohmann::json meta = nlohmann::json::object();
  for (const auto& g : groups_) {
    std::vector<float> v;
    const std::vector<int64_t> shape = {static_cast<int64_t>(g->rows()), g->row_size()};
    g->exp_avg().download(v, g->size());
    archive.put("adam/" + g->name() + "/exp_avg", v, shape);
    g->exp_avg_sq().download(v, g->size());
    archive.put("adam/" + g->name() + "/exp_avg_sq", v, shape);
    meta[g->name()] = {{"steps", g->steps()}, {"rows", g->rows()}, {"row_size", g->row_size()}};
  }
  return meta;
}

std::unique_ptr<ParamGroups> ParamGroups::from_archive(Runtime& rt, std::vector<ParamGroupSpec> specs,
                                                       const ModelArchive& archive, const nlohmann::json& meta,
                                                       size_t rows, size_t anchor_rows) {
  auto groups = std::make_unique<ParamGroups>(rt, std::move(specs), rows, anchor_rows);
  for (size_t i = 0; i < groups->size(); ++i) {
    AdamGroup& g = (*groups)[i];
    const std::string pre = "adam/" + g.name();
    const std::vector<int64_t> shape = {static_cast<int64_t>(g.rows()), g.row_size()};
    g.exp_avg().upload(archive.get<float>(pre + "/exp_avg", shape));
    g.exp_avg_sq().upload(archive.get<float>(pre + "/exp_avg_sq", shape));
    g.set_steps(meta.at(g.name()).at("steps").get<int64_t>());
  }
  return groups;
}

bool ParamGroups::step_if_finite(Adam& adam, const std::vector<GroupStep>& steps, int iteration, double loss,
                                 uint64_t* nonfinite) const {
  *nonfinite = count_nonfinite(adam, steps);
  if (*nonfinite > 0 || !std::isfinite(loss)) {
    spdlog::warn("iteration {}: {} non-finite gradient values (loss {}); step skipped", iteration, *nonfinite, loss);
    return false;
  }
  step(adam, steps);
  return true;
}

}  // namespace ag2gs
