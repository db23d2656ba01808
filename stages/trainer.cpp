#include "stages/trainer.h"

#include <spdlog/spdlog.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <limits>
#include <map>
#include <stdexcept>
#include <system_error>

#include "host/atomic_file.h"
#include "host/counter_rng.h"
#include "host/model_io.h"
#include "host/ply_io.h"

namespace fs = std::filesystem;

namespace ag2gs {

// ------------------------------------------------------------------ config
void TrainConfig::validate() const {
  auto bad = [](const std::string& what) { throw std::invalid_argument("TrainConfig: " + what); };
  anchors.validate();
  if (iterations < 1) bad("iterations is " + std::to_string(iterations) + "; it must be at least 1");
  if (sh_interval < 0) bad("sh_interval is " + std::to_string(sh_interval) + "; use 0 (automatic) or more");
  if (!(lambda_ssim >= 0 && lambda_ssim <= 1)) bad("lambda_ssim must be in [0, 1]");
  if (!(w_offset >= 0) || !std::isfinite(w_offset)) bad("w_offset must be finite and >= 0");
  if (!(w_distortion >= 0) || !std::isfinite(w_distortion)) bad("w_distortion must be finite and >= 0");
  if (distortion_from < 0) bad("distortion_from must be >= 0");
  if (!(w_is >= 0) || !std::isfinite(w_is)) bad("w_is must be finite and >= 0");
  if (!(w_ic >= 0) || !std::isfinite(w_ic)) bad("w_ic must be finite and >= 0");
  if (mask_from < -1) bad("mask_from must be -1 (iterations / 6) or >= 0");
  if (prop_iters < -1) bad("prop_iters must be -1 (iterations / 6), 0 (no stage 2) or more");
  if (static_cast<int64_t>(iterations) + effective_prop_iters() > std::numeric_limits<int>::max())
    bad("iterations + prop_iters is too large");
  if (!(w_prop >= 0) || !std::isfinite(w_prop)) bad("w_prop must be finite and >= 0");
  if (!(prop_tau > 0) || !std::isfinite(prop_tau)) bad("prop_tau must be finite and > 0");
  const std::pair<const char*, double> rates[] = {
      {"offset_lr_init", offset_lr_init}, {"offset_lr_final", offset_lr_final},
      {"feature_lr", feature_lr},         {"sh_dc_lr", sh_dc_lr},
      {"sh_rest_lr", sh_rest_lr},         {"opacity_lr", opacity_lr},
      {"scaling_lr", scaling_lr},         {"rotation_lr", rotation_lr}};
  for (const auto& [name, v] : rates)
    if (!(v >= 0) || !std::isfinite(v)) bad(std::string(name) + " must be finite and >= 0");
  if (!(prune_opacity >= 0 && prune_opacity < 1)) bad("prune_opacity must be in [0, 1)");
  if (!(recycle_opacity >= 0 && recycle_opacity < 1)) bad("recycle_opacity must be in [0, 1)");
  if (downscales < -1 || downscales > 6)
    bad("downscales is " + std::to_string(downscales) + "; use -1 (from the images), 0 (off) or 1 to 6");
  if (res_schedule < 0) bad("res_schedule must be 0 (from the iterations) or at least 1 iteration");
  if (grow_every < 0 || grow_from < 0 || grow_until < 0 || !(grow_min_seen >= 0 && grow_min_seen <= 1))
    bad("grow_every, grow_from and grow_until must be >= 0 and grow_min_seen in [0, 1]");
  if (!(grow_threshold > 0) || !std::isfinite(grow_threshold)) bad("grow_threshold must be finite and > 0");
  if (prune_unseen_window < -1)
    bad("prune_unseen_window is " + std::to_string(prune_unseen_window) +
        "; use -1 (off), 0 (2 x training views) or a number of views");
  if (opacity_reset_every < 0 || opacity_reset_pause < 0)
    bad("opacity_reset_every and opacity_reset_pause must be >= 0 (opacity_reset_every 0 = no reset)");
  if (!(grow_budget >= 0) || !std::isfinite(grow_budget))
    bad("grow_budget must be finite and >= 0 (a fraction of the anchors per round; 0 = no limit)");
  if (max_gaussians < -1) bad("max_gaussians must be -1 (from the scene), 0 (no limit) or a count");
  if (offset_lr_init > 0 && !(offset_lr_final > 0))
    bad("offset_lr_final must be > 0 when offset_lr_init is (exponential decay)");
}

int TrainConfig::effective_sh_interval() const {
  if (sh_interval > 0) return sh_interval;
  return std::max(1, std::min(1000, iterations / (anchors.sh_degree + 1)));
}

int TrainConfig::effective_mask_from() const {
  return mask_from >= 0 ? mask_from : iterations / 6;
}

int TrainConfig::effective_grow_until() const {
  return grow_until > 0 ? grow_until : static_cast<int>(static_cast<int64_t>(iterations) * 2 / 3);
}

GrowthConfig TrainConfig::growth_config(size_t train_views) const {
  GrowthConfig g;
  g.grad_threshold = static_cast<float>(grow_threshold);
  g.layer_factor = 2.f;
  g.start = grow_from;
  g.stop = effective_grow_until();
  g.every = grow_every;
  g.min_observations = 1;
  g.min_seen_fraction = static_cast<float>(grow_min_seen);
  g.prune_opacity = static_cast<float>(prune_opacity);
  g.prune_unseen = prune_unseen_window >= 0;
  const size_t two_epochs = std::min<size_t>(2 * train_views, static_cast<size_t>(std::numeric_limits<int>::max()));
  g.unseen_window = prune_unseen_window > 0 ? prune_unseen_window : static_cast<int>(two_epochs);
  g.ndc = true;
  g.same_layer = grow_same_layer;
  g.recycle_opacity = static_cast<float>(recycle_opacity);
  g.round_growth = static_cast<float>(grow_budget);
  return g;
}

int TrainConfig::auto_downscales(int min_side) {
  int levels = 0;
  while (levels < 3 && (min_side >> (levels + 1)) >= kCoarseMinSide) ++levels;
  return levels;
}

int TrainConfig::auto_res_schedule(int iterations, int downscales) {
  if (downscales <= 0) return 1;
  return std::max(1, std::min(iterations / (2 * downscales), 3000));
}

size_t TrainConfig::effective_max_gaussians(size_t view_pixels, size_t initial) const {
  if (max_gaussians >= 0) return static_cast<size_t>(max_gaussians);
  return std::max(view_pixels, 2 * initial);
}

nlohmann::json TrainConfig::to_json() const {
  nlohmann::json a = {
      {"children", anchors.children},         {"layers", anchors.layers},
      {"top_cells", anchors.top_cells},       {"voxel_size", anchors.voxel_size},
      {"layer_ratio", anchors.layer_ratio},   {"init_layer", anchors.init_layer},
      {"init_opacity", anchors.init_opacity}, {"init_children_at_points", anchors.init_children_at_points},
      {"init_scale", anchors.init_scale},     {"init_feature", anchors.init_feature},
      {"scale_cap", anchors.scale_cap},       {"scale_cap_layers", anchors.scale_cap_layers},
      {"sh_degree", anchors.sh_degree}};
  return {{"iterations", iterations},
          {"seed", seed},
          {"anchors", a},
          {"sh_interval", effective_sh_interval()},
          {"lambda_ssim", lambda_ssim},
          {"w_offset", w_offset},
          {"w_distortion", w_distortion},
          {"distortion_from", distortion_from},
          {"w_is", w_is},
          {"w_ic", w_ic},
          {"mask_from", effective_mask_from()},
          {"mask_alpha_normalise", mask_alpha_normalise},
          {"mask_geometry", mask_geometry},
          {"mask_unmasked_group", mask_unmasked_group},
          {"feature_ball", feature_ball},
          {"grow_same_layer", grow_same_layer},
          {"recycle_opacity", recycle_opacity},
          {"grow_budget", grow_budget},
          {"max_gaussians", max_gaussians},
          {"prop_iters", effective_prop_iters()},
          {"w_prop", w_prop},
          {"prop_tau", prop_tau},
          {"offset_lr_init", offset_lr_init},
          {"offset_lr_final", offset_lr_final},
          {"offset_lr_extent", offset_lr_extent},
          {"feature_lr", feature_lr},
          {"sh_dc_lr", sh_dc_lr},
          {"sh_rest_lr", sh_rest_lr},
          {"opacity_lr", opacity_lr},
          {"scaling_lr", scaling_lr},
          {"rotation_lr", rotation_lr},
          {"adam", {{"beta1", adam.beta1}, {"beta2", adam.beta2}, {"eps", adam.eps}}},
          {"white_background", white_background},
          {"grow",
           {{"from", grow_from},
            {"until", effective_grow_until()},
            {"every", grow_every},
            {"threshold", grow_threshold},
            {"min_seen", grow_min_seen}}},
          {"prune_opacity", prune_opacity},
          {"prune_unseen_window", prune_unseen_window},
          {"opacity_reset_every", opacity_reset_every},
          {"opacity_reset_pause", opacity_reset_pause},
          {"downscales", downscales},
          {"res_schedule", res_schedule}};
}

namespace {

// Every leaf of a JSON object as "a.b.c" -> value.
void flatten(const nlohmann::json& j, const std::string& prefix, std::map<std::string, nlohmann::json>* out) {
  if (j.is_object()) {
    for (auto it = j.begin(); it != j.end(); ++it)
      flatten(it.value(), prefix.empty() ? it.key() : prefix + "." + it.key(), out);
  } else {
    (*out)[prefix] = j;
  }
}

}  // namespace

std::vector<std::string> config_differences(const nlohmann::json& a, const nlohmann::json& b) {
  std::map<std::string, nlohmann::json> fa, fb;
  flatten(a, "", &fa);
  flatten(b, "", &fb);
  std::vector<std::string> out;
  for (const auto& [k, v] : fa) {
    auto it = fb.find(k);
    if (it == fb.end())
      out.push_back(k + " (" + v.dump() + " vs missing)");
    else if (it->second != v)
      out.push_back(k + " (" + v.dump() + " vs " + it->second.dump() + ")");
  }
  for (const auto& [k, v] : fb)
    if (!fa.count(k)) out.push_back(k + " (missing vs " + v.dump() + ")");
  return out;
}

TrainConfig TrainConfig::from_json(const nlohmann::json& j) {
  TrainConfig c;
  try {
    const nlohmann::json& a = j.at("anchors");
    c.anchors.children = a.at("children").get<int>();
    c.anchors.layers = a.at("layers").get<int>();
    c.anchors.top_cells = a.at("top_cells").get<int>();
    c.anchors.voxel_size = a.value("voxel_size", 0.0);
    c.anchors.layer_ratio = a.at("layer_ratio").get<int>();
    c.anchors.init_layer = a.at("init_layer").get<int>();
    c.anchors.init_children_at_points = a.value("init_children_at_points", false);
    c.anchors.init_opacity = a.at("init_opacity").get<float>();
    c.anchors.init_scale = a.at("init_scale").get<float>();
    c.anchors.scale_cap = a.value("scale_cap", 1.f);
    c.anchors.scale_cap_layers = a.value("scale_cap_layers", kMaxLayers);
    c.anchors.init_feature = a.at("init_feature").get<float>();
    c.anchors.sh_degree = a.at("sh_degree").get<int>();
    c.iterations = j.at("iterations").get<int>();
    c.seed = j.at("seed").get<uint64_t>();
    c.sh_interval = j.at("sh_interval").get<int>();
    c.lambda_ssim = j.at("lambda_ssim").get<float>();
    c.w_offset = j.at("w_offset").get<float>();
    c.w_distortion = j.at("w_distortion").get<float>();
    c.distortion_from = j.at("distortion_from").get<int>();
    c.w_is = j.at("w_is").get<float>();
    c.w_ic = j.at("w_ic").get<float>();
    c.mask_from = j.at("mask_from").get<int>();
    c.mask_alpha_normalise = j.at("mask_alpha_normalise").get<bool>();
    c.mask_geometry = j.at("mask_geometry").get<bool>();
    c.mask_unmasked_group = j.value("mask_unmasked_group", false);  // written before the option
    c.feature_ball = j.value("feature_ball", false);
    c.grow_same_layer = j.value("grow_same_layer", false);
    c.recycle_opacity = j.value("recycle_opacity", 0.0);
    // Checkpoints from before the budgets grew without limit.
    c.grow_budget = j.value("grow_budget", 0.0);
    c.max_gaussians = j.value("max_gaussians", int64_t{0});
    // Written before stage 2 existed: stage 1 only.
    c.prop_iters = j.value("prop_iters", 0);
    c.w_prop = j.value("w_prop", 0.01f);  // the default of that time
    c.prop_tau = j.value("prop_tau", kPropagationTau);
    c.offset_lr_init = j.at("offset_lr_init").get<double>();
    c.offset_lr_final = j.at("offset_lr_final").get<double>();
    c.offset_lr_extent = j.at("offset_lr_extent").get<bool>();
    c.feature_lr = j.at("feature_lr").get<double>();
    c.sh_dc_lr = j.at("sh_dc_lr").get<double>();
    c.sh_rest_lr = j.at("sh_rest_lr").get<double>();
    c.opacity_lr = j.at("opacity_lr").get<double>();
    c.scaling_lr = j.at("scaling_lr").get<double>();
    c.rotation_lr = j.at("rotation_lr").get<double>();
    c.adam.beta1 = j.at("adam").at("beta1").get<double>();
    c.adam.beta2 = j.at("adam").at("beta2").get<double>();
    c.adam.eps = j.at("adam").at("eps").get<double>();
    c.white_background = j.at("white_background").get<bool>();
    const nlohmann::json& g = j.at("grow");
    c.grow_from = g.at("from").get<int>();
    c.grow_until = g.at("until").get<int>();
    c.grow_every = g.at("every").get<int>();
    c.grow_threshold = g.at("threshold").get<double>();
    c.grow_min_seen = g.at("min_seen").get<double>();
    c.prune_opacity = j.at("prune_opacity").get<double>();
    c.prune_unseen_window = j.at("prune_unseen_window").get<int>();
    c.opacity_reset_every = j.at("opacity_reset_every").get<int>();
    c.opacity_reset_pause = j.at("opacity_reset_pause").get<int>();
    c.downscales = j.value("downscales", 0);  // written before the option: full resolution throughout
    c.res_schedule = j.value("res_schedule", 250);
  } catch (const nlohmann::json::exception& e) {
    throw std::runtime_error(std::string("training config: ") + e.what());
  }
  return c;
}

// ------------------------------------------------------------------ helpers
Camera downscaled_camera(const Camera& cam, int factor) {
  if (factor <= 1) return cam;
  Camera c = cam;
  c.width = std::max(1, cam.width / factor);
  c.height = std::max(1, cam.height / factor);
  // Pixel (x, y) of the small image covers [f x, f x + f) of the large one:
  // u_small = u_large / f exactly (a partial block at the right or bottom
  // edge is cropped, not resampled).
  c.fx = cam.fx / factor;
  c.fy = cam.fy / factor;
  c.cx = cam.cx / factor;
  c.cy = cam.cy / factor;
  return c;
}

void box_downscale_planar(const Image& img, int factor, float* out) {
  const int w = std::max(1, img.width / factor), h = std::max(1, img.height / factor);
  const size_t npix = static_cast<size_t>(w) * h;
  const int fx = std::min(factor, img.width), fy = std::min(factor, img.height);
  const float inv = 1.f / static_cast<float>(fx * fy);
  for (int y = 0; y < h; ++y)
    for (int x = 0; x < w; ++x)
      for (int c = 0; c < 3; ++c) {
        float sum = 0.f;
        for (int dy = 0; dy < fy; ++dy)
          for (int dx = 0; dx < fx; ++dx)
            sum += img.rgb[(static_cast<size_t>(y * fy + dy) * img.width + (x * fx + dx)) * 3 + c];
        out[c * npix + static_cast<size_t>(y) * w + x] = sum * inv;
      }
}

void check_model_dir_writable(const std::string& dir) {
  std::error_code ec;
  fs::create_directories(dir, ec);
  if (ec || !fs::is_directory(dir))
    throw std::runtime_error("model directory " + dir + " cannot be created" + (ec ? ": " + ec.message() : "") +
                             "; choose another -o");
  const fs::path probe = fs::path(dir) / (".ag2gs_write_test." + std::to_string(::getpid()));
  bool ok = false;
  {
    std::ofstream f(probe, std::ios::binary);
    if (f) {
      f << "ok";
      f.close();
      ok = static_cast<bool>(f);
    }
  }
  fs::remove(probe, ec);
  if (!ok) throw std::runtime_error("model directory " + dir + " is not writable; choose another -o");
}

void write_json_atomic(const std::string& path, const nlohmann::json& doc) {
  AtomicFile f(path);
  f.write(doc.dump(2) + "\n");
  f.commit();
}

// ------------------------------------------------------------------ trainer
Trainer::Trainer(Runtime& rt, Scene& scene, const TrainConfig& config)
    : rt_(rt),
      scene_(scene),
      config_(config),
      anchors_(rt),
      grads_(rt),
      feature_grads_(rt),
      gaussians_(rt),
      expander_(rt),
      renderer_(rt),
      image_loss_(rt),
      mask_loss_(rt),
      adam_(rt, config.adam),
      growth_(rt, GrowthConfig{}),
      prop_(rt, PropagationLossConfig{config.prop_tau > 0 ? config.prop_tau : kPropagationTau, false, 0}) {
  config_.validate();
  scene_.require_points();
  train_views_ = scene_.train_views();
  if (train_views_.empty()) throw std::runtime_error("scene " + scene_.dir() + " has no training views");
  std::vector<Camera> train_cameras;
  for (int v : train_views_) train_cameras.push_back(scene_.views()[v].camera);
  voxel_choice_ = choose_top_voxel(config_.anchors, scene_.bounds(), scene_.points(), train_cameras);
  if (config_.downscales < 0) {
    int min_side = std::numeric_limits<int>::max();
    for (const Camera& c : train_cameras) min_side = std::min({min_side, c.width, c.height});
    config_.downscales = TrainConfig::auto_downscales(min_side);
  }
  if (config_.res_schedule == 0)
    config_.res_schedule = TrainConfig::auto_res_schedule(config_.iterations, config_.downscales);
  const VoxelGrid grid = VoxelGrid::from_bounds(scene_.bounds(), config_.anchors, voxel_choice_.top_voxel);
  init_stats_ = model_.initialise_from_points(scene_.points(), scene_.colors(), grid, config_.anchors, config_.seed);
  if (model_.size() == 0)
    throw std::runtime_error("scene " + scene_.dir() + ": no anchor could be placed from " +
                             std::to_string(scene_.points().size()) + " SfM points (all non-finite or out of range)");
  extent_ = scene_.bounds().camera_radius > 0 ? scene_.bounds().camera_radius : scene_.bounds().longest_extent();
  anchors_.upload(model_);
  const size_t n = model_.gaussians();
  g_offset_ = std::make_unique<AdamGroup>(rt_, "offset", n, 3);
  g_scale_ = std::make_unique<AdamGroup>(rt_, "scaling", n, 3);
  g_quat_ = std::make_unique<AdamGroup>(rt_, "rotation", n, 4);
  g_opacity_ = std::make_unique<AdamGroup>(rt_, "opacity", n, 1);
  g_dc_ = std::make_unique<AdamGroup>(rt_, "sh_dc", n, 3);
  g_rest_ = std::make_unique<AdamGroup>(rt_, "sh_rest", n, 3 * kShRestCoeffs);
  g_feature_ = std::make_unique<AdamGroup>(rt_, "feature", model_.size(), 3);
  reg_value_.bind(&rt_);
  for (DeviceBuffer* b : {&target_dev_, &grad_rgb_dev_, &grad_dist_dev_, &grad_feat_dev_, &grad_alpha_dev_})
    b->bind(&rt_);
  if (scene_.semantics() == SemanticsKind::none) {
    spdlog::info("scene {} has no SAM masks (language_features/ or masks/): training appearance only", scene_.dir());
  } else if (config_.w_is <= 0 && config_.w_ic <= 0) {
    spdlog::info("mask loss weights are 0: training appearance only");
  } else {
    has_masks_ = true;
  }
  GrowthConfig gc = config_.growth_config(train_views_.size());
  size_t view_pixels = 0;
  for (int v : train_views_)
    view_pixels = std::max(view_pixels, static_cast<size_t>(scene_.views()[v].camera.width) *
                                            static_cast<size_t>(scene_.views()[v].camera.height));
  max_gaussians_ = config_.effective_max_gaussians(view_pixels, n);
  gc.max_gaussians = max_gaussians_;
  if (gc.max_gaussians > 0 && n > gc.max_gaussians)
    throw std::invalid_argument("--max-gaussians " + std::to_string(gc.max_gaussians) + " is below the " +
                                std::to_string(n) + " Gaussians the SfM points seed (" + std::to_string(model_.size()) +
                                " anchors x " + std::to_string(config_.anchors.children) +
                                "); raise it, or coarsen the voxels with --voxel-size / --top-cells");
  growth_.set_config(gc);
  growth_.reset(n);
}

Trainer::~Trainer() = default;

int Trainer::active_sh_degree() const {
  return std::min(config_.anchors.sh_degree, iteration_ / config_.effective_sh_interval());
}

double Trainer::offset_lr(int it) const {
  const double scale = config_.offset_lr_extent ? extent_ : 1.0;
  if (config_.offset_lr_init <= 0) return 0;
  const double p = std::clamp(static_cast<double>(it) / config_.iterations, 0.0, 1.0);
  return scale * std::exp(std::log(config_.offset_lr_init) * (1 - p) + std::log(config_.offset_lr_final) * p);
}

int Trainer::view_for_iteration(int it) const {
  return epoch_shuffled_view(train_views_, config_.seed, it);
}

bool Trainer::opacity_reset_due(int iteration) const {
  const int every = config_.opacity_reset_every;
  return every > 0 && iteration % every == 0 && iteration < config_.effective_grow_until() &&
         iteration <= config_.iterations;
}

AdamGroup& Trainer::adam_group(const std::string& name) {
  for (AdamGroup* g :
       {g_offset_.get(), g_scale_.get(), g_quat_.get(), g_opacity_.get(), g_dc_.get(), g_rest_.get(), g_feature_.get()})
    if (g->name() == name) return *g;
  throw std::invalid_argument("no optimiser group '" + name +
                              "' (offset, scaling, rotation, opacity, sh_dc, sh_rest, feature)");
}

const AnchorModel& Trainer::model() {
  if (host_stale_) {
    anchors_.download(model_);
    host_stale_ = false;
  }
  return model_;
}

StepStats Trainer::step(bool compute_offset_loss, const std::function<void()>& before_rounds) {
  StepStats st;
  const int it = iteration_;
  st.iteration = it + 1;
  st.stage2 = it >= config_.iterations;
  if (st.stage2 && !graph_ready_) {
    // Growing is over: the anchors keep their rows for the rest of the run.
    graph_ = AnchorGraph::build(model());
    prop_.set_graph(graph_);
    graph_ready_ = true;
    spdlog::debug("stage 2: anchor graph of {} anchors, {} edges", graph_.anchors(), graph_.edges());
  }
  st.view = view_for_iteration(it);
  st.sh_degree = active_sh_degree();
  const SceneView& view = scene_.views()[st.view];
  std::shared_ptr<const Image> target = scene_.image(st.view);
  const bool mask_step = has_masks_ && (it >= config_.effective_mask_from() || st.stage2);
  const int level = st.stage2 || mask_step ? 0 : config_.resolution_level(it);
  st.downscale = 1 << level;
  const Camera camera = level > 0 ? downscaled_camera(view.camera, st.downscale) : view.camera;

  RenderSettings settings;
  const float bg = config_.white_background ? 1.f : 0.f;
  settings.background = {bg, bg, bg};
  settings.features = mask_step;  // only the mask losses read the rendered features

  expander_.forward(anchors_, gaussians_, st.sh_degree);
  renderer_.forward(gaussians_, camera, settings);
  st.intersections = renderer_.stats().n_intersections;
  const int w = camera.width, h = camera.height;
  const size_t npix = static_cast<size_t>(w) * h;

  // The losses read the rendered planes where they are, on the device; only
  // the target goes up and the distortion plane comes back (for the report).
  target_planar_.resize(npix * 3);
  if (level > 0) {
    box_downscale_planar(*target, st.downscale, target_planar_.data());
  } else {
    for (size_t p = 0; p < npix; ++p)
      for (int c = 0; c < 3; ++c) target_planar_[c * npix + p] = target->rgb[p * 3 + c];
  }
  target_dev_.upload(target_planar_);
  image_loss_.enqueue(renderer_.device_rgb(), target_dev_, w, h, config_.lambda_ssim, &grad_rgb_dev_, nullptr,
                      ImageLayout::kPlanar);
  Renderer::DeviceOutputGrads og;
  og.rgb = &grad_rgb_dev_;
  const bool with_dist = config_.w_distortion > 0 && it >= config_.distortion_from;
  if (with_dist) {
    const float value = config_.w_distortion / static_cast<float>(npix);
    if (grad_dist_pixels_ != npix || grad_dist_value_ != value) {
      grad_dist_dev_.upload(std::vector<float>(npix, value));
      grad_dist_pixels_ = npix;
      grad_dist_value_ = value;
    }
    og.distortion = &grad_dist_dev_;
  }
  std::shared_ptr<const ViewMasks> masks;
  if (mask_step) masks = scene_.masks(st.view);
  if (masks) {
    if (mask_loss_.masks_key() != st.view || !mask_loss_.mask_count())
      mask_loss_.set_masks(config_.mask_unmasked_group ? with_unmasked_group(*masks) : *masks, st.view);
    const DeviceBuffer* alpha = config_.mask_alpha_normalise ? &renderer_.device_alpha() : nullptr;
    mask_loss_.enqueue(renderer_.device_feature(), alpha, w, h, ImageLayout::kPlanar, config_.w_is, config_.w_ic,
                       &grad_feat_dev_, alpha ? &grad_alpha_dev_ : nullptr);
    if (config_.mask_geometry) {
      og.feature = &grad_feat_dev_;
      if (alpha) og.alpha = &grad_alpha_dev_;
    } else {
      // A pass of the feature gradient alone (the alpha gradient only moves
      // geometry): its anchor-feature gradient is the one kept.
      Renderer::DeviceOutputGrads fg;
      fg.feature = &grad_feat_dev_;
      renderer_.backward(fg);
      expander_.backward(anchors_, renderer_.device_grads(), feature_grads_);
    }
  }
  renderer_.backward(og);
  const ImageLossResult lr = image_loss_.result();
  st.l1 = lr.l1;
  st.ssim = lr.ssim;
  st.psnr = lr.psnr();
  renderer_.device_distortion().download(distortion_host_, npix);
  double dist_sum = 0;
  for (float d : distortion_host_) dist_sum += d;
  st.distortion = dist_sum / static_cast<double>(npix);
  st.loss = lr.loss;
  if (with_dist) st.loss += config_.w_distortion * st.distortion;
  if (masks) {
    const MaskLossResult mr = mask_loss_.result();
    st.with_masks = true;
    st.l_is = mr.l_is;
    st.l_ic = mr.l_ic;
    st.masks = mr.masks;
    st.loss += mr.loss(config_.w_is, config_.w_ic);
  }

  expander_.backward(anchors_, renderer_.device_grads(), grads_);

  const size_t n = anchors_.gaussians();
  if (config_.w_offset > 0 && n > 0) {
    reg_value_.reserve(n * 4);
    cl::Kernel k = rt_.kernel("train.cl", "offset_reg", {});
    set_kernel_args(k, static_cast<cl_int>(n), config_.w_offset / static_cast<float>(n), anchors_.offset.get(),
                    grads_.offset.get(), reg_value_.get());
    rt_.launch("offset_reg", k, cl::NDRange(n), cl::NDRange(64));
    if (compute_offset_loss) {
      std::vector<float> v;
      reg_value_.download(v, n);
      double s = 0;
      for (float x : v) s += x;
      st.offset_reg = s / static_cast<double>(n);
      st.with_offset_loss = true;
      st.loss += config_.w_offset * st.offset_reg;
    }
  }

  adam_.clear_nonfinite();
  adam_.accumulate_nonfinite(grads_.offset, n * 3);
  adam_.accumulate_nonfinite(grads_.scale_logit, n * 3);
  adam_.accumulate_nonfinite(grads_.quat, n * 4);
  adam_.accumulate_nonfinite(grads_.opacity_logit, n);
  adam_.accumulate_nonfinite(grads_.sh_dc, n * 3);
  adam_.accumulate_nonfinite(grads_.sh_rest, n * 3 * kShRestCoeffs);
  DeviceBuffer& feature_grad = config_.mask_geometry ? grads_.feature : feature_grads_.feature;
  // Stage 2: the features step on every iteration, with or without masks.
  const bool with_prop = st.stage2 && config_.w_prop > 0;
  const bool step_features = st.with_masks || with_prop;
  if (with_prop) {
    const size_t fbytes = anchors_.anchors * 3 * sizeof(float);
    if (!st.with_masks && !config_.mask_geometry) {
      // No mask pass wrote this buffer this step.
      feature_grad.reserve(fbytes);
      feature_grad.fill_zero(fbytes);
    }
    prop_.enqueue(anchors_.feature, &feature_grad, anchors_.anchors, config_.w_prop);
    st.l_prop = prop_.result();
    st.loss += config_.w_prop * st.l_prop;
  }
  if (step_features) adam_.accumulate_nonfinite(feature_grad, anchors_.anchors * 3);
  st.nonfinite = adam_.read_nonfinite();
  if (st.nonfinite > 0 || !std::isfinite(st.loss)) {
    st.skipped = true;
    spdlog::warn("iteration {}: {} non-finite gradient values (loss {}); step skipped", st.iteration, st.nonfinite,
                 st.loss);
  } else {
    adam_.step(*g_offset_, anchors_.offset, grads_.offset, offset_lr(it));
    adam_.step(*g_scale_, anchors_.scale_logit, grads_.scale_logit, config_.scaling_lr);
    adam_.step(*g_quat_, anchors_.quat, grads_.quat, config_.rotation_lr);
    adam_.step(*g_opacity_, anchors_.opacity_logit, grads_.opacity_logit, config_.opacity_lr);
    adam_.step(*g_dc_, anchors_.sh_dc, grads_.sh_dc, config_.sh_dc_lr);
    adam_.step(*g_rest_, anchors_.sh_rest, grads_.sh_rest, config_.sh_rest_lr);
    if (step_features) {
      adam_.step(*g_feature_, anchors_.feature, feature_grad, config_.feature_lr);
      if (config_.feature_ball && anchors_.anchors > 0) {
        cl::Kernel k = rt_.kernel("train.cl", "feature_ball", {});
        set_kernel_args(k, static_cast<cl_int>(anchors_.anchors), anchors_.feature.get());
        rt_.launch("feature_ball", k, cl::NDRange((anchors_.anchors + 63) / 64 * 64), cl::NDRange(64));
      }
    }
    host_stale_ = true;
    // The renderer's gradients and radii of this view are still on the device.
    if (!st.stage2 && growth_.collecting(st.iteration))
      growth_.accumulate(*renderer_.device_grads().means2d, renderer_.device_radii(), w, h);
  }
  if (before_rounds) before_rounds();
  if (!st.stage2 && growth_.due(st.iteration)) {
    model();  // host values current
    // No opacity pruning shortly after a reset (a pure function of the
    // iteration, so a resumed run decides the same).
    GrowthConfig gc = config_.growth_config(train_views_.size());
    const int every = config_.opacity_reset_every;
    if (every > 0 && st.iteration > every) {
      const int last_reset = (st.iteration - 1) / every * every;  // strictly before this iteration
      if (opacity_reset_due(last_reset) && st.iteration - last_reset <= config_.opacity_reset_pause)
        gc.prune_opacity = gc.recycle_opacity = 0;
    }
    gc.max_gaussians = max_gaussians_;
    growth_.set_config(gc);
    const GrowthResult r = growth_.step(model_, config_.seed);
    spdlog::debug(
        "growing round at iteration {}: {} requests, {} anchors added ({} left out by the budgets), {} pruned ({} "
        "opacity, {} unseen)",
        st.iteration, r.requests, r.added, r.over_budget, r.pruned, r.pruned_opacity, r.pruned_unseen);
    st.grown = r.added;
    st.over_budget = r.over_budget;
    st.pruned = r.pruned;
    st.recycled = r.recycled;
    if (r.changed()) {
      if (model_.size() == 0)
        throw std::runtime_error("iteration " + std::to_string(st.iteration) + ": pruning removed every anchor (" +
                                 std::to_string(r.pruned_opacity) + " with mean opacity below " +
                                 std::to_string(config_.prune_opacity) + ", " + std::to_string(r.pruned_unseen) +
                                 " unseen); lower --prune-opacity or raise --prune-unseen-window");
      anchors_.upload(model_);
      for (AdamGroup* grp :
           {g_offset_.get(), g_scale_.get(), g_quat_.get(), g_opacity_.get(), g_dc_.get(), g_rest_.get()})
        grp->gather(r.child_rows);
      g_feature_->gather(r.anchor_rows);
    }
  }
  if (opacity_reset_due(st.iteration)) {
    // 3DGS: opacity = min(opacity, 0.01), through the logit; fresh moments.
    model();  // host values current
    const float cap = std::log(0.01f / 0.99f);
    for (float& x : model_.opacity_logit()) x = std::min(x, cap);
    anchors_.opacity_logit.upload(model_.opacity_logit());
    g_opacity_->zero_moments();
    st.opacity_reset = true;
    spdlog::debug("iteration {}: opacities reset to at most 0.01", st.iteration);
  }
  iteration_ = it + 1;
  return st;
}

EvalStats Trainer::evaluate(const std::vector<int>& views) {
  EvalStats ev;
  if (views.empty()) return ev;
  RenderSettings settings;
  const float bg = config_.white_background ? 1.f : 0.f;
  settings.background = {bg, bg, bg};
  expander_.forward(anchors_, gaussians_, active_sh_degree());
  for (int v : views) {
    renderer_.forward(gaussians_, scene_.views()[v].camera, settings);
    RenderOutput out = renderer_.download_output();
    for (float& x : out.rgb) x = std::clamp(x, 0.f, 1.f);
    std::shared_ptr<const Image> target = scene_.image(v);
    ImageLossResult r = image_loss_.forward_backward(out.rgb, target->rgb, out.width, out.height, config_.lambda_ssim,
                                                     nullptr, nullptr);
    ev.psnr += r.psnr();
    ev.ssim += r.ssim;
    ev.l1 += r.l1;
    ++ev.views;
  }
  ev.psnr /= ev.views;
  ev.ssim /= ev.views;
  ev.l1 /= ev.views;
  return ev;
}

std::string Trainer::checkpoint_path(const std::string& model_dir) {
  return (fs::path(model_dir) / "checkpoint.ag2gs").string();
}

nlohmann::json Trainer::scene_fingerprint() const {
  // Cameras hashed through their printed values (exact: %a is lossless).
  std::string cams;
  char buf[512];
  for (const SceneView& v : scene_.views()) {
    const Camera& c = v.camera;
    std::snprintf(buf, sizeof buf, "%s %d %d %a %a %a %a %d|", v.name.c_str(), c.width, c.height, c.fx, c.fy, c.cx,
                  c.cy, v.test ? 1 : 0);
    cams += buf;
    for (int i = 0; i < 3; ++i) {
      std::snprintf(buf, sizeof buf, "%a %a %a %a|", c.R(i, 0), c.R(i, 1), c.R(i, 2), c.t(i));
      cams += buf;
    }
  }
  std::vector<double> pts;
  pts.reserve(scene_.points().size() * 3);
  for (const Eigen::Vector3d& p : scene_.points()) pts.insert(pts.end(), {p.x(), p.y(), p.z()});
  char hex[2][20];
  std::snprintf(hex[0], sizeof hex[0], "%016llx", static_cast<unsigned long long>(fnv1a64(cams.data(), cams.size())));
  std::snprintf(hex[1], sizeof hex[1], "%016llx",
                static_cast<unsigned long long>(fnv1a64(pts.data(), pts.size() * sizeof(double))));
  return {{"views", scene_.views().size()},
          {"train_views", train_views_.size()},
          {"resolution", scene_.options().resolution},
          {"eval_split", scene_.options().eval},
          {"cameras_fnv1a64", hex[0]},
          {"points", scene_.points().size()},
          {"points_fnv1a64", hex[1]}};
}

void Trainer::save_checkpoint(const std::string& model_dir) {
  const AnchorModel& m = model();
  ModelArchive archive;
  m.to_archive(archive);
  nlohmann::json groups = nlohmann::json::object();
  for (AdamGroup* g : {g_offset_.get(), g_scale_.get(), g_quat_.get(), g_opacity_.get(), g_dc_.get(), g_rest_.get(),
                       g_feature_.get()}) {
    std::vector<float> v;
    const std::vector<int64_t> shape = {static_cast<int64_t>(g->rows()), g->row_size()};
    g->exp_avg().download(v, g->size());
    archive.put("adam/" + g->name() + "/exp_avg", v, shape);
    g->exp_avg_sq().download(v, g->size());
    archive.put("adam/" + g->name() + "/exp_avg_sq", v, shape);
    groups[g->name()] = {{"steps", g->steps()}, {"rows", g->rows()}, {"row_size", g->row_size()}};
  }
  const GrowthStatsHost gs = growth_.download();
  archive.put("growth/grad_sum", gs.grad_sum);
  archive.put("growth/count", gs.count);
  archive.put("growth/last_seen", gs.last_seen);
  if (graph_ready_) graph_.to_archive(archive);
  archive.meta["checkpoint"] = {{"iteration", iteration_},
                                {"config", config_.to_json()},
                                {"scene", scene_fingerprint()},
                                {"scene_dir", scene_.dir()},
                                {"adam", groups},
                                {"growth", {{"steps", gs.steps}, {"step", gs.step}}}};
  if (!run_record_.is_null()) archive.meta["checkpoint"]["run"] = run_record_;
  fs::create_directories(model_dir);
  write_model_archive(checkpoint_path(model_dir), archive);
}

void Trainer::resume(const std::string& model_dir) {
  const std::string path = checkpoint_path(model_dir);
  if (!fs::exists(path))
    throw std::runtime_error("no checkpoint " + path + " to resume from; train without --resume to start afresh");
  const ModelArchive archive = read_model_archive(path);
  auto fail = [&](const std::string& what) { throw std::runtime_error("checkpoint " + path + ": " + what); };
  if (!archive.meta.contains("checkpoint")) fail("no training state (not written by ag2gs train)");
  const nlohmann::json& ck = archive.meta["checkpoint"];
  try {
    const std::vector<std::string> scene_diff = config_differences(ck.at("scene"), scene_fingerprint());
    if (!scene_diff.empty()) {
      std::string list;
      for (const std::string& d : scene_diff) list += "\n  " + d;
      fail("written for another scene (" + ck.value("scene_dir", std::string("?")) +
           ") or resolution/split; checkpoint vs now:" + list);
    }
    const std::vector<std::string> config_diff = config_differences(ck.at("config"), config_.to_json());
    if (!config_diff.empty()) {
      std::string list;
      for (const std::string& d : config_diff) list += "\n  " + d;
      fail("written with another training config; checkpoint vs now:" + list);
    }
    const int iteration = ck.at("iteration").get<int>();
    if (iteration < 0 || iteration > config_.total_iterations())
      fail("iteration " + std::to_string(iteration) + " is outside the run's 0.." +
           std::to_string(config_.total_iterations()));
    AnchorModel m = AnchorModel::from_archive(archive);
    AnchorGraph graph;
    const bool has_graph = AnchorGraph::in_archive(archive);
    if (has_graph) {
      graph = AnchorGraph::from_archive(archive);
      if (!graph.matches(m)) fail("its anchor graph does not describe its anchors; train stage 2 afresh");
    }
    const int64_t a = static_cast<int64_t>(m.size()), n = static_cast<int64_t>(m.gaussians());
    std::vector<std::pair<AdamGroup*, int64_t>> groups;
    const std::pair<const char*, int> specs[] = {{"offset", 3},  {"scaling", 3}, {"rotation", 4},
                                                 {"opacity", 1}, {"sh_dc", 3},   {"sh_rest", 3 * kShRestCoeffs}};
    std::vector<std::unique_ptr<AdamGroup>> fresh;
    for (const auto& [name, row] : specs) fresh.push_back(std::make_unique<AdamGroup>(rt_, name, n, row));
    fresh.push_back(std::make_unique<AdamGroup>(rt_, "feature", a, 3));
    for (auto& g : fresh) {
      const std::string pre = "adam/" + g->name();
      const std::vector<int64_t> shape = {g->name() == "feature" ? a : n, g->row_size()};
      g->exp_avg().upload(archive.get<float>(pre + "/exp_avg", shape));
      g->exp_avg_sq().upload(archive.get<float>(pre + "/exp_avg_sq", shape));
      g->set_steps(ck.at("adam").at(g->name()).at("steps").get<int64_t>());
    }
    GrowthStatsHost gs;
    gs.grad_sum = archive.get<float>("growth/grad_sum", {n});
    gs.count = archive.get<int32_t>("growth/count", {n});
    gs.last_seen = archive.get<int32_t>("growth/last_seen", {n});
    gs.steps = ck.at("growth").at("steps").get<int>();
    gs.step = ck.at("growth").at("step").get<int>();
    // Everything read: now replace the state.
    model_ = std::move(m);
    anchors_.upload(model_);
    host_stale_ = false;
    g_offset_ = std::move(fresh[0]);
    g_scale_ = std::move(fresh[1]);
    g_quat_ = std::move(fresh[2]);
    g_opacity_ = std::move(fresh[3]);
    g_dc_ = std::move(fresh[4]);
    g_rest_ = std::move(fresh[5]);
    g_feature_ = std::move(fresh[6]);
    growth_.set_config(config_.growth_config(train_views_.size()));
    growth_.restore(gs);
    iteration_ = iteration;
    graph_ready_ = false;
    if (has_graph && iteration >= config_.iterations) {
      graph_ = std::move(graph);
      prop_.set_graph(graph_);
      graph_ready_ = true;
    }
  } catch (const nlohmann::json::exception& e) {
    fail(std::string("bad training state: ") + e.what());
  } catch (const std::invalid_argument& e) {
    fail(e.what());
  }
}

void Trainer::save(const std::string& model_dir) {
  save_checkpoint(model_dir);
  const AnchorModel& m = model();
  ModelArchive archive;
  m.to_archive(archive);
  if (graph_ready_) graph_.to_archive(archive);
  archive.meta["train"] = {{"stage", iteration_ > config_.iterations ? 2 : 1},
                           {"iteration", iteration_},
                           {"seed", config_.seed},
                           {"active_sh_degree", active_sh_degree()},
                           {"scene", scene_.dir()},
                           {"resolution", scene_.options().resolution},
                           {"eval_split", scene_.options().eval},
                           {"config", config_.to_json()}};
  fs::create_directories(model_dir);
  write_model_archive((fs::path(model_dir) / "model.ag2gs").string(), archive);
  GaussianSet set = expand_reference(m, active_sh_degree());
  write_ply((fs::path(model_dir) / "point_cloud.ply").string(), set, true, PlyValues::activated);
}

Stage3Summary run_stage3_on_model(Runtime& rt, Scene& scene, const std::string& model_dir,
                                  const std::vector<int>& views, const Stage3Config& config) {
  const auto t0 = std::chrono::steady_clock::now();
  const std::string path = (fs::path(model_dir) / "model.ag2gs").string();
  if (!fs::exists(path))
    throw std::runtime_error("no model " + path + " for stage 3; train stage 1 (and 2) into " + model_dir + " first");
  ModelArchive archive = read_model_archive(path);
  const AnchorModel model = AnchorModel::from_archive(archive);
  AnchorGraph graph;
  if (AnchorGraph::in_archive(archive)) graph = AnchorGraph::from_archive(archive);
  if (!AnchorGraph::in_archive(archive) || !graph.matches(model)) {
    spdlog::info("stage 3: {} has no current anchor graph (no stage 2?); building it", path);
    graph = AnchorGraph::build(model);
    graph.to_archive(archive);
  }
  const AnchorGraphView gv{graph.anchors(), graph.row_offsets().data(), graph.neighbours().data(), nullptr};
  Stage3Summary sum;
  sum.anchors = model.size();
  Clustering clustering;
  if (scene.semantics() == SemanticsKind::language_features) {
    Stage3Result r = run_stage3(rt, model, gv, scene, views, config);
    clustering = std::move(r.clustering);
    sum.language = true;
    sum.with_language = r.language.with_language();
    sum.stats = r.stats;
    sum.cluster_ms = r.cluster_ms;
    language_to_archive(archive, r.language, config.language);
  } else {
    const auto tc = std::chrono::steady_clock::now();
    std::vector<float> values = edge_feature_distances(gv, model.feature());
    if (config.cluster.edge_value == EdgeValue::bilateral_weight)
      for (float& v : values) v = static_cast<float>(std::exp(-double(v) * v / (2.0 * config.tau * config.tau)));
    AnchorGraphView g = gv;
    g.edge_values = values.data();
    clustering = cluster_anchors(g, config.cluster);
    sum.cluster_ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - tc).count();
    // A language entry from an earlier run would describe other clusters.
    ModelArchive kept;
    kept.source = archive.source;
    kept.meta = archive.meta;
    kept.meta.erase("language");
    for (const auto& [name, t] : archive.arrays())
      if (name.rfind("clusters/language", 0) != 0) kept.put_tensor(name, t);
    archive = std::move(kept);
    spdlog::info(
        "stage 3: scene {} has no CLIP features (language_features/<stem>_f.npy): clusters only, no "
        "language features attached",
        scene.dir());
  }
  sum.clusters = clustering.clusters();
  sum.components = clustering.components;
  sum.skipped_anchors = clustering.skipped_anchors;
  clustering_to_archive(archive, clustering, config.cluster);
  write_model_archive(path, archive);
  sum.total_ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
  return sum;
}

}  // namespace ag2gs
