#include "train/trainer.h"

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
#include <unordered_set>

#include "host/core/counter_rng.h"
#include "host/io/atomic_file.h"
#include "host/io/model_io.h"
#include "host/io/ply_io.h"
#include "host/render/importance.h"
#include "train/anchors/anchor_regularisers.h"

namespace fs = std::filesystem;

namespace ag2gs {

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
      sky_(rt),
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
  reg_value_.bind(&rt_);
  for (DeviceBuffer* b : {&target_dev_, &grad_rgb_dev_, &grad_dist_dev_, &grad_feat_dev_, &grad_alpha_dev_,
                          &sky_grad_alpha_, &sky_weight_dev_})
    b->bind(&rt_);
  std::vector<Eigen::Vector3d> seed_points = scene_.points();
  std::vector<Eigen::Vector3<uint8_t>> seed_colors = scene_.colors();
  choose_background(grid, seed_points, seed_colors);
  init_stats_ = model_.initialise_from_points(seed_points, seed_colors, grid, config_.anchors, config_.seed,
                                              scene_.points().size());
  if (model_.size() == 0)
    throw std::runtime_error("scene " + scene_.dir() + ": no anchor could be placed from " +
                             std::to_string(scene_.points().size()) + " SfM points (all non-finite or out of range)");
  extent_ = scene_.bounds().camera_radius > 0 ? scene_.bounds().camera_radius : scene_.bounds().longest_extent();
  anchors_.upload(model_);
  const size_t n = model_.gaussians();
  groups_ = std::make_unique<ParamGroups>(rt_, group_specs(), n, model_.size());
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

void Trainer::choose_background(const VoxelGrid& grid, std::vector<Eigen::Vector3d>& points,
                                std::vector<Eigen::Vector3<uint8_t>>& colors) {
  // What lies where no SfM point does (docs/design.md 5.7): an open sky (a
  // sky fits the open pixels closely), surfaces without SfM points (it does
  // not: a room's far walls and furniture), or too little to matter.
  const int asked = config_.sky_degree;  // kSkyAuto, -1 or a degree
  if (asked == -1 && !config_.far_shell) return;
  find_open_pixels();
  const bool open = sky_open_fraction_ >= TrainConfig::kSkyMinOpenShare;
  double fit_error = -1;  // of a degree-3 sky, which tells the two apart
  if (open) {
    config_.sky_degree = 3;
    fit_error = init_sky();
  }
  const bool room = open && fit_error > TrainConfig::kSkyMaxFitError;
  // In a room the sky stays too: it fills what the shell's Gaussians
  // leave open while they grow (the cup: 29.03 dB with both, 28.65 with
  // the shell alone).
  int degree = asked;
  if (asked == TrainConfig::kSkyAuto) degree = open ? 3 : -1;
  const std::string what =
      !open  ? fmt::format("too few for a sky or a far shell (both start at {:.0f}%)",
                           100.0 * TrainConfig::kSkyMinOpenShare)
      : room ? fmt::format(
                   "a sky fits them with an RMS error of {:.3f}, above {:.2f}: surfaces without SfM points, as "
                   "a room's far walls",
                   fit_error, TrainConfig::kSkyMaxFitError)
             : fmt::format("a sky fits them within {:.3f} (at most {:.2f}): an open sky", fit_error,
                           TrainConfig::kSkyMaxFitError);
  spdlog::info("background: {:.1f}% of the training pixels have no SfM point within {} px; {}",
               100.0 * sky_open_fraction_, sky_radius_, what);
  if (room && config_.far_shell) {
    const SceneBounds& b = scene_.bounds();
    const double radius = far_shell_radius(scene_.points(), b.camera_center, b.camera_radius);
    const size_t before = points.size();
    if (colors.size() != points.size()) colors.assign(points.size(), {128, 128, 128});  // a model without colours
    // Every second open radius: kumamon 30.95 / 30.62 / 30.30 dB with
    // 89k / 58k / 53k Gaussians at 1 / 2 / 3 radii (without: 30.08, 49k).
    const int stride = 2 * std::max(1, sky_radius_);
    std::vector<Eigen::Vector3d> shell;
    std::vector<Eigen::Vector3<uint8_t>> shell_colors;
    for (int v : train_views_)
      far_shell_points(scene_.views()[v].camera, sky_open_[v], scene_.image(v)->rgb, b.camera_center, radius, stride,
                       shell, shell_colors);
    // Only where the SfM points left the top layer empty (a voxel and its
    // 26 neighbours): on a small image of a scene whose surfaces all have
    // points, the gaps between their projections are open too, and a shell
    // there would crowd the surfaces' own anchors (the sample at -r 2,
    // 80x60: -1.3 dB).
    const int top = std::max(0, config_.anchors.init_layer);
    std::unordered_set<uint64_t> taken;  // the top-layer voxels holding an SfM point
    for (const Eigen::Vector3d& p : scene_.points()) {
      const Eigen::Vector3i c = grid.cell_of(top, p);
      if (p.allFinite() && cell_in_range(c)) taken.insert(anchor_voxel_key(top, c));
    }
    auto near_points = [&](const Eigen::Vector3i& c) {
      for (int dz = -1; dz <= 1; ++dz)
        for (int dy = -1; dy <= 1; ++dy)
          for (int dx = -1; dx <= 1; ++dx) {
            const Eigen::Vector3i n = c + Eigen::Vector3i(dx, dy, dz);
            if (cell_in_range(n) && taken.count(anchor_voxel_key(top, n))) return true;
          }
      return false;
    };
    size_t near = 0;
    for (size_t i = 0; i < shell.size(); ++i) {
      const Eigen::Vector3i c = grid.cell_of(top, shell[i]);
      if (!cell_in_range(c) || near_points(c)) {
        ++near;
        continue;
      }
      points.push_back(shell[i]);
      colors.push_back(shell_colors[i]);
    }
    spdlog::info(
        "far shell: {} points where the rays of open pixels (every {} px) leave a sphere of radius {:.4g} "
        "around the cameras, away from the SfM points' top-layer voxels ({} near them left out), seed "
        "anchors on the top layer; --far-shell false turns it off",
        points.size() - before, stride, radius, near);
  }
  config_.sky_degree = degree;
  if (degree < 0) {
    sky_.clear();
    sky_open_.clear();
  } else if (!open || degree != 3) {
    init_sky();  // the degree the flag asks for
  }
  spdlog::info("sky: {}{}", degree >= 0 ? fmt::format("SH degree {}", degree) : std::string("off, a fixed background"),
               asked == TrainConfig::kSkyAuto ? " (from the scene; --sky-degree D sets it)" : " (--sky-degree)");
}

void Trainer::find_open_pixels() {
  // Only open pixels (no SfM point projects near them) teach the sky: where
  // a point shows a surface, the Gaussians are to explain the colour.
  sky_open_.assign(scene_.views().size(), {});
  size_t open = 0, total = 0;
  for (int v : train_views_) {
    const Camera& cam = scene_.views()[v].camera;
    sky_radius_ = open_sky_radius(cam);
    sky_open_[v] = open_sky_pixels(cam, scene_.points(), sky_radius_);
    for (uint8_t o : sky_open_[v]) open += o;
    total += sky_open_[v].size();
  }
  sky_open_fraction_ = total ? static_cast<double>(open) / static_cast<double>(total) : 0.0;
}

double Trainer::init_sky() {
  // The sky starts as the least-squares fit to the open pixels of the
  // training photos; directions no open pixel saw stay at the fixed
  // background.
  const float bg = config_.white_background ? 1.f : 0.f;
  const std::vector<float> start = sky_constant(config_.sky_degree, {bg, bg, bg});
  sky_.set(config_.sky_degree, start);
  Eigen::MatrixXd gram, rhs;
  Eigen::Vector3d squares = Eigen::Vector3d::Zero();
  std::vector<float> weights;
  size_t largest = 0;
  for (int v : train_views_) {
    const Camera& cam = scene_.views()[v].camera;
    largest = std::max(largest, sky_open_[v].size());
    upload_target(*scene_.image(v), 1, target_planar_, target_dev_);
    open_sky_weights(sky_open_[v], cam.width, cam.height, 1, weights);
    sky_weight_dev_.upload(weights);
    sky_.add_fit(target_dev_, cam, gram, rhs, &sky_weight_dev_, &squares);
  }
  // The ridge is at least what 1% of one view's pixels give: a few open
  // pixels cannot bend the whole sky.
  const std::vector<float> fitted = Sky::solve_fit(gram, rhs, start, 0.01 * static_cast<double>(largest));
  sky_.set(config_.sky_degree, fitted);
  const double error = Sky::fit_residual_rms(gram, rhs, squares, fitted);
  spdlog::info(
      "sky start: SH degree {} fitted to the {:.1f}% of the training pixels with no SfM point within {} px "
      "(RMS error {:.3f})",
      config_.sky_degree, 100.0 * sky_open_fraction_, sky_radius_, error);
  return error;
}

int Trainer::active_sh_degree() const {
  return std::min(config_.anchors.sh_degree, iteration_ / config_.effective_sh_interval());
}

double Trainer::offset_lr(int it) const {
  const double scale = config_.offset_lr_extent ? extent_ : 1.0;
  return scale *
         exp_decay_lr(config_.offset_lr_init, config_.offset_lr_final, static_cast<double>(it) / config_.iterations);
}

int Trainer::view_for_iteration(int it) const {
  return epoch_shuffled_view(train_views_, config_.seed, it);
}

bool Trainer::opacity_reset_due(int iteration) const {
  const int every = config_.opacity_reset_every;
  return every > 0 && iteration % every == 0 && iteration < config_.effective_grow_until() &&
         iteration <= config_.iterations;
}

std::vector<ParamGroupSpec> Trainer::group_specs() const {
  std::vector<ParamGroupSpec> specs = {{"offset", 3},
                                       {"scaling", 3},
                                       {"rotation", 4},
                                       {"opacity", 1},
                                       {"sh_dc", 3},
                                       {"sh_rest", 3 * kShRestCoeffs},
                                       {"feature", 3, /*per_anchor=*/true}};
  if (config_.sky_degree >= 0)
    specs.push_back({"sky", 3, false, static_cast<size_t>(sh_coeffs_for_degree(config_.sky_degree))});
  return specs;
}

AdamGroup& Trainer::adam_group(const std::string& name) {
  return groups_->named(name);
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
  st.iteration = iteration_ + 1;
  st.stage2 = iteration_ >= config_.iterations;
  const std::pair<int, int> size = render_and_losses(st, compute_offset_loss);
  update(st, size.first, size.second);
  if (before_rounds) before_rounds();
  if (!st.stage2 && growth_.due(st.iteration)) growing_round(st);
  if (!st.stage2 && config_.prune_importance > 0 && st.iteration == config_.effective_prune_importance_at())
    importance_prune(st);
  if (!st.stage2 && st.iteration == config_.iterations && config_.final_prune_opacity > 0) final_prune(st);
  if (opacity_reset_due(st.iteration)) reset_opacities(st);
  iteration_ = st.iteration;
  return st;
}

int Trainer::training_level(int it, bool stage2) const {
  const bool mask_step = has_masks_ && (it >= config_.effective_mask_from() || stage2);
  return stage2 || mask_step ? 0 : config_.resolution_level(it);
}

std::pair<int, int> Trainer::render_and_losses(StepStats& st, bool compute_offset_loss) {
  const int it = st.iteration - 1;
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
  const int level = training_level(it, st.stage2);
  st.downscale = 1 << level;
  const Camera camera = level > 0 ? downscaled_camera(view.camera, st.downscale) : view.camera;

  RenderSettings settings;
  const float bg = config_.white_background && !sky_.enabled() ? 1.f : 0.f;
  settings.background = {bg, bg, bg};
  settings.features = mask_step;  // only the mask losses read the rendered features
  settings.lowpass = config_.lowpass_at_level(level);

  expander_.forward(anchors_, gaussians_, st.sh_degree);
  renderer_.forward(gaussians_, camera, settings);
  const DeviceBuffer& rgb =
      sky_.enabled() ? sky_.compose(renderer_.device_rgb(), renderer_.device_alpha(), camera) : renderer_.device_rgb();
  st.intersections = renderer_.stats().n_intersections;
  const int w = camera.width, h = camera.height;
  const size_t npix = static_cast<size_t>(w) * h;

  // The losses read the rendered planes where they are, on the device; only
  // the target goes up and the distortion plane comes back (for the report).
  upload_target(*target, st.downscale, target_planar_, target_dev_);
  image_loss_.enqueue(rgb, target_dev_, w, h, config_.lambda_ssim, &grad_rgb_dev_, nullptr, ImageLayout::kPlanar);
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
  if (sky_.enabled()) {
    // The sky's alpha gradient joins the mask loss's, or stands alone.
    const bool add = og.alpha != nullptr;
    DeviceBuffer& ga = add ? grad_alpha_dev_ : sky_grad_alpha_;
    open_sky_weights(sky_open_[st.view], view.camera.width, view.camera.height, st.downscale, sky_weight_host_);
    sky_weight_dev_.upload(sky_weight_host_);
    sky_.backward(grad_rgb_dev_, renderer_.device_alpha(), camera, ga, add, &sky_weight_dev_);
    og.alpha = &ga;
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
    enqueue_offset_regulariser(rt_, n, config_.w_offset, anchors_.offset, grads_.offset, reg_value_);
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

  return {w, h};
}

void Trainer::update(StepStats& st, int w, int h) {
  const int it = st.iteration - 1;
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
  std::vector<GroupStep> updates = {{kOffset, &anchors_.offset, &grads_.offset, offset_lr(it)},
                                    {kScaling, &anchors_.scale_logit, &grads_.scale_logit, config_.scaling_lr},
                                    {kRotation, &anchors_.quat, &grads_.quat, config_.rotation_lr},
                                    {kOpacity, &anchors_.opacity_logit, &grads_.opacity_logit, config_.opacity_lr},
                                    {kShDc, &anchors_.sh_dc, &grads_.sh_dc, config_.sh_dc_lr},
                                    {kShRest, &anchors_.sh_rest, &grads_.sh_rest, config_.sh_rest_lr}};
  // Only the rest coefficients of the degrees switched on so far: the others
  // have had zero gradients since the start (the degree never goes down).
  updates.back().cols = 3 * (sh_coeffs_for_degree(active_sh_degree()) - 1);
  if (step_features) updates.push_back({kFeature, &anchors_.feature, &feature_grad, config_.feature_lr});
  if (sky_.enabled()) updates.push_back({kSky, &sky_.coefficients(), &sky_.gradient(), config_.sky_lr});
  st.skipped = !groups_->step_if_finite(adam_, updates, st.iteration, st.loss, &st.nonfinite);
  if (!st.skipped) {
    if (step_features && config_.feature_ball) enqueue_feature_ball(rt_, anchors_.anchors, anchors_.feature);
    host_stale_ = true;
    // The renderer's gradients and radii of this view are still on the device.
    if (!st.stage2 && growth_.collecting(st.iteration))
      growth_.accumulate(*renderer_.device_grads().means2d, renderer_.device_radii(), w, h);
  }
}

void Trainer::growing_round(StepStats& st) {
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
    groups_->gather(r.child_rows, r.anchor_rows);
  }
}

void Trainer::remove_anchor_rows(const std::vector<uint8_t>& keep) {
  const std::vector<int> kept = model_.remove_anchors(keep);
  anchors_.upload(model_);
  groups_->gather(AnchorModel::child_rows(kept, model_.children()), kept);
  growth_.reset(model_.gaussians());  // the statistics follow the rows
}

void Trainer::importance_prune(StepStats& st) {
  model();  // host values current
  expander_.forward(anchors_, gaussians_, active_sh_degree());
  // The views at this step's resolution (the one the model is being fitted
  // at; a level-L walk has 4^L times fewer pixels to blend). Each pixel's
  // weights then cover 4^L full-resolution pixels, the same scale for every
  // anchor, and the prune takes a share of the total, so the choice is
  // about the same at a fraction of the cost.
  const int level = training_level(st.iteration - 1, false);
  RenderSettings settings;
  settings.lowpass = config_.lowpass_at_level(level);
  // The weights need no colour: the projection skips the SH terms past the
  // constant one (they change no weight, culling reads every coefficient).
  settings.sh_degree = 0;
  std::vector<Camera> cameras;
  for (int v : train_views_) {
    const Camera& c = scene_.views()[v].camera;
    cameras.push_back(level > 0 ? downscaled_camera(c, 1 << level) : c);
  }
  // This step's gradients and images are spent (the optimiser has stepped);
  // the sweep needs neither, and the next step allocates them again.
  grads_.release();
  feature_grads_.release();
  renderer_.release_images_and_gradients();
  // On a simulator every launch of the sweep pays for the memory held, so
  // the optimiser's moments and the anchors (model_ holds their values:
  // model() above) wait in host memory meanwhile; the same bits return
  // (the anchors with remove_anchor_rows' upload when the prune removes any).
  const bool park = rt_.simulated();
  if (park) {
    groups_->park();
    anchors_.release();
  }
  std::vector<double> per_child;
  try {
    per_child = blend_weight_sums(renderer_, gaussians_, cameras, settings);
  } catch (...) {
    if (park) {
      groups_->unpark();
      anchors_.upload(model_);
    }
    throw;
  }
  if (park) groups_->unpark();
  const size_t before = model_.size();
  const std::vector<uint8_t> keep = least_drawing_anchors(per_child, model_.children(), config_.prune_importance);
  const size_t removed = before - static_cast<size_t>(std::count(keep.begin(), keep.end(), uint8_t{1}));
  if (removed == 0) {
    if (park) anchors_.upload(model_);
    return;
  }
  const int K = model_.children();
  double total = 0, gone = 0;
  for (size_t i = 0; i < per_child.size(); ++i) {
    total += per_child[i];
    if (!keep[i / K]) gone += per_child[i];
  }
  remove_anchor_rows(keep);
  st.pruned += static_cast<int>(removed);
  spdlog::info(
      "iteration {}: removed the {} anchors that draw least, together {:.3g}% of the training views' blending weight "
      "(at most {:.3g}%) -> {} anchors, {} Gaussians",
      st.iteration, removed, total > 0 ? 100 * gone / total : 0.0, 100 * config_.prune_importance, model_.size(),
      model_.gaussians());
}

void Trainer::final_prune(StepStats& st) {
  model();  // host values current
  const size_t before = model_.size();
  std::vector<uint8_t> keep(before, 1);
  size_t removed = 0;
  for (size_t a = 0; a < before; ++a)
    if (mean_opacity_below(model_, a, config_.final_prune_opacity)) {
      keep[a] = 0;
      ++removed;
    }
  if (removed == 0) return;
  if (removed == before) {
    spdlog::warn("iteration {}: every anchor's children have a mean opacity below {}; the final prune keeps them all",
                 st.iteration, config_.final_prune_opacity);
    return;
  }
  remove_anchor_rows(keep);
  st.pruned += static_cast<int>(removed);
  spdlog::info("iteration {}: removed {} anchors whose children's mean opacity is below {} -> {} anchors, {} Gaussians",
               st.iteration, removed, config_.final_prune_opacity, model_.size(), model_.gaussians());
}

void Trainer::reset_opacities(StepStats& st) {
  // 3DGS: opacity = min(opacity, 0.01), through the logit; fresh moments.
  model();  // host values current
  cap_opacity_logits(model_.opacity_logit());
  anchors_.opacity_logit.upload(model_.opacity_logit());
  (*groups_)[kOpacity].zero_moments();
  st.opacity_reset = true;
  spdlog::debug("iteration {}: opacities reset to at most 0.01", st.iteration);
}

EvalStats Trainer::evaluate(const std::vector<int>& views) {
  if (views.empty()) return {};
  RenderSettings settings;
  const float bg = config_.white_background && !sky_.enabled() ? 1.f : 0.f;
  settings.background = {bg, bg, bg};
  expander_.forward(anchors_, gaussians_, active_sh_degree());
  return evaluate_views(renderer_, image_loss_, gaussians_, scene_, views, settings, config_.lambda_ssim,
                        sky_.enabled() ? &sky_ : nullptr);
}

}  // namespace ag2gs
