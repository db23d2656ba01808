#include "cli/object_selection.h"

#include <spdlog/spdlog.h>
#include <unistd.h>

#include <cerrno>
#include <csignal>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <stdexcept>
#include <system_error>

#include "cli/run_guard.h"
#include "host/io/json_input.h"
#include "train/graph/anchor_graph.h"

namespace fs = std::filesystem;

namespace ag2gs::cli {

fs::path check_new_output_folder(const std::string& out_arg, const std::string& model_arg) {
  fs::path out = fs::absolute(out_arg).lexically_normal();
  if (!out.has_filename()) out = out.parent_path();
  if (path_is_within(out.string(), model_arg))
    throw std::invalid_argument(
        "-o " + out_arg +
        (path_is_within(model_arg, out.string()) ? " is the model folder itself" : " lies inside the model folder") +
        "; write the result to a new folder outside it");
  if (fs::exists(out) && !(fs::is_directory(out) && fs::is_empty(out)))
    throw std::invalid_argument("-o " + out_arg + " exists and is not empty; give a new folder (nothing was written)");
  return out;
}

namespace {

// Folders "<out>.partial.<pid>" that runs killed with SIGKILL (or by a power
// cut) left beside OUT_DIR: their process is gone, so nobody else removes
// them. Live processes' folders stay.
void remove_stale_partial_folders(const fs::path& out) {
  const std::string prefix = out.filename().string() + ".partial.";
  std::error_code ec;
  for (fs::directory_iterator it(out.parent_path(), ec), end; !ec && it != end; it.increment(ec)) {
    const std::string name = it->path().filename().string();
    if (name.rfind(prefix, 0) != 0) continue;
    const std::string digits = name.substr(prefix.size());
    if (digits.empty() || digits.size() > 7 || digits.find_first_not_of("0123456789") != std::string::npos) continue;
    const long pid = std::strtol(digits.c_str(), nullptr, 10);
    if (pid <= 0 || pid == static_cast<long>(::getpid())) continue;
    if (::kill(static_cast<pid_t>(pid), 0) == 0 || errno != ESRCH) continue;  // ESRCH: no such process
    std::error_code rm;
    if (!it->is_directory(rm)) continue;
    fs::remove_all(it->path(), rm);
    if (!rm) spdlog::info("removed {}, left by an interrupted run", it->path().string());
  }
}

}  // namespace

StagedFolder::StagedFolder(const fs::path& out, const std::string& out_arg)
    : out_(out),
      tmp_(out.parent_path() / (out.filename().string() + ".partial." + std::to_string(::getpid()))),
      out_arg_(out_arg) {
  remove_stale_partial_folders(out_);
  std::error_code ec;
  fs::remove_all(tmp_, ec);
  fs::create_directories(tmp_);
}

StagedFolder::~StagedFolder() {
  if (committed_) return;
  std::error_code ec;
  fs::remove_all(tmp_, ec);
}

void StagedFolder::stop_if_interrupted(const std::string& during) {
  if (!InterruptGuard::interrupted()) return;
  std::error_code ec;
  fs::remove_all(tmp_, ec);
  spdlog::warn("{} during {}: nothing was written ({} does not exist); run the command again",
               InterruptGuard::signal_name(), during, out_arg_);
  InterruptGuard::exit_after_saving();
}

void StagedFolder::commit() {
  stop_if_interrupted("writing");
  if (fs::exists(out_)) fs::remove(out_);  // an empty folder (check_new_output_folder)
  fs::rename(tmp_, out_);
  committed_ = true;
}

std::vector<int32_t> read_selection_file(const std::string& path, const AnchorModel& model) {
  const size_t anchors = model.size();
  if (!std::ifstream(path))
    throw std::runtime_error(path + ": cannot be read (give the selection.json that `ag2gs query` wrote)");
  const nlohmann::json j = read_json_file(path);
  if (!j.is_object() || !j.contains("anchors") || !j["anchors"].is_array())
    throw std::runtime_error(path + ": no \"anchors\" list; give the selection.json that `ag2gs query` wrote");
  if (j.contains("anchor_fingerprint")) {
    const std::string mine = anchor_fingerprint(model);
    if (!j["anchor_fingerprint"].is_string() || j["anchor_fingerprint"].get<std::string>() != mine)
      throw std::runtime_error(path + ": made on another model (anchor fingerprint " + j["anchor_fingerprint"].dump() +
                               ", this model's \"" + mine + "\"); query this model again");
  }
  std::vector<int32_t> out;
  for (const auto& v : j["anchors"]) {
    if (!v.is_number_integer() || v.get<int64_t>() < 0 || v.get<int64_t>() >= static_cast<int64_t>(anchors))
      throw std::runtime_error(path + ": anchor id " + v.dump() + " is not one of the model's " +
                               std::to_string(anchors) + " anchors (was the selection made on another model?)");
    out.push_back(v.get<int32_t>());
  }
  return out;
}

void check_selection_request(const QueryRequest& request, const std::string& selection_file) {
  const bool by_selection = !selection_file.empty();
  if (by_selection && (request.by_click() || request.by_text()))
    throw std::invalid_argument("give either --selection FILE or a query (--click / --text), not both");
  if (!by_selection) check_query_request(request);
  if (by_selection && !(request.view.empty() && request.vocab.empty()))
    throw std::invalid_argument("--view and --vocab belong to a click or text query, not to --selection");
}

SelectedObject select_object(Runtime& rt, const OpenedModel& opened, const ObjectArgs& a, nlohmann::json& report,
                             const std::string& action) {
  const TrainedModel& tm = opened.tm;
  const Scene& scene = *opened.scene;
  const QueryRequest& request = a.request;
  const std::string& selection_file = a.selection;
  const QueryConfig& config = a.config;
  report["model"] = tm.file;
  report["scene"] = a.scene;
  report["resolution"] = a.resolution;
  const AnchorModel& model = tm.model;
  std::vector<int32_t> selected;
  SelectedObject out;
  if (!selection_file.empty()) {
    selected = read_selection_file(selection_file, model);
    report["query"] = {{"type", "selection"}, {"file", selection_file}};
  } else {
    QueryEngine engine(rt, model, config);
    if (request.by_text()) engine.set_language(tm.clustering, tm.language);
    if (request.by_click()) prepare_click(engine, request.click_by, tm.archive.meta, scene, &report);
    selected =
        run_query(engine, scene, request, opened.embedding, a.resolution, config.text_margin, report, &out.query_ms);
  }
  out.anchors.assign(model.size(), 0);
  for (int32_t s : selected) out.anchors[s] = 1;
  for (uint8_t b : out.anchors) out.count += b;
  if (out.count == 0 && report.value("none", false))
    throw std::runtime_error("\"" + request.text + "\" names nothing in this model (another phrase of " +
                             request.vocab + " describes every object better): nothing to " + action +
                             " (try another phrase; `ag2gs query` shows what a query selects)");
  if (out.count == 0)
    throw std::runtime_error("the query selected no anchor: nothing to " + action +
                             " (try another click or phrase; `ag2gs query` shows what a query selects)");
  return out;
}

void add_object_options(CLI::App* cmd, ObjectArgs& a, const std::string& verb, const std::string& out_help) {
  cmd->add_option("model", a.model, "Model folder written by `ag2gs train` (MODEL_DIR/model.ag2gs)")->required();
  cmd->add_option("--scene", a.scene, "Scene directory (images/, sparse/0/) the model was trained on")->required();
  cmd->add_option("-o,--out", a.out, out_help)->check(output_path())->required();
  add_query_request_options(cmd, a.request);
  cmd->add_option("--selection", a.selection, verb + " the anchors of a selection.json written by `ag2gs query`");
  cmd->add_option("-r,--resolution", a.resolution, "Divide the cameras by R (default: the model's training -r)")
      ->check(CLI::Range(1, 64));
  cmd->add_option("--sparse", a.sparse,
                  "COLMAP model folder inside the scene (default: sparse/0/, else sparse/ when it holds the model)");
  add_query_config_options(cmd, a.config);
}

OpenedModel open_model_and_scene(const std::string& model_dir, const std::string& scene_dir, int& resolution,
                                 const std::string& sparse, const QueryRequest& request,
                                 const std::string& selection_file) {
  const bool by_text = selection_file.empty() && request.by_text();
  OpenedModel o;
  o.tm = load_trained_model(model_dir, by_text);
  if (resolution == 0) resolution = o.tm.resolution;
  SceneOptions so;
  so.resolution = resolution;
  so.eval = o.tm.eval_split;
  so.sparse = sparse;
  o.scene = Scene::open(scene_dir, so);
  if (by_text) o.embedding = load_query_embedding(request, o.tm.file, o.tm.language.dim);
  return o;
}

ObjectInModel object_in_model(const OpenedModel& opened, const SelectedObject& sel) {
  ObjectInModel o;
  o.model_file = opened.tm.file;
  o.archive = &opened.tm.archive;
  o.model = &opened.tm.model;
  o.sh_degree = opened.tm.sh_degree;
  o.scene = opened.scene.get();
  o.selected = sel.anchors;
  return o;
}

}  // namespace ag2gs::cli
