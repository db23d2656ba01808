// Scene-making subcommands: sfm (photos to a scene through COLMAP) and
// undistort.
#include <spdlog/spdlog.h>

#include <memory>
#include <string>

#include "cli/commands.h"
#include "host/scene/sfm.h"

namespace ag2gs::cli {
namespace {

struct SfmArgs {
  std::string input, out, colmap = "colmap", camera_model = "OPENCV", matcher = "auto";
  bool per_image_camera = false, downscaled = false, force = false;
  int max_image_size = 1600;
  int init_min_inliers = 100, abs_pose_min_inliers = 30;
};

SfmOptions to_options(const SfmArgs& a, const GlobalOptions& global) {
  SfmOptions o;
  o.colmap = a.colmap;
  o.camera_model = a.camera_model;
  o.single_camera = !a.per_image_camera;
  o.matcher = a.matcher;
  o.max_image_size = a.max_image_size;
  o.init_min_inliers = a.init_min_inliers;
  o.abs_pose_min_inliers = a.abs_pose_min_inliers;
  o.downscaled_copies = a.downscaled;
  o.force = a.force;
  if (!global.quiet) o.progress = [](const std::string& line) { spdlog::info("{}", line); };
  return o;
}

void report(const SfmResult& r, const std::string& out) {
  spdlog::info("scene ready in {}: {}/{} images registered, {} points, {:.1f} s (COLMAP log: {})", out,
               r.images_registered, r.images_in, r.points, r.seconds, r.log_path);
  if (r.images_registered < r.images_in) {
    spdlog::warn("{} photos could not be registered and are left out", r.images_in - r.images_registered);
  }
}

}  // namespace

void register_scene_commands(CLI::App& app, GlobalOptions& global) {
  auto sa = std::make_shared<SfmArgs>();
  auto* sfm = app.add_subcommand("sfm", "Structure from motion with COLMAP: photos in, a trainable scene out");
  sfm->add_option("images", sa->input, "Folder of photos (jpg, png, ...)")->required();
  sfm->add_option("-o,--out", sa->out, "Scene directory to create (images/ + sparse/0/)")
      ->check(output_path())
      ->required();
  sfm->add_option("--matcher", sa->matcher,
                  "auto (default: sequential for more than 40 photos whose names number an ordered sequence, as "
                  "video frames do; else exhaustive), exhaustive (every pair) or sequential (neighbours in name "
                  "order)")
      ->check(CLI::IsMember({"auto", "exhaustive", "sequential"}));
  sfm->add_option("--camera-model", sa->camera_model, "COLMAP camera model before undistortion (default OPENCV)");
  sfm->add_flag("--per-image-camera", sa->per_image_camera, "Intrinsics per photo (mixed cameras or zoom)");
  sfm->add_option("--max-image-size", sa->max_image_size,
                  "Longest side SIFT works on; larger photos are reduced to it (default 1600)");
  sfm->add_option("--init-min-inliers", sa->init_min_inliers,
                  "Inliers the initial image pair needs (default 100; lower for small or low-texture photos)");
  sfm->add_option("--abs-pose-min-inliers", sa->abs_pose_min_inliers,
                  "Inliers a further image needs to be registered (default 30)");
  sfm->add_flag("--downscaled", sa->downscaled, "Also write images_2/4/8 for -r 2/4/8");
  sfm->add_flag("--force", sa->force, "Replace an existing output folder (only once the new scene is complete)");
  sfm->add_option("--colmap", sa->colmap, "COLMAP program (default: colmap on PATH, or AG2GS_COLMAP)");
  set_action(sfm, [sa, &global] { report(run_sfm(sa->input, sa->out, to_options(*sa, global)), sa->out); });

  auto ua = std::make_shared<SfmArgs>();
  auto* und = app.add_subcommand("undistort", "Undistort a scene with a distorted COLMAP camera model");
  und->add_option("scene", ua->input, "Scene directory (images/ + sparse/0/, or sparse/ itself)")->required();
  und->add_option("-o,--out", ua->out, "New scene directory with PINHOLE cameras")->check(output_path())->required();
  und->add_flag("--downscaled", ua->downscaled, "Also write images_2/4/8 for -r 2/4/8");
  und->add_flag("--force", ua->force, "Replace an existing output folder (only once complete)");
  und->add_option("--colmap", ua->colmap, "COLMAP program (default: colmap on PATH, or AG2GS_COLMAP)");
  set_action(und, [ua, &global] {
    report(undistort_scene(ua->input, ua->out, to_options(*ua, global)), ua->out);
    spdlog::warn("semantic files (language_features/, masks/) are not undistorted: recompute them on the new images");
  });
}

}  // namespace ag2gs::cli
