// query: select an object of a trained model by a click or by text
// (apps/selection/selection.h: select_object) and write its Gaussians, the
// rest, a JSON summary and the selection's masks in the requested views.
#include <spdlog/spdlog.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <memory>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <set>
#include <sstream>
#include <string>

#include "cli/commands.h"
#include "cli/object_selection.h"
#include "cli/run_guard.h"
#include "cli/setting_options.h"
#include "host/core/timing.h"
#include "host/device/cl_runtime.h"
#include "host/io/atomic_file.h"
#include "host/io/model_io.h"
#include "host/io/npy_io.h"
#include "host/io/output_set.h"
#include "host/io/ply_io.h"
#include "host/io/semantic_io.h"
#include "host/scene/scene.h"
#include "host/scene/scene_up.h"
#include "queries/query.h"
#include "queries/query_settings.h"
#include "train/anchors/anchor_model.h"
#include "train/stage3/clustering.h"
#include "train/stage3/language.h"

namespace fs = std::filesystem;

namespace ag2gs::cli {
namespace {

struct QueryArgs {
  SelectionRequest request;  // the model, the scene, the query, the mask views, the settings
  std::string out;
  bool force = false;  // --force: replace the results of an earlier query in OUT
};

}  // namespace

std::vector<uint8_t> encode_mask_png(const std::vector<uint8_t>& mask, int width, int height) {
  cv::Mat img(height, width, CV_8UC1);
  for (int y = 0; y < height; ++y)
    for (int x = 0; x < width; ++x) img.at<uint8_t>(y, x) = mask[static_cast<size_t>(y) * width + x] ? 255 : 0;
  std::vector<uint8_t> bytes;
  if (!cv::imencode(".png", img, bytes)) throw std::runtime_error("could not encode the mask as PNG");
  return bytes;
}

void write_mask_png(const std::string& path, const std::vector<uint8_t>& mask, int width, int height) {
  const std::vector<uint8_t> bytes = encode_mask_png(mask, width, height);
  AtomicFile f(path);
  f.write(bytes.data(), bytes.size());
  f.commit();
}

namespace {

void cmd_query(const GlobalOptions& global, QueryArgs a) {
  SelectionRequest& r = a.request;
  check_query_request(r.query);
  r.config.validate();
  refuse_output_in_inputs(a.out, r.scene, {r.model}, "-o");
  refuse_file_as_output_folder(a.out, "-o");
  finish_interrupted_output_sets(a.out);  // a killed run's last commit, finished
  std::vector<std::string> old_masks;     // an earlier selection's, replaced or deleted together with it
  {
    std::vector<std::string> files = {"selection.json", "selection.ply", "remainder.ply"};
    std::error_code ec;
    if (fs::is_directory(fs::path(a.out) / "masks", ec))
      for (const auto& e : fs::directory_iterator(fs::path(a.out) / "masks", ec))
        files.push_back("masks/" + e.path().filename().string());
    refuse_existing_results("-o", a.out, files, a.force);
    old_masks.assign(files.begin() + 3, files.end());
  }
  Runtime rt(global.device);
  SelectionResult sel = select_object(rt, r);
  std::printf("query latency: %.1f ms (after the model was loaded); %zu of %zu anchors selected\n", sel.query_ms,
              sel.anchors.size(), sel.model_anchors);

  // Outputs: the selection's files go into place together, at the end.
  const auto t_out = std::chrono::steady_clock::now();
  fs::create_directories(fs::path(a.out) / "masks");
  OutputSet written(a.out);
  write_ply((fs::path(a.out) / "selection.ply").string(), sel.selection, true);
  write_ply((fs::path(a.out) / "remainder.ply").string(), sel.remainder, true);
  nlohmann::json& j = sel.record;
  j["timing_ms"]["ply"] = ms_since(t_out);
  std::vector<std::string> names;
  for (const SelectionResult::Mask& m : sel.masks) names.push_back(m.view);
  const std::vector<std::string> stems = output_stems(names);  // a/1.jpg and b/1.jpg: a_1.png, b_1.png
  nlohmann::json masks = nlohmann::json::array();
  for (size_t i = 0; i < sel.masks.size(); ++i) {
    const SelectionResult::Mask& m = sel.masks[i];
    write_mask_png((fs::path(a.out) / "masks" / (stems[i] + ".png")).string(), m.pixels, m.width, m.height);
    masks.push_back({{"view", m.view}, {"file", "masks/" + stems[i] + ".png"}, {"pixels", m.on}});
  }
  j["masks"] = masks;
  AtomicFile f((fs::path(a.out) / "selection.json").string());
  f.write(j.dump(2) + "\n");
  f.commit();
  for (const std::string& m : old_masks)
    if (std::find_if(masks.begin(), masks.end(), [&](const nlohmann::json& x) { return x["file"] == m; }) ==
        masks.end())
      written.remove_at_commit((fs::path(a.out) / m).string());
  written.commit();
  spdlog::info("wrote {}: selection.ply ({} Gaussians), remainder.ply ({}), selection.json, {} mask(s) in {:.0f} ms",
               a.out, sel.selection.size(), sel.remainder.size(), sel.masks.size(),
               j["timing_ms"]["masks"].get<double>());
}

}  // namespace

void add_query_config_options(CLI::App* sub, QueryConfig& c) {
  add_setting_options(sub, query_settings(), c);
}

void add_query_request_options(CLI::App* sub, QueryRequest& r) {
  sub->add_option("--view", r.view, "Click query: the clicked image (name, name without extension or stem)");
  sub->add_option("--click", r.click, "Click query: X,Y pixel (column,row) of the full-size image file");
  sub->add_option("--text", r.text, "Text query: a phrase of the --vocab file")
      ->check(CLI::Validator(
          [](std::string& v) {
            return v.find_first_not_of(" \t") == std::string::npos
                       ? std::string("the phrase is empty; give one listed in the --vocab file, e.g. --text "
                                     "\"red mug\"")
                       : std::string();
          },
          "PHRASE"));
  sub->add_option("--vocab", r.vocab, "Text vocabulary JSON {\"phrase\": [D floats], ...}");
  sub->add_option("--text-embedding", r.text_embedding, "Text query by a float vector .npy of shape [D] or [1,D]");
  sub->add_option("--click-by", r.click_by,
                  "How a click selects: features (grow over trained features), support (what stands on the "
                  "scene's main plane, for models trained without SAM masks), auto (support when the model has "
                  "no trained features)")
      ->check(CLI::IsMember({"auto", "features", "support"}));
}

void register_query(CLI::App& app, GlobalOptions& global) {
  auto a = std::make_shared<QueryArgs>();
  auto* q = app.add_subcommand("query", "Select an object by a click or by text; write its Gaussians and masks");
  q->add_option("model", a->request.model, "Model folder written by `ag2gs train` (MODEL_DIR/model.ag2gs)")->required();
  q->add_option("--scene", a->request.scene, "Scene directory (images/, sparse/0/) the model was trained on")
      ->required();
  q->add_option("-o,--out", a->out, "Output folder: selection.ply, remainder.ply, selection.json, masks/")
      ->check(output_path())
      ->required();
  add_query_request_options(q, a->request.query);
  q->add_flag("--force", a->force,
              "Replace the results of an earlier query in OUT (default: refused, so a second query does not "
              "overwrite the first)");
  q->add_option("--views", a->request.mask_views,
                "Also write masks for: train, test (every 8th image in name order), all, or comma-separated names");
  q->add_option("--sparse", a->request.sparse,
                "COLMAP model folder inside the scene (default: sparse/0/, else sparse/ when it holds the model)");
  q->add_option("-r,--resolution", a->request.resolution, "Divide the cameras by R (default: the model's training -r)")
      ->check(CLI::Range(1, 64));
  add_query_config_options(q, a->request.config);
  auto print_config = add_print_config_flag(q, "query");
  set_action(q, [&global, a, print_config] {
    if (*print_config) return print_config_json(a->request.config);
    cmd_query(global, *a);
  });
}

}  // namespace ag2gs::cli
