#include "cli/model_render.h"

#include <spdlog/spdlog.h>

#include <algorithm>
#include <filesystem>
#include <stdexcept>

#include "host/device/cl_runtime.h"
#include "host/io/model_io.h"
#include "host/io/model_ply.h"
#include "host/io/ply_io.h"
#include "host/render/renderer.h"
#include "host/render/sky.h"
#include "train/anchors/anchor_model.h"
#include "train/model_check.h"
#include "train/stage3/clustering.h"
#include "train/stage3/instance_map.h"
#include "train/train_common.h"

namespace fs = std::filesystem;

namespace ag2gs::cli {
namespace {

void refuse_ply_of_another_model(const std::string& ply, const GaussianSet& set, const ModelArchive& archive) {
  const AnchorModel am = AnchorModel::from_archive(archive);
  const std::string& mf = archive.source;
  const std::string fix = "; move it aside and train again, or render the file alone with --ply " + ply;
  if (set.size() != am.gaussians())
    throw std::runtime_error(ply + " holds " + std::to_string(set.size()) + " Gaussians where " + mf + " has " +
                             std::to_string(am.gaussians()) + ": it was not written from this model" + fix);
  // point_cloud(_objects).ply holds the model's expanded Gaussians row for
  // row; their means are a function of the anchors and offsets alone.
  const GaussianSet mine = expand_reference(am, 0);
  for (size_t i = 0; i < mine.means.size(); ++i)
    if (mine.means[i] != set.means[i])
      throw std::runtime_error(ply + ": Gaussian " + std::to_string(i / 3) + " lies elsewhere than in " + mf +
                               ": the file was not written from this model" + fix);
}

bool has(const std::vector<std::string>& outputs, const char* o) {
  return std::find(outputs.begin(), outputs.end(), o) != outputs.end();
}

}  // namespace

void check_render_outputs(const std::vector<std::string>& outputs, const std::string& flag) {
  const std::vector<std::string>& names = render_output_names();
  for (const std::string& o : outputs)
    if (std::find(names.begin(), names.end(), o) == names.end())
      throw std::invalid_argument(flag + ": unknown output '" + o + "'; choose from rgb,depth,alpha,feature,instance");
  if (outputs.empty()) throw std::invalid_argument(flag + " is empty; choose from rgb,depth,alpha,feature,instance");
}

struct ModelRender::State {
  State(Runtime& rt) : renderer(rt), dg(rt), sky(rt), mapper(rt) {}
  ModelRenderOptions options;
  std::string ply;
  RenderSettings settings;
  GaussianSet set;
  Renderer renderer;
  DeviceGaussians dg;
  Sky sky;
  InstanceMapper mapper;
};

ModelRender::ModelRender(Runtime& rt, const ModelRenderOptions& options) : s_(std::make_unique<State>(rt)) {
  s_->options = options;
  const std::vector<std::string>& outputs = options.outputs;
  check_render_outputs(outputs, "--outputs");
  const bool instance = has(outputs, "instance");
  std::string ply = options.ply;
  if (!options.model.empty()) {
    if (!ply.empty()) throw std::invalid_argument("give either MODEL_DIR or --ply, not both");
    if (!fs::is_directory(options.model))
      throw std::runtime_error(options.model + ": no such model folder (a folder written by `ag2gs train`)");
    if (!fs::exists(fs::path(options.model) / "point_cloud.ply") && !instance)
      throw std::runtime_error(options.model +
                               ": has no point_cloud.ply; is it a model folder written by `ag2gs train`?");
    // A model with a sky: its Gaussians alone, the sky composited below
    // (point_cloud.ply also holds the sky baked into Gaussians).
    ply = model_objects_ply(options.model);
  }
  if (ply.empty()) throw std::invalid_argument("give a model folder (MODEL_DIR) or a Gaussian file (--ply FILE)");
  s_->ply = ply;
  s_->settings.background = options.background.value_or(std::array<float, 3>{0.f, 0.f, 0.f});
  // A model trained with a sky (host/render/sky.h) renders its rgb over
  // it, as training saw it, unless a fixed background is asked for.
  std::optional<std::vector<float>> sky_coefficients;
  std::optional<ModelArchive> archive;
  if (!options.model.empty() && fs::exists(fs::path(options.model) / "model.ag2gs"))
    archive = read_model_archive((fs::path(options.model) / "model.ag2gs").string());
  if (archive) check_model_archive(*archive);
  if (archive && !options.background) sky_coefficients = sky_from_archive(*archive);
  // Instance maps need the anchors' clusters: the model's Gaussians are then
  // expanded from model.ag2gs (row g = anchor g / K, the same Gaussians as
  // its point_cloud.ply) instead of read from the PLY.
  if (instance) {
    if (options.model.empty())
      throw std::invalid_argument("--outputs instance needs a model folder with clusters (stage 3), not --ply");
    const std::string mf = (fs::path(options.model) / "model.ag2gs").string();
    if (!archive) throw std::runtime_error(options.model + ": no model.ag2gs, which --outputs instance needs");
    if (!archive->meta.contains("clusters"))
      throw std::runtime_error(mf +
                               " has no clusters, which --outputs instance needs: run stage 3 "
                               "(`ag2gs train SCENE_DIR -o MODEL_DIR --stages 3`)");
    const AnchorModel am = AnchorModel::from_archive(*archive);
    const nlohmann::json tr = archive->meta.value("train", nlohmann::json::object());
    const int sh = recorded_sh_degree(tr, am.config().sh_degree, mf);
    s_->set = expand_reference(am, sh);
    s_->mapper.set_clusters(clustering_from_archive(*archive, am.size()).anchor_cluster, am.config().children);
  } else {
    size_t dropped = 0;
    s_->set = read_ply(ply, PlyValues::activated,
                       options.drop_invalid ? InvalidGaussians::drop : InvalidGaussians::reject, &dropped);
    if (dropped > 0) spdlog::warn("{}: left out {} Gaussians with invalid numbers (--drop-invalid)", ply, dropped);
    // The folder's PLY must be its model's: a file copied in from another
    // model, or left from an earlier one, would render another scene under
    // this model's name (and over its sky).
    if (archive && dropped == 0) refuse_ply_of_another_model(ply, s_->set, *archive);
  }
  s_->dg.upload(s_->set);
  if (sky_coefficients) {
    s_->sky.set(sky_degree_for(sky_coefficients->size()), *sky_coefficients);
    s_->settings.background = {0.f, 0.f, 0.f};
  }
}

ModelRender::~ModelRender() = default;

size_t ModelRender::gaussians() const {
  return s_->set.size();
}
int ModelRender::sh_degree() const {
  return s_->set.sh_degree;
}
bool ModelRender::has_sky() const {
  return s_->sky.enabled();
}
const std::string& ModelRender::ply() const {
  return s_->ply;
}

ModelFrame ModelRender::render(const Camera& cam) {
  const std::vector<std::string>& outputs = s_->options.outputs;
  s_->renderer.forward(s_->dg, cam, s_->settings);
  RenderOutput out = s_->renderer.download_output();
  if (s_->sky.enabled() && has(outputs, "rgb")) composite_sky(s_->renderer, s_->sky, cam, out);
  ModelFrame f;
  f.width = out.width;
  f.height = out.height;
  f.intersections = s_->renderer.stats().n_intersections;
  if (has(outputs, "rgb")) f.rgb = std::move(out.rgb);
  if (has(outputs, "depth")) {
    // Mean depth along the ray (sum w z / alpha; 0 where nothing was hit).
    f.depth.resize(out.depth.size());
    for (size_t p = 0; p < f.depth.size(); ++p) f.depth[p] = out.alpha[p] > 1e-6f ? out.depth[p] / out.alpha[p] : 0.f;
  }
  if (has(outputs, "feature")) f.feature = std::move(out.feature);
  f.alpha = std::move(out.alpha);  // always: the feature colours need it
  if (has(outputs, "instance")) {
    // Cluster ids (-1 = none): the pixels where one cluster holds more than
    // half of the blending weight (train/stage3/instance_map.h).
    s_->mapper.compute(s_->renderer);
    f.instance = s_->mapper.download().ids;
  }
  return f;
}

}  // namespace ag2gs::cli
