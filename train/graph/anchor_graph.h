// The anchor graph of stage 2 (docs/design.md section 6): a sparse, symmetric
// graph over the anchors of an AnchorModel, built from the voxel structure.
//
// Neighbourhood cells: the top-layer voxel grid coarsened by an integer
// factor `cell_scale` (1 = the top-layer voxel itself; the click query of a
// later stage uses 2). Every anchor, whatever its layer, belongs to exactly
// one neighbourhood cell: floor(top-layer cell / cell_scale) per axis, the
// top-layer cell being VoxelGrid::parent_cell(layer, cell, 0), integer
// arithmetic only. Anchors i != j are joined when their neighbourhood cells
// are equal (intra-voxel edges) or 26-neighbours, i.e. differ by at most 1 on
// every axis (inter-voxel edges).
//
// Storage: CSR over anchor ids, symmetric (j in row i <=> i in row j), every
// row sorted ascending, no self loops, no duplicates. An undirected edge
// appears twice (once per row), so entries() = 2 * edges(). The result
// depends on the anchors' (layer, cell) lists and the grid's layer ratio
// only, never on hash-table order: the same model gives the same bytes.
//
// Rebuild whenever anchors are added, removed or reordered (after every
// growing/pruning round): anchor ids are row indices. matches(model) tells
// whether a graph still describes a model.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include "host/io/model_io.h"
#include "train/anchors/anchor_model.h"

namespace ag2gs {

class AnchorGraph {
 public:
  AnchorGraph() = default;

  // Builds the graph of `model` (see the file comment). cell_scale must lie
  // in 1..1024 (std::invalid_argument otherwise). Cost: one hash of the
  // occupied neighbourhood cells, then per cell one merge of its 27
  // neighbouring cells' anchor lists; O(entries) memory.
  static AnchorGraph build(const AnchorModel& model, int cell_scale = 1);

  size_t anchors() const { return row_offsets_.empty() ? 0 : row_offsets_.size() - 1; }
  size_t entries() const { return neighbours_.size(); }    // directed entries, 2 * edges()
  size_t edges() const { return neighbours_.size() / 2; }  // undirected edges |E|
  int cell_scale() const { return cell_scale_; }

  const std::vector<int32_t>& row_offsets() const { return row_offsets_; }  // [A+1], row i = [off[i], off[i+1])
  const std::vector<int32_t>& neighbours() const { return neighbours_; }    // [entries] ascending per row
  int degree(size_t i) const { return row_offsets_[i + 1] - row_offsets_[i]; }

  // Histogram of degrees in power-of-two bins: bin 0 counts degree 0, bin b
  // (b >= 1) degrees in [2^(b-1), 2^b). Trailing empty bins are dropped.
  std::vector<int64_t> degree_histogram() const;

  // FNV-1a 64 over the model's layer ratio, anchor count, layers and cells:
  // what the graph was built from. matches() compares it and the count.
  static uint64_t anchor_fingerprint(const AnchorModel& model);
  uint64_t fingerprint() const { return fingerprint_; }
  bool matches(const AnchorModel& model) const;

  // Throws std::logic_error naming the first violation of the CSR contract
  // (offsets, range, order, self loops, symmetry). `who` prefixes the message.
  void validate(const std::string& who = "anchor graph") const;

  // Stores "graph/row_offsets" [A+1] i32, "graph/neighbours" [entries] i32 and
  // meta["graph"] = {format, cell_scale, anchors, entries, fingerprint}; other
  // entries are left alone.
  void to_archive(ModelArchive& archive) const;
  static bool in_archive(const ModelArchive& archive) { return archive.meta.contains("graph"); }
  // Reads and validates what to_archive wrote (validate() plus meta vs array
  // shapes). Throws std::runtime_error naming the archive's file and the fault.
  static AnchorGraph from_archive(const ModelArchive& archive);

  bool operator==(const AnchorGraph& o) const {
    return cell_scale_ == o.cell_scale_ && fingerprint_ == o.fingerprint_ && row_offsets_ == o.row_offsets_ &&
           neighbours_ == o.neighbours_;
  }

 private:
  int cell_scale_ = 1;
  uint64_t fingerprint_ = 0;
  std::vector<int32_t> row_offsets_{0};
  std::vector<int32_t> neighbours_;
};

}  // namespace ag2gs
