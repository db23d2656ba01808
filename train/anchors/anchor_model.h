// The stage-1 representation (docs/design.md section 2): anchors at voxel centres of
// a layered grid, each with a semantic feature and K child Gaussians whose
// parameters are stored raw (logits, offsets in voxel units) so that
//
//   mean    = pos + offset * l            (l = the anchor's voxel edge)
//   scale   = sigmoid(scale_logit) * scale_cap * l    (scale_cap 1, the paper's: a child never outgrows its voxel)
//   opacity = sigmoid(opacity_logit)
//   quat    = quat as stored (w x y z; the renderer normalises)
//   sh      = the first (d+1)^2 coefficients, d = the active SH degree
//   feature = the anchor's feature (children inherit it)
//
// Host-side ownership: the arrays here are the truth between training steps
// and on disk; train/anchors/expander.h holds their device copies and the expansion
// kernels. An anchor is identified by (layer, integer voxel cell); a hash map
// answers "is this voxel taken". Nothing here depends on hash-map iteration
// order: anchor order is fixed by the calls that create them.
#pragma once

#include <Eigen/Core>
#include <cstddef>
#include <cstdint>
#include <unordered_map>
#include <vector>

#include "host/core/gaussians.h"
#include "host/io/model_io.h"
#include "host/scene/scene.h"

namespace ag2gs {

// Coefficients per channel stored for every child: room for SH degree 3.
constexpr int kAnchorShCoeffs = 16;
// Voxel layers at most (4 bits of an anchor's voxel key).
constexpr int kMaxLayers = 16;

struct AnchorConfig {
  int children = 5;  // K child Gaussians per anchor
  int layers = 3;    // voxel layers, 0 = coarsest ("top")
  // Top-layer voxel edge: voxel_size (world units) when > 0, else the robust
  // extent / top_cells when top_cells > 0, else chosen from the scene's points
  // and training views (train/anchors/voxel_rule.h, the default).
  double voxel_size = 0;
  int top_cells = 0;
  int layer_ratio = 4;        // each layer is this much finer than the one above
  int init_layer = 0;         // first layer initialised from the SfM points; -1 = every layer
  int init_layers = 1;        // layers seeded from init_layer down (clipped at the finest); >= 1
  float init_opacity = 0.1f;  // opacity of a fresh child, in (0, 1)
  float init_scale = 0.5f;    // scale of a fresh child as a fraction of its voxel edge, in (0, scale_cap)
  // scale = sigmoid(logit) * scale_cap * l: 1 (the paper) keeps a child
  // inside its voxel; larger lets it cover what its voxel's neighbours
  // hold no anchors for (measured in the README, train section).
  float scale_cap = 1.f;
  // The cap holds on the coarsest scale_cap_layers layers (0 = top); finer
  // layers keep 1. Default: every layer.
  int scale_cap_layers = kMaxLayers;
  float init_feature = 0.05f;  // semantic features start uniform in [-init_feature, init_feature]
                               // (small and random: identical features would give the
                               // mask losses no direction to separate masks in); 0 = zero
  int sh_degree = 3;           // the highest SH degree training will use (0..3)
  // Children of the anchors seeded from SfM points sit on (up to K of) the
  // points of their voxel with those points' colours; false: random offsets
  // in the voxel and the voxel's mean colour for all.
  bool init_children_at_points = false;

  // The cap M of `layer`: scale_cap on the capped layers, 1 below them.
  float cap(int layer) const { return layer < scale_cap_layers ? scale_cap : 1.f; }

  // Throws std::invalid_argument naming the first field out of range.
  void validate() const;
};

// The layered voxel grid. Every layer shares `origin`; layer L has edge
// top_voxel / layer_ratio^L, so a cell of layer L+1 lies inside exactly one
// cell of layer L (parent_cell). Cells are integer coordinates relative to
// origin and may be negative (points outside the robust box still get cells).
struct VoxelGrid {
  Eigen::Vector3d origin = Eigen::Vector3d::Zero();  // corner of cell (0,0,0) on every layer
  double top_voxel = 1.0;                            // edge of a top-layer voxel
  int layer_ratio = 4;
  int layers = 3;

  // top_voxel = longest robust extent (bounds.hi - bounds.lo) / config.top_cells
  // and origin = bounds.lo (no margin: cells below lo are simply negative).
  // A degenerate box (all points in a plane or fewer) falls back to the
  // camera rig's diameter 2 * camera_radius as the extent; throws
  // std::invalid_argument when that is zero too.
  // With top_voxel > 0 that edge is used instead (choose_top_voxel's).
  static VoxelGrid from_bounds(const SceneBounds& bounds, const AnchorConfig& config, double top_voxel = 0);

