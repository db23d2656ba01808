// Evaluation of text and click queries against labelled frames, the
// LERF-OVS protocol (docs/design.md section 8):
//
// - text: every category present in every label frame is one query; its
//   embedding comes from the vocabulary, the selection from
//   QueryEngine::text, and its mask is rendered in that frame's view;
// - click: every click of the click list that names a category of its
//   frame's label is one query (QueryEngine::click at the clicked pixel);
// - each (frame, query) pair scores the IoU and the boundary IoU of its
//   predicted mask against the category's ground truth (the union of its
//   filled polygons); a missing prediction (a click on the background, an
//   empty selection) scores 0; the reported numbers are means over pairs.
//
// Masks are rendered at the label frame's size (the view's full-size camera
// scaled to it), so no resampling enters the score; click coordinates are in
// full-size image pixels and are scaled the same way.
//
// Boundary IoU (Cheng et al., CVPR 2021): with d = max(1, round(ratio *
// image diagonal)) (ratio 0.02), the boundary region of a mask is the mask
// minus its erosion by a (2d+1)x(2d+1) square, pixels outside the image
// counting as background (so a mask touching the border has a boundary
// there, as in the reference implementation's zero padding);
// BIoU = |B(P) & B(G)| / |B(P) | B(G)|.
#pragma once

#include <cstdint>
#include <map>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "host/io/semantic_io.h"
#include "host/scene/scene.h"
#include "queries/query.h"

namespace ag2gs {

// |P & G| / |P | G| of two 0/1 masks of the same size; 1 when both are empty.
// Throws std::invalid_argument when the sizes differ.
double mask_iou(const std::vector<uint8_t>& pred, const std::vector<uint8_t>& gt);
// max(1, round(ratio * sqrt(w^2 + h^2))).
int boundary_width(int width, int height, double ratio = 0.02);
// The boundary region of a 0/1 mask [H,W] at width d (see the file comment).
std::vector<uint8_t> mask_boundary(const std::vector<uint8_t>& mask, int width, int height, int d);
double boundary_iou(const std::vector<uint8_t>& pred, const std::vector<uint8_t>& gt, int width, int height,
                    double ratio = 0.02);

// One label file: its stem (label/<stem>.json) and contents.
struct NamedLabelFrame {
  std::string stem;
  LabelFrame frame;
};
// Every label/<stem>.json in `dir`, sorted by stem. Throws std::runtime_error
// naming the folder when it holds none.
std::vector<NamedLabelFrame> read_label_dir(const std::string& dir);

struct QueryEvalItem {
  std::string kind;      // "text" or "click"
  std::string frame;     // label stem
  std::string view;      // scene image name
  std::string category;
  double x = 0, y = 0;   // click, full-size image pixels
  bool predicted = false;  // false: no prediction (scores 0), see note
  std::string note;
  size_t selected_anchors = 0;
  int predicted_pixels = 0, gt_pixels = 0;
  double iou = 0, biou = 0;
  double select_ms = 0, mask_ms = 0;  // selection (text: once per category), mask rendering
};

struct QueryEvalSummary {
  int count = 0;
  double mean_iou = 0, mean_biou = 0;
  double mean_ms = 0, max_ms = 0;  // select + mask per query
};

// A vocabulary phrase no label frame has (a distractor): asked as a text
// query, the right answer is "none" (QueryEngine::text against the other
// phrases).
struct AbsentPhrase {
  std::string phrase;
  bool none = false;   // answered "nothing here"
  size_t anchors = 0;  // selected otherwise
  double best = 0;     // the phrase's best cosine
};

struct QueryEvalReport {
  std::vector<QueryEvalItem> items;
  std::vector<AbsentPhrase> absent;  // with a vocabulary: its phrases no frame labels
  std::vector<std::string> frames;  // label stems in order
  int unscored_clicks = 0;          // clicks without a category or label for their frame
  QueryEvalSummary summary(const std::string& kind, const std::string& frame = "") const;
  nlohmann::json to_json() const;
};

struct QueryEvalInputs {
  std::vector<NamedLabelFrame> frames;
  const Vocabulary* vocab = nullptr;  // text queries when set
  std::vector<Click> clicks;          // click queries
  double boundary_ratio = 0.02;
};

// Runs every query (see the file comment). The engine needs set_language()
// for text queries. Throws std::runtime_error naming the frame when a label
// frame names no view of the scene and std::invalid_argument naming the
// category when the vocabulary lacks it.
QueryEvalReport evaluate_queries(QueryEngine& engine, const Scene& scene, const QueryEvalInputs& inputs);

}  // namespace ag2gs
