// Selecting an object as one library call (docs/design.md section 8): a
// click on a view or a phrase of a vocabulary, grown over the query graph of
// a trained model (queries/query.h), with the selection's Gaussians, the
// rest, and its masks in chosen views.
//
// `ag2gs query` calls select_object and writes what it returns
// (selection.ply, remainder.ply, selection.json, masks/); `remove` and
// `simulate` select with the same pieces (load_trained_model, run_query);
// the viewer, the Python module and the tests call them directly. Nothing
// here writes files.
#pragma once

#include <cstdint>
#include <memory>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "host/core/gaussians.h"
#include "host/device/cl_runtime.h"
#include "host/io/model_io.h"
#include "host/scene/scene.h"
#include "queries/query.h"
#include "train/anchors/anchor_model.h"
#include "train/stage3/clustering.h"
#include "train/stage3/language.h"

namespace ag2gs {

// A click or text query as `query`, `remove` and `simulate` take it.
struct QueryRequest {
  std::string view, click, text, vocab, text_embedding;
  std::string click_by = "auto";  // auto | features | support (prepare_click)
  bool by_click() const { return !click.empty(); }
  bool by_text() const { return !text.empty() || !text_embedding.empty(); }
};
// Throws std::invalid_argument unless exactly one well-formed query is given
// (messages name the `query` flags: --click, --view, --text, --vocab,
// --text-embedding).
void check_query_request(const QueryRequest& request);
// "X,Y" -> the clicked pixel (column, row); throws naming --click.
void parse_click(const std::string& text, double* x, double* y);

// A trained model folder as the selecting commands read it.
struct TrainedModel {
  std::string file;  // MODEL_DIR/model.ag2gs
  ModelArchive archive;
  AnchorModel model;
  int sh_degree = 0;   // the SH degree training had reached
  int resolution = 1;  // the training -r
  bool eval_split = true;
  Clustering clustering;  // stage 3's, when the model has them (with_language: required)
  LanguageFeatures language;
};
// Reads MODEL_DIR/model.ag2gs; with_language also its stage-3 clusters and
// language features, which a text query needs. Throws naming the file and
// the fix.
TrainedModel load_trained_model(const std::string& model_dir, bool with_language);
// The same from an archive in memory (`file` names it in messages): the
// live training view's snapshots.
TrainedModel trained_model_from_archive(ModelArchive archive, const std::string& file, bool with_language);

// The text query's embedding: the request's .npy or its phrase of the
// vocabulary; throws naming the file and the fix when it does not fit `dim`.
std::vector<float> load_query_embedding(const QueryRequest& request, const std::string& model_file, int dim);
// The embeddings of the vocabulary's other phrases (a text query by phrase):
// a cluster is the phrase's only if none of them describes it better
// (QueryEngine::text). Empty for a query by embedding.
std::vector<std::vector<float>> load_rival_embeddings(const QueryRequest& request);
// How a click selects (click_by): "features" grows over the trained
// features (queries/query.h); "support" takes what stands on the scene's
// main plane (a model trained without SAM masks has no features to grow
// over); "auto" is support when the model never trained features (its
// training stopped at stage 1) and the scene shows a floor, else features.
// Sets the engine's support plane when chosen, records the choice in
// (*j)["click_by"] and logs it. Throws naming the fix when "support" is asked
// for and the scene has no floor.
void prepare_click(QueryEngine& engine, const std::string& click_by, const nlohmann::json& model_meta,
                   const Scene& scene, nlohmann::json* j);
// Runs the query (a click maps its full-size pixel to the view's camera at
// -r `resolution`) and records it in j ("query", "seeds", text scores);
// *ms gets the query's latency. Returns the selected anchors.
std::vector<int32_t> run_query(QueryEngine& engine, const Scene& scene, const QueryRequest& request,
                               const std::vector<float>& embedding, int resolution, double text_margin,
                               nlohmann::json& j, double* ms);

// What ties a selection to the model it was made on: the hash of the
// anchors' layers and cells in order that the anchor graph keeps (16 hex
// digits). `query` writes it into selection.json as "anchor_fingerprint".
std::string anchor_fingerprint(const AnchorModel& model);

// train | test (every 8th image in name order) | all | comma-separated view
// names, as Scene::find_view reads them (which throws for an unknown one);
// empty: none.
std::vector<int> pick_scene_views(const Scene& scene, const std::string& views);

// One `ag2gs query`: the defaults are the program's.
struct SelectionRequest {
  std::string model;   // model folder (MODEL_DIR/model.ag2gs)
  std::string scene;   // the scene folder it was trained on
  std::string sparse;  // COLMAP model folder inside the scene; empty = the scene-folder rule
  int resolution = 0;  // 0 = the model's training -r
  QueryRequest query;
  QueryConfig config;
  std::string mask_views;  // pick_scene_views' form; a click's view always gets its mask
};

struct SelectionResult {
  std::string model_file;
  int resolution = 0;            // the -r the query ran at
  std::vector<int32_t> anchors;  // selected, ascending
  size_t model_anchors = 0;
  GaussianSet selection, remainder;  // the selected anchors' Gaussians and the rest's
  struct Mask {
    std::string view;  // the view's image name
    int width = 0, height = 0;
    std::vector<uint8_t> pixels;  // [H,W] 0/1
    size_t on = 0;                // pixels set
  };
  std::vector<Mask> masks;  // in the order of the request's views (the click's first when added)
  // selection.json without its file names: model, anchor_fingerprint, resolution, thresholds,
  // query (and click_by, seeds, text scores), anchors and counts;
  // "timing_ms" {load_and_prepare, prepare, query, masks, mask_views}.
  nlohmann::json record;
  double query_ms = 0;
};

// Loads the model and the scene, runs the query, cuts the model in two and
// draws the masks. Throws std::invalid_argument for a request that cannot
// run (no query or two, a click outside its image, an unknown view) and
// std::runtime_error naming the file for unreadable inputs, before the
// query runs.
SelectionResult select_object(Runtime& rt, const SelectionRequest& request);

}  // namespace ag2gs
