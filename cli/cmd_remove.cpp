// remove: select an object as `query` does, remove it (apps/removal/removal.h:
// delete its anchors, find the holes and their targets, fill and fine-tune),
// and write the model without the object as a complete model folder, with
// holes/, targets/ and removal.json (docs/design.md section 15).
#include <spdlog/spdlog.h>

#include <chrono>
#include <filesystem>
#include <memory>
#include <nlohmann/json.hpp>
#include <string>

#include "apps/removal/removal.h"
#include "apps/removal/removal_settings.h"
#include "cli/commands.h"
#include "cli/object_selection.h"
#include "cli/run_driver.h"
#include "cli/run_guard.h"
#include "cli/setting_options.h"
#include "host/device/cl_runtime.h"
#include "host/io/atomic_file.h"
#include "host/io/image_io.h"
#include "host/io/model_io.h"
#include "host/io/model_ply.h"
#include "host/io/ply_io.h"
#include "host/render/sky.h"
#include "host/scene/scene.h"
#include "queries/query.h"
#include "train/train_common.h"

namespace fs = std::filesystem;

namespace ag2gs::cli {
namespace {

double seconds_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

struct RemoveArgs {
  ObjectArgs obj;
  std::string inpainted;
  RemovalSettings settings;  // the flags set its fields (apps/removal/removal_settings.h)
};

// The image an external inpainter wrote for `view`: DIR/<stem>.png (`stem`:
// the view's name in holes/ and targets/, output_stems), exactly the size the
// view is rendered at. Returns [H,W,3] in 0..1.
std::vector<float> read_inpainted(const std::string& dir, const SceneView& view, const std::string& stem) {
  const fs::path path = fs::path(dir) / (stem + ".png");
  if (!fs::exists(path))
    throw std::runtime_error("--inpainted " + dir + ": " + path.filename().string() + " is missing (one " +
                             std::to_string(view.camera.width) + "x" + std::to_string(view.camera.height) +
                             " PNG per training view, named after the view)");
  int width = 0, height = 0;
  std::vector<float> rgb = read_rgb(path.string(), width, height);
  if (width != view.camera.width || height != view.camera.height)
    throw std::runtime_error(path.string() + ": " + std::to_string(width) + "x" + std::to_string(height) +
                             ", expected " + std::to_string(view.camera.width) + "x" +
                             std::to_string(view.camera.height) + " (the view at the model's -r; use -r to match)");
  return rgb;
}

// The file names of the training views' holes/ and targets/ images.
std::vector<std::string> train_view_stems(const Scene& scene) {
  std::vector<std::string> names;
  for (int v : scene.train_views()) names.push_back(scene.views()[v].name);
  return output_stems(names);
}

// The settings of the flags that are not RemovalSettings' own fields.
void cmd_remove(const GlobalOptions& global, RemoveArgs a) {
  const auto t_start = std::chrono::steady_clock::now();
  // ---- everything that can be checked before any work
  check_selection_request(a.obj.request, a.obj.selection);
  const RemovalSettings& rs = a.settings;
  rs.validate();
  a.obj.config.validate();
  const fs::path out = check_new_output_folder(a.obj.out, a.obj.model);
  if (!a.inpainted.empty() && !fs::is_directory(a.inpainted))
    throw std::invalid_argument("--inpainted " + a.inpainted + " is not a folder");

  const OpenedModel opened =
      open_model_and_scene(a.obj.model, a.obj.scene, a.obj.resolution, a.obj.sparse, a.obj.request, a.obj.selection);
  const TrainedModel& tm = opened.tm;
  Scene* scene = opened.scene.get();
  // The training views' names in holes/, targets/ and --inpainted (a/1.jpg
  // and b/1.jpg: a_1.png and b_1.png).
  const std::vector<std::string> stems = train_view_stems(*scene);
  const std::vector<int> train_views = scene->train_views();
  if (!a.inpainted.empty())
    for (size_t i = 0; i < stems.size(); ++i)  // all present, right size
      read_inpainted(a.inpainted, scene->views()[train_views[i]], stems[i]);

  // ---- selection
  Runtime rt(global.device);
  nlohmann::json report;
  const SelectedObject sel = select_object(rt, opened, a.obj, report, "remove");
  if (sel.count == tm.model.size())
    throw std::runtime_error("the query selected all " + std::to_string(tm.model.size()) +
                             " anchors: removing them would leave an empty model");
  spdlog::info("selected {} of {} anchors ({} Gaussians) to remove", sel.count, tm.model.size(),
               sel.count * static_cast<size_t>(tm.model.children()));
  InterruptGuard interrupts;

  // ---- the removal; holes/ and targets/ are written into a folder beside OUT_DIR as they are found
  StagedFolder staged(out, a.obj.out);
  const fs::path& tmp = staged.path();
  fs::create_directories(tmp / "holes");
  fs::create_directories(tmp / "targets");
  RemovalRequest req;
  req.object = object_in_model(opened, sel);
  req.settings = rs;
  if (!a.inpainted.empty())
    req.inpainted = [&](size_t i) { return read_inpainted(a.inpainted, scene->views()[train_views[i]], stems[i]); };
  req.on_view = [&](size_t i, const ViewHole& h, const std::vector<float>& target) {
    write_mask_png((tmp / "holes" / (stems[i] + ".png")).string(), h.hole, h.width, h.height);
    write_rgb_png((tmp / "targets" / (stems[i] + ".png")).string(), target, h.width, h.height);
  };
  req.check_stop = [&](const std::string& during) { staged.stop_if_interrupted(during); };
  const RemovalResult result = remove_object(rt, req);

  // ---- the model after the removal
  write_model_archive((tmp / "model.ag2gs").string(), result.archive);
  {
    // As train writes it: with the model's sky baked in when it has one.
    std::vector<Camera> all_cameras;
    for (const SceneView& sv : scene->views()) all_cameras.push_back(sv.camera);
    write_model_plys(tmp.string(), expand_reference(result.model, tm.sh_degree), sky_from_archive(tm.archive),
                     all_cameras);
  }
  report.update(result.report);
  report["inpaint"] = a.inpainted.empty() ? rs.to_json()["inpaint"] : nlohmann::json("external: " + a.inpainted);
  report["seconds"]["query"] = sel.query_ms / 1000.0;
  report["seconds"]["total"] = seconds_since(t_start);
  AtomicFile f((tmp / "removal.json").string());
  f.write(report.dump(2) + "\n");
  f.commit();
  staged.commit();
  spdlog::info(
      "wrote {}: model.ag2gs and point_cloud.ply without the object ({} anchors kept, {} added, {} "
      "Gaussians), holes/ and targets/ for {} training views, removal.json ({:.1f} s)",
      a.obj.out, result.kept_anchors, result.added_anchors, result.model.gaussians(), train_views.size(),
      seconds_since(t_start));
}

}  // namespace

void register_remove(CLI::App& app, GlobalOptions& global) {
  auto a = std::make_shared<RemoveArgs>();
  auto* r = app.add_subcommand("remove",
                               "Remove an object selected by a click or by text: delete its anchors, find the holes it "
                               "leaves and their inpainted targets; writes a new model folder");
  add_object_options(r, a->obj, "Remove",
                     "New folder for the model without the object: model.ag2gs, point_cloud.ply, holes/, targets/, "
                     "removal.json");
  r->add_option("--inpainted", a->inpainted,
                "Folder of targets from an external inpainter: <view stem>.png per training view, at the size the "
                "view is rendered at (used as they are)");
  add_setting_options(r, removal_settings(), a->settings);
  auto print_config = add_print_config_flag(r, "remove with");
  set_action(r, [&global, a, print_config] {
    if (*print_config) {
      return print_config_json(a->settings);
    }
    cmd_remove(global, *a);
  });
}

}  // namespace ag2gs::cli
