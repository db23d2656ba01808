// Object removal as one library call (docs/design.md section 15): delete a
// selected object's anchors from a trained model, with the kept anchors it
// hid from every photo and the kept children that show it; find in every
// training view the hole it leaves and the target that fills it (classical
// inpainting, or an external inpainter's images); place fill anchors where
// the holes' rays meet the surfaces around them, optionally fine-tune them
// and their neighbours; and return the model without the object.
//
// `ag2gs remove` selects the object, calls remove_object and writes what it
// returns (model.ag2gs, point_cloud.ply, holes/, targets/, removal.json);
// the tests call it directly. Nothing here writes files.
#pragma once

#include <cstdint>
#include <functional>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "apps/backdrop.h"
#include "apps/removal/fill.h"
#include "apps/removal/holes.h"
#include "host/device/cl_runtime.h"
#include "host/io/model_io.h"
#include "host/scene/scene.h"
#include "train/anchors/anchor_model.h"

namespace ag2gs {

// How to remove; the defaults are `ag2gs remove`'s.
struct RemovalSettings {
  InpaintMethod inpaint = InpaintMethod::kTelea;  // the holes' targets, without external images
  // Fine-tuning iterations: 0 by default. Measured on the removal benchmark
  // (docs/benchmarks.md, "Object removal: fill and fine-tune"): the fill's
  // colours, an upper quantile by brightness of the inpainted targets of the
  // views that see its voxel, score higher at the test views than the same
  // fill tuned to the per-view targets (100 or 300 iterations), which differ
  // from view to view. An inpainter that agrees across views is what a
  // fine-tune needs.
  int iters = 0;
  bool fill_holes = true;    // false: delete only (no fill anchors, no fine-tune)
  bool clear_stray = true;   // clear kept children among the object's Gaussians with its colour
  float stray_colour = 0.2f;
  int stray_reach = 3;       // finest-layer voxels
  bool clear_hidden = true;  // remove kept anchors the views saw only through the object
  double hidden_fraction = 0.1;
  bool tune_to_fill = false;  // fine-tune the holes towards the filled model's render, not the targets
  FillSettings fill;
  HoleSettings holes;
  uint64_t seed = 1;
  // Throws std::invalid_argument naming the `remove` flag.
  void validate() const;
  // The settings as `ag2gs remove --print-config` prints them.
  nlohmann::json to_json() const;
};

struct RemovalRequest {
  ObjectInModel object;  // the model, its scene (at the resolution used) and the selection
  RemovalSettings settings;
  // An external inpainter's image for training view i (scene->train_views()[i]),
  // [H,W,3] in 0..1 at the view's size; empty function: settings.inpaint.
  std::function<std::vector<float>(size_t i)> inpainted;
  // Called once per training view i with its hole and target (what holes/ and
  // targets/ hold), in order, as soon as they are found.
  std::function<void(size_t i, const ViewHole& hole, const std::vector<float>& target)> on_view;
  // Called between views and fine-tune iterations with what is running; it
  // may throw to stop the removal (Ctrl-C).
  std::function<void(const std::string& during)> check_stop;
};

struct RemovalResult {
  AnchorModel model;      // without the object, with the fill
  ModelArchive archive;   // the model with the input's sky, training record, clusters and language features
  size_t kept_anchors = 0, added_anchors = 0;
  // removal.json's record of the removal: counts, settings, per-view holes,
  // "seconds" {hidden, holes, fill_and_fine_tune} (the caller adds the rest).
  nlohmann::json report;
};

// Throws std::invalid_argument for a request that cannot be run (no model,
// a selection of another size, none or every anchor selected).
RemovalResult remove_object(Runtime& rt, const RemovalRequest& request);

// The archive after a removal: `result`'s anchors, and of `in` the training
// record, the sky, and stage 3's clusters and language features, where
// anchor r of `result` takes the cluster of the old anchor source[r] (a kept
// anchor its own, a fill anchor the one it grew from; a cluster may become
// empty). The stage-2 graph is left out: it described the old anchors.
ModelArchive archive_after_removal(const ModelArchive& in, const AnchorModel& result, const std::vector<int>& source);

}  // namespace ag2gs
