// eval: the LERF-OVS protocol on a trained model (queries/query_eval.h):
// text queries for every labelled category of every label frame, click
// queries from a click list, IoU and boundary IoU per (frame, query) pair, a
// per-frame and mean table, timing per query, and a JSON report.
#include <spdlog/spdlog.h>

#include <chrono>
#include <cstdio>
#include <filesystem>
#include <memory>
#include <nlohmann/json.hpp>
#include <string>

#include "cli/commands.h"
#include "cli/run_guard.h"
#include "host/device/cl_runtime.h"
#include "host/io/model_io.h"
#include "host/io/semantic_io.h"
#include "host/scene/scene.h"
#include "queries/query.h"
#include "queries/query_eval.h"
#include "train/anchors/anchor_model.h"
#include "train/stage3/clustering.h"
#include "train/stage3/language.h"
#include "train/trainer.h"

namespace fs = std::filesystem;

namespace ag2gs::cli {
namespace {

struct EvalArgs {
  std::string model, scene, labels, vocab, clicks, out;
  double boundary_ratio = 0.02;
  bool no_grow = false;
  std::string click_by = "features";
  QueryConfig config;
  bool force = false;  // --force: replace an existing report
};

void cmd_eval(const GlobalOptions& global, EvalArgs a) {
  a.config.grow = !a.no_grow;
  a.config.validate();
  if (!(a.boundary_ratio > 0 && a.boundary_ratio < 1))
    throw std::invalid_argument("--boundary-ratio must lie in (0, 1) (0.02 of the image diagonal is the standard)");
  const auto t_load = std::chrono::steady_clock::now();
  const std::string model_file = (fs::path(a.model) / "model.ag2gs").string();
  {
    std::vector<std::string> inputs = {a.scene, a.labels, a.vocab, a.clicks};
    for (const char* f :
         {"model.ag2gs", "checkpoint.ag2gs", "point_cloud.ply", "point_cloud_objects.ply", "metrics.json"})
      inputs.push_back((fs::path(a.model) / f).string());
    refuse_output_over_inputs(a.out, inputs, "-o");
    refuse_output_in_inputs(a.out, a.scene, {a.model}, "-o");
    refuse_existing_results("-o", a.out, {}, a.force);
  }
  if (!fs::exists(model_file))
    throw std::runtime_error(a.model + ": no model.ag2gs; give a model folder written by `ag2gs train`");
  // Fail on an unwritable report before the work.
  const fs::path out_dir = fs::absolute(a.out).parent_path();
  fs::create_directories(out_dir);
  check_model_dir_writable(out_dir.string());

  const ModelArchive archive = read_model_archive(model_file);
  const AnchorModel model = check_model_archive(archive);
  if (!archive.meta.contains("clusters") || !archive.meta.contains("language"))
    throw std::runtime_error(model_file +
                             " has no clusters/language features, which the text queries need: run stage 3 on the "
                             "model (`ag2gs train SCENE_DIR -o MODEL_DIR --stages 3`)");
  const Clustering clustering = clustering_from_archive(archive, model.size());
  const LanguageFeatures language = language_from_archive(archive, clustering.clusters());
  const Vocabulary vocab = read_vocabulary(a.vocab);
  if (vocab.dim != language.dim)
    throw std::invalid_argument(a.vocab + ": embeddings of " + std::to_string(vocab.dim) + " dimensions, the language "
                                "features in " + model_file + " have " + std::to_string(language.dim) +
                                " (use the CLIP model that made the scene's features)");
  QueryEvalInputs in;
  in.frames = read_label_dir(a.labels);
  in.vocab = &vocab;
  if (!a.clicks.empty()) in.clicks = read_clicks(a.clicks);
  in.boundary_ratio = a.boundary_ratio;

  SceneOptions so;
  so.eval = true;
  std::unique_ptr<Scene> scene = Scene::open(a.scene, so);
  Runtime rt(global.device);
  QueryEngine engine(rt, model, a.config);
  engine.set_language(clustering, language);
  nlohmann::json how;
  if (a.click_by == "support") prepare_click(engine, a.click_by, archive.meta, *scene, &how);
  const double load_ms =
      std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t_load).count();
  spdlog::info("model {}: {} anchors, {} clusters ({} with language); {} label frames, {} clicks; region growing {}",
               model_file, model.size(), clustering.clusters(), language.with_language(), in.frames.size(),
               in.clicks.size(), a.config.grow ? "on" : "off (plain feature similarity)");

  const auto t_eval = std::chrono::steady_clock::now();
  const QueryEvalReport report = evaluate_queries(engine, *scene, in);
  const double eval_ms =
      std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t_eval).count();