  double voxel(int layer) const;  // edge length of layer `layer`
  // floor((p - origin) / voxel(layer)), each coordinate clamped to +-2^30.
  Eigen::Vector3i cell_of(int layer, const Eigen::Vector3d& p) const;
  Eigen::Vector3d centre(int layer, const Eigen::Vector3i& cell) const;
  // The cell of the coarser layer `to_layer` (<= layer) containing `cell`.
  Eigen::Vector3i parent_cell(int layer, const Eigen::Vector3i& cell, int to_layer) const;
  // Throws std::invalid_argument unless finite, top_voxel > 0, ratio >= 2, 1..16 layers.
  void validate() const;
};

// What initialise_from_points did, for logs.
struct AnchorInitStats {
  size_t points_used = 0;
  size_t points_skipped = 0;              // non-finite, or cells beyond +-kMaxAnchorCell
  std::vector<size_t> anchors_per_layer;  // [layers]
};

// Anchor cells must lie in [-kMaxAnchorCell, kMaxAnchorCell) on every axis
// (20 bits per axis in the 64-bit voxel key).
constexpr int kMaxAnchorCell = 1 << 19;
inline bool cell_in_range(const Eigen::Vector3i& c) {
  return (c.array() >= -kMaxAnchorCell).all() && (c.array() < kMaxAnchorCell).all();
}

class AnchorModel {
 public:
  AnchorModel() = default;

  // Replaces the model by anchors at the centres of the voxels occupied by
  // `points` on the init_layers layers from config.init_layer down (every
  // layer with init_layer -1), in (layer,
  // cell x, y, z) order. Every finite point counts, also those outside the
  // robust box (which only sizes the voxels). colors: [points] RGB 0..255 or
  // empty (grey).
  // Per anchor: SH DC = (mean colour of its points - 0.5) / C0, other SH 0;
  // feature uniform in [-init_feature, init_feature]. Per child: offset
  // uniform in [-0.5, 0.5]^3 (the child starts inside the voxel), scale =
  // init_scale * l, quat = identity + a perturbation of ~1e-2, normalised,
  // opacity = init_opacity. Random numbers come from a counter-based hash of
  // (seed, layer, cell, child, stream): the result depends on the point set
  // and the seed only, not on the point order.
  // Points from index `first_layer_only_from` on seed the first of those
  // layers only (the far shell's points: Trainer, docs/design.md 5.7).
  AnchorInitStats initialise_from_points(const std::vector<Eigen::Vector3d>& points,
                                         const std::vector<Eigen::Vector3<uint8_t>>& colors, const VoxelGrid& grid,
                                         const AnchorConfig& config, uint64_t seed,
                                         size_t first_layer_only_from = static_cast<size_t>(-1));
  // An empty model with this grid and config (anchors then come from add_anchor).
  void reset(const VoxelGrid& grid, const AnchorConfig& config);

  // Appends an anchor at (layer, cell) (its centre and edge from the grid)
  // and returns its id; -1 when that voxel already has an anchor or the cell
  // is outside +-kMaxAnchorCell. Children start as in initialise_from_points
  // (random offsets keyed by seed and cell, scale init_scale * l), except
  // that with parent_child >= 0 (a child row, anchor = parent_child / K) the
  // new anchor takes the parent anchor's feature and every new child the
  // parent child's SH and rotation, and its opacity capped at init_opacity
  // (five full copies of an opaque parent would stack up where it already
  // covers the surface): the growing step's "a finer anchor where this child
  // needs detail". parent_child = -1 gives
  // grey children with init_opacity and a random feature. With
  // parent_scale_divisor > 0 (and a parent), every new child takes the parent
  // child's world scale per axis divided by it instead of init_scale * l,
  // kept between init_scale * l and 0.9 x its cap (the split of section 3.3
  // in docs/design.md). Throws std::out_of_range for a bad layer or
  // parent_child.
  int add_anchor(int layer, const Eigen::Vector3i& cell, int64_t parent_child, uint64_t seed,
                 double parent_scale_divisor = 0);

  // Keeps the anchors with keep[a] != 0 (keep: [size()]) in their order and
  // drops the rest with their children. Returns the old id of every kept
  // anchor (new id r = old id result[r]), the row map AdamGroup::gather takes
  // (child_rows() turns it into the children's rows).
  std::vector<int> remove_anchors(const std::vector<uint8_t>& keep);

  // Anchor rows -> child rows: anchor r -> rows r*K .. r*K+K-1, -1 stays -1
  // for each child. For gathering per-child optimiser state.
  static std::vector<int> child_rows(const std::vector<int>& anchor_rows, int children);

