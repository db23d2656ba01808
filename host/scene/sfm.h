// Structure from motion and undistortion through the `colmap` program:
// photos in, a scene directory ag2gs trains on out (images/ undistorted,
// sparse/0/ with PINHOLE cameras), as 3DGS's convert.py lays it out.
#pragma once

#include <functional>
#include <string>
#include <vector>

namespace ag2gs {

struct SfmOptions {
  std::string colmap = "colmap";        // program name or path (AG2GS_COLMAP overrides the default)
  std::string camera_model = "OPENCV";  // model COLMAP fits before undistortion
  bool single_camera = true;            // one camera for all photos (one phone/lens)
  std::string matcher = "auto";         // auto (choose_matcher) | exhaustive | sequential
  int max_image_size = 1600;            // SIFT works on images downscaled to this (longest side, px)
  int threads = -1;                     // -1 = all cores
  // Mapper thresholds (COLMAP's defaults); lower them for small or low-texture
  // photo sets whose image pairs share fewer matches.
  int init_min_inliers = 100;                        // inliers of the initial image pair
  int abs_pose_min_inliers = 30;                     // inliers to register a further image
  bool downscaled_copies = false;                    // also write images_2/4/8 (for -r 2/4/8)
  bool force = false;                                // replace an existing scene directory
  std::function<void(const std::string&)> progress;  // one line per step/update; may be empty
};

struct SfmResult {
  int images_in = 0;
  int images_registered = 0;
  int points = 0;
  double seconds = 0;
  std::string log_path;
};

// Runs feature extraction (CPU), matching, mapping and undistortion on the
// photos in `images_dir` and leaves `scene_dir`/images + sparse/0. Work happens
// in a sibling temporary folder that replaces `scene_dir` only on success, so
// an existing scene is never half-overwritten; without `force` an existing
// non-empty `scene_dir` is an error. COLMAP's full output goes to
// `scene_dir`/sfm_log.txt. Throws std::runtime_error saying which step
// failed, the last lines COLMAP printed and where the log is; a missing
// `colmap` program gets the install command.
SfmResult run_sfm(const std::string& images_dir, const std::string& scene_dir, const SfmOptions& options);

// Undistorts a scene whose COLMAP model uses a distorted camera model into
// `out_dir` (images/ + sparse/0/ with PINHOLE cameras), via COLMAP's
// image_undistorter. Same safety rules as run_sfm.
SfmResult undistort_scene(const std::string& scene_dir, const std::string& out_dir, const SfmOptions& options);

// Finds the COLMAP program: `name` if it contains a '/', else AG2GS_COLMAP,
// else `name` on PATH. Throws std::runtime_error with the install command.
std::string find_colmap(const std::string& name);

// Image files (by extension) directly inside `dir`, sorted.
std::vector<std::string> list_image_files(const std::string& dir);

// COLMAP's matcher for `names` (the photos' file names) and why, in words.
// Sequential when there are more than kSequentialMinImages and the names,
// in the sorted order COLMAP's sequential matcher pairs them in, carry
// numbers that step evenly (video frames: frame_0001.jpg, 0001.png,
// IMG_1234.JPG, every 5th frame, a few dropped); otherwise exhaustive, which
// matches every pair (n(n-1)/2 of them) and finds the loop closures a walk
// around an object needs.
struct MatcherChoice {
  std::string matcher;  // exhaustive | sequential
  std::string reason;
};
constexpr int kSequentialMinImages = 40;
MatcherChoice choose_matcher(const std::vector<std::string>& names);

// One progress update in a line COLMAP prints: feature extraction
// ("Processed file [i/n]"), exhaustive ("Matching block [i/n, j/m]") and
// sequential matching ("Matching image [i/n]"). `done` counts finished
// units: COLMAP 3.8 completes a matching line with " in 1.234s" when the
// unit is done, newer versions log it when the unit starts.
struct ColmapProgress {
  std::string unit;  // "image" or "block"
  int done = 0;
  int total = 0;
};
bool parse_colmap_progress(const std::string& line, ColmapProgress* progress);

}  // namespace ag2gs
