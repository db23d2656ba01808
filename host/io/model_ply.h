// The .ply files of a model folder (docs/formats.md section 8). A model with
// a learned sky is written twice:
//   point_cloud.ply          the Gaussians and the sky baked into Gaussians on
//                            a far shell (host/render/sky_bake.h): what a
//                            standard 3DGS viewer shows is what ag2gs renders;
//   point_cloud_objects.ply  the Gaussians alone (rendered by ag2gs over the
//                            sky, and for users who want the objects alone).
// Without a sky only point_cloud.ply is written (and a stale
// point_cloud_objects.ply from an earlier model in the folder is removed).
#pragma once

#include <optional>
#include <string>
#include <vector>

#include "host/core/gaussians.h"

namespace ag2gs {

inline constexpr const char* kModelPly = "point_cloud.ply";
inline constexpr const char* kModelObjectsPly = "point_cloud_objects.ply";

struct ModelPlyReport {
  size_t objects = 0;  // Gaussians of the model
  size_t sky = 0;      // baked sky Gaussians in point_cloud.ply (0 without a sky)
  double shell_radius = 0;
  std::string describe() const;  // one line for the log
};

// Writes the files above into `model_dir` (each atomically, write_ply).
// `sky` holds the sky's [K, 3] coefficients when the model has one; `cameras`
// place the shell (sky_shell). `with_features` as write_ply.
ModelPlyReport write_model_plys(const std::string& model_dir, const GaussianSet& objects,
                                const std::optional<std::vector<float>>& sky, const std::vector<Camera>& cameras,
                                bool with_features = true);

// The file of a model folder that holds its Gaussians alone, for renderers
// that composite the sky themselves: point_cloud_objects.ply when present,
// else point_cloud.ply.
std::string model_objects_ply(const std::string& model_dir);

}  // namespace ag2gs
