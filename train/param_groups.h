// The optimiser groups of a trainer, written once: a table of (name, row
// size, rows per child or per anchor) that creates the Adam state, finds a
// group by name, follows the rows when growth or densification changes
// them, and saves and restores the moments in a checkpoint. Both trainers
// (train/trainer.h, train/baseline/free_trainer.h) keep their groups here; a step
// binds each group to its parameter and gradient buffers and learning rate
// (GroupStep) and runs the non-finite check and the updates over that list.
#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "host/io/model_io.h"
#include "host/optim/adam.h"

namespace ag2gs {

struct ParamGroupSpec {
  const char* name;
  int row_size;
  bool per_anchor = false;  // one row per anchor (else one per Gaussian)
  size_t fixed_rows = 0;    // > 0: this many rows whatever the model (the sky); growth leaves them
};

// One update: group `index` of the table steps `param` with `grad` at `lr`.
struct GroupStep {
  size_t index;
  DeviceBuffer* param;
  const DeviceBuffer* grad;
  double lr;
  // When set: [rows] ints, and only the rows with a nonzero entry change
  // (Adam::step_visible); the others keep their values and moments bit
  // for bit (the removal's fine-tune freezes what lies far from the hole).
  const DeviceBuffer* rows_on = nullptr;
  // >= 0: only the first `cols` values of each row step and are checked
  // (Adam::step_cols): the SH coefficients of degrees not yet switched on
  // have zero gradients and zero moments, so leaving them out keeps the
  // bits. -1: the whole row. Not combined with rows_on.
  int cols = -1;
};

class ParamGroups {
 public:
  // Zero moments for `rows` Gaussians and `anchor_rows` anchors.
  ParamGroups(Runtime& rt, std::vector<ParamGroupSpec> specs, size_t rows, size_t anchor_rows);

  size_t size() const { return groups_.size(); }
  AdamGroup& operator[](size_t i) const { return *groups_[i]; }
  const ParamGroupSpec& spec(size_t i) const { return specs_[i]; }
  // Throws std::invalid_argument listing the names when there is no such group.
  AdamGroup& named(const std::string& name) const;

  // Rows follow a change of the model: per-Gaussian groups take
  // `rows`, per-anchor groups `anchor_rows` (AdamGroup::gather).
  void gather(const std::vector<int>& rows, const std::vector<int>& anchor_rows);
  // Every group's AdamGroup::park / unpark.
  void park();
  void unpark();

  // The number of non-finite values in the gradients of `steps` (one read
  // back: a trainer skips the whole step when it is not 0).
  uint64_t count_nonfinite(Adam& adam, const std::vector<GroupStep>& steps) const;
  // Every update of `steps`.
  void step(Adam& adam, const std::vector<GroupStep>& steps) const;
  // The trainers' step rule: when a gradient of `steps` holds a non-finite
  // value or `loss` is not finite, nothing changes and one warning names
  // the iteration (*nonfinite: the count); else every update runs. Returns
  // whether the parameters were stepped.
  bool step_if_finite(Adam& adam, const std::vector<GroupStep>& steps, int iteration, double loss,
                      uint64_t* nonfinite) const;

  // The moments as adam/<name>/exp_avg and exp_avg_sq, and the step counts
  // and shapes in the returned JSON object (keyed by name).
  nlohmann::json to_archive(ModelArchive& archive) const;
  // The inverse, for a model of `rows` Gaussians and `anchor_rows` anchors:
  // throws (nlohmann::json or std::runtime_error) when an entry is missing
  // or has another shape; `meta` is what to_archive returned.
  static std::unique_ptr<ParamGroups> from_archive(Runtime& rt, std::vector<ParamGroupSpec> specs,
                                                   const ModelArchive& archive, const nlohmann::json& meta, size_t rows,
                                                   size_t anchor_rows);

 private:
  std::vector<ParamGroupSpec> specs_;
  std::vector<std::unique_ptr<AdamGroup>> groups_;
};

}  // namespace ag2gs