  // The anchor id at (layer, cell), -1 when the voxel is empty.
  int find(int layer, const Eigen::Vector3i& cell) const;

  size_t size() const { return layer_.size(); }  // anchors A
  int children() const { return config_.children; }
  size_t gaussians() const { return size() * static_cast<size_t>(children()); }
  const AnchorConfig& config() const { return config_; }
  const VoxelGrid& grid() const { return grid_; }

  // Fixed geometry, one entry per anchor.
  const std::vector<float>& pos() const { return pos_; }        // [A,3] voxel centre
  const std::vector<int32_t>& layer() const { return layer_; }  // [A]
  const std::vector<int32_t>& cell() const { return cell_; }    // [A,3]
  const std::vector<float>& voxel() const { return voxel_; }    // [A]   edge l

  // Trained parameters. The mutable accessors let the trainer and the device
  // copies write values; sizes must not change (check() verifies).
  const std::vector<float>& feature() const { return feature_; }              // [A,3]
  const std::vector<float>& offset() const { return offset_; }                // [A*K,3] voxel units
  const std::vector<float>& scale_logit() const { return scale_logit_; }      // [A*K,3]
  const std::vector<float>& quat() const { return quat_; }                    // [A*K,4] w x y z
  const std::vector<float>& opacity_logit() const { return opacity_logit_; }  // [A*K]
  const std::vector<float>& sh() const { return sh_; }                        // [A*K,16,3] sh[(g*16+k)*3+c]
  std::vector<float>& feature() { return feature_; }
  std::vector<float>& offset() { return offset_; }
  std::vector<float>& scale_logit() { return scale_logit_; }
  std::vector<float>& quat() { return quat_; }
  std::vector<float>& opacity_logit() { return opacity_logit_; }
  std::vector<float>& sh() { return sh_; }

  // Throws std::logic_error naming the first array whose size disagrees with size().
  void check() const;

  // Stores every array under "anchors/..." and the config and grid under
  // meta["anchors"]; other entries of the archive are left alone.
  void to_archive(ModelArchive& archive) const;
  // Reads what to_archive wrote and validates it: config and grid, every
  // array's dtype and shape, layers and cells in range, no voxel taken twice,
  // pos and voxel equal to the grid's. Throws std::runtime_error naming the
  // archive and the array at fault.
  static AnchorModel from_archive(const ModelArchive& archive);

 private:
  void append_anchor(int layer, const Eigen::Vector3i& cell, uint64_t seed, const Eigen::Vector3d& dc_colour,
                     int64_t parent_child, double parent_scale_divisor = 0);
  void rebuild_index();

  struct KeyHash {
    size_t operator()(uint64_t key) const;
  };

  AnchorConfig config_;
  VoxelGrid grid_;
  std::vector<float> pos_, voxel_, feature_;
  std::vector<int32_t> layer_, cell_;
  std::vector<float> offset_, scale_logit_, quat_, opacity_logit_, sh_;
  std::unordered_map<uint64_t, int, KeyHash> index_;  // voxel key -> anchor id
};

// A uniform number in [0, 1) that is a pure function of its counter (seed,
// voxel key, child, stream): no generator state, no call order. The anchors'
// random initial values use streams 0..8; growing's recycling uses 16..18.
double anchor_uniform01(uint64_t seed, uint64_t voxel_key, int child, int stream);

// The 64-bit voxel key of (layer, cell): layer in the top 4 bits, then each
// coordinate + 2^19 in 20 bits. Injective on layer < 16, |cell| < 2^19; the
// keys order like (layer, x, y, z) tuples.
uint64_t anchor_voxel_key(int layer, const Eigen::Vector3i& cell);

// The expansion in double precision (layout of GaussianSet), the reference the
// device kernels are tested against.
struct ExpandedGaussians {
  int sh_degree = 0;
  std::vector<double> means;      // [N,3]
  std::vector<double> scales;     // [N,3]
  std::vector<double> quats;      // [N,4]
  std::vector<double> opacities;  // [N]
  std::vector<double> sh;         // [N,(d+1)^2,3]
  std::vector<double> features;   // [N,3]

  GaussianSet to_float() const;
};

// Gaussian g = a*K + i is child i of anchor a. active_sh_degree must be in
// 0..config().sh_degree (std::invalid_argument otherwise).
ExpandedGaussians expand_reference_double(const AnchorModel& model, int active_sh_degree);
// The same rounded once to float: the activated Gaussians (PLY export, tests).
GaussianSet expand_reference(const AnchorModel& model, int active_sh_degree);

}  // namespace ag2gs