  std::printf("%-16s %6s %8s %8s %6s %8s %8s\n", "frame", "text", "IoU", "BIoU", "click", "IoU", "BIoU");
  auto row = [](const std::string& name, const QueryEvalSummary& t, const QueryEvalSummary& c) {
    std::printf("%-16s %6d %8.2f %8.2f %6d %8.2f %8.2f\n", name.c_str(), t.count, 100 * t.mean_iou,
                100 * t.mean_biou, c.count, 100 * c.mean_iou, 100 * c.mean_biou);
  };
  for (const std::string& f : report.frames) row(f, report.summary("text", f), report.summary("click", f));
  const QueryEvalSummary text = report.summary("text"), click = report.summary("click");
  row("mean", text, click);
  std::printf("query time (selection + mask): text %.1f ms mean, %.1f ms max; click %.1f ms mean, %.1f ms max\n",
              text.mean_ms, text.max_ms, click.mean_ms, click.max_ms);
  if (!report.absent.empty()) {
    size_t none = 0;
    std::string missed;
    for (const AbsentPhrase& a : report.absent) {
      none += a.none;
      if (!a.none) missed += (missed.empty() ? " (selected something: \"" : ", \"") + a.phrase + "\"";
    }
    if (!missed.empty()) missed += ")";
    std::printf("absent phrases (in the vocabulary, in no label): %zu of %zu answered none%s\n", none,
                report.absent.size(), missed.c_str());
  }
  if (report.unscored_clicks > 0)
    spdlog::warn("{} click(s) not scored: no category, or no label file for their frame", report.unscored_clicks);

  nlohmann::json j = report.to_json();
  j["model"] = model_file;
  j["scene"] = a.scene;
  j["labels"] = a.labels;
  j["vocab"] = a.vocab;
  j["clicks_file"] = a.clicks;
  j["anchors"] = model.size();
  j["clusters"] = clustering.clusters();
  j["config"] = {{"grow", a.config.grow},
                 {"min_weight", a.config.min_weight},
                 {"tau", a.config.tau},
                 {"equivalent_feature_distance", a.config.equivalent_distance()},
                 {"graph_cell_scale", a.config.graph_cell_scale},
                 {"text_margin", a.config.text_margin},
                 {"text_threshold", a.config.text_threshold},
                 {"mask_threshold", a.config.mask_threshold},
                 {"click_candidates", a.config.click_candidates},
                 {"click_dominant", a.config.click_dominant},
                 {"click_front_weight", a.config.click_front_weight},
                 {"boundary_ratio", a.boundary_ratio}};
  j["click_by"] = a.click_by;
  if (how.contains("support_plane")) j["support_plane"] = how["support_plane"];
  j["timing_ms"] = {{"load_and_prepare", load_ms}, {"prepare", engine.prepare_ms()}, {"evaluation", eval_ms}};
  write_json_atomic(a.out, j);
  spdlog::info("wrote {} ({} text and {} click queries in {:.1f} s)", a.out, text.count, click.count, eval_ms / 1000);
}

}  // namespace

void register_eval(CLI::App& app, GlobalOptions& global) {
  auto a = std::make_shared<EvalArgs>();
  auto* e = app.add_subcommand("eval", "Score text and click queries against LERF-style labels (IoU, boundary IoU)");
  e->add_option("model", a->model, "Model folder written by `ag2gs train` with stage 3 (MODEL_DIR/model.ag2gs)")
      ->required();
  e->add_option("--scene", a->scene, "Scene directory the model was trained on (its cameras)")->required();
  e->add_option("--labels", a->labels, "Folder of <frame>.json label files (labelme polygons per category)")
      ->required();
  e->add_option("--vocab", a->vocab, "Text vocabulary JSON {\"category\": [D floats], ...}")->required();
  e->add_option("--clicks", a->clicks, "Click list JSON [{\"frame\", \"x\", \"y\", \"category\"}, ...]");
  e->add_option("-o,--out", a->out, "Report JSON to write")->check(output_path())->required();
  e->add_flag("--force", a->force, "Replace the report -o names when it exists (default: refused)");
  e->add_flag("--no-grow", a->no_grow,
              "Ablation: select by plain feature similarity to the seeds instead of region growing over the graph");
  add_query_config_options(e, a->config);
  e->add_option("--click-by", a->click_by,
                "Clicks select by the trained features (default) or by what stands on the scene's main plane "
                "(support: the rule of models trained without SAM masks)")
      ->check(CLI::IsMember({"features", "support"}));
  e->add_option("--boundary-ratio", a->boundary_ratio, "Boundary IoU width as a fraction of the diagonal (0.02)");
  set_action(e, [&global, a] { cmd_eval(global, *a); });
}

}  // namespace ag2gs::cli
