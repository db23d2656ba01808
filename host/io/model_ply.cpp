#include "host/io/model_ply.h"

#include <filesystem>

#include "host/io/ply_io.h"
#include "host/render/sky.h"
#include "host/render/sky_bake.h"

namespace fs = std::filesystem;

namespace ag2gs {

std::string ModelPlyReport::describe() const {
  if (sky == 0) return std::string(kModelPly) + " holds the model's " + std::to_string(objects) + " Gaussians";
  return std::string(kModelPly) + " holds the model's " + std::to_string(objects) + " Gaussians and its sky as " +
         std::to_string(sky) + " Gaussians on a shell of radius " + std::to_string(shell_radius) +
         " (what other 3DGS viewers show); " + kModelObjectsPly + " holds the Gaussians alone";
}

ModelPlyReport write_model_plys(const std::string& model_dir, const GaussianSet& objects,
                                const std::optional<std::vector<float>>& sky, const std::vector<Camera>& cameras,
                                bool with_features) {
  ModelPlyReport report;
  report.objects = objects.size();
  const fs::path dir(model_dir);
  if (!sky) {
    write_ply((dir / kModelPly).string(), objects, with_features, PlyValues::activated);
    std::error_code ec;
    fs::remove(dir / kModelObjectsPly, ec);
    return report;
  }
  const SkyShell shell = sky_shell(objects, cameras);
  const int degree = std::max(objects.sh_degree, sky_degree_for(sky->size()));
  const GaussianSet baked = bake_sky(*sky, shell, degree);
  write_ply((dir / kModelObjectsPly).string(), objects, with_features, PlyValues::activated);
  write_ply((dir / kModelPly).string(), concat_gaussians(objects, baked), with_features, PlyValues::activated);
  report.sky = baked.size();
  report.shell_radius = shell.radius;
  return report;
}

std::string model_objects_ply(const std::string& model_dir) {
  const fs::path objects = fs::path(model_dir) / kModelObjectsPly;
  std::error_code ec;
  if (fs::exists(objects, ec)) return objects.string();
  return (fs::path(model_dir) / kModelPly).string();
}

}  // namespace ag2gs
