// Stage 3 on a saved model (clusters over the anchor graph, language
// features per cluster): run_stage3_on_model.
#pragma once

#include <string>
#include <vector>

#include "host/device/cl_runtime.h"
#include "host/scene/scene.h"
#include "train/stage3/language.h"

namespace ag2gs {

// Stage 3 on a saved model: reads MODEL_DIR/model.ag2gs, takes its anchor
// graph (built when missing or stale), clusters the anchors
// (config.cluster), attaches CLIP language features from `views` when the
// scene has them (SemanticsKind::language_features; otherwise the clusters
// alone are stored and `language` is false), and replaces model.ag2gs
// atomically with the graph, clusters and language features added (earlier
// stage-3 entries are overwritten). Throws std::runtime_error naming the file
// when the model is missing or broken.
struct Stage3Summary {
  int clusters = 0;
  size_t components = 0, skipped_anchors = 0, anchors = 0;
  bool language = false;  // the scene had CLIP features
  int with_language = 0;  // clusters with a language feature
  double cluster_ms = 0, total_ms = 0;
  LanguageStats stats;
};
Stage3Summary run_stage3_on_model(Runtime& rt, Scene& scene, const std::string& model_dir,
                                  const std::vector<int>& views, const Stage3Config& config);

}  // namespace ag2gs
