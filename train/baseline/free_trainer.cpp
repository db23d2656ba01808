#include "train/baseline/free_trainer.h"

#include <spdlog/spdlog.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <filesystem>
#include <limits>
#include <stdexcept>

#include "host/core/counter_rng.h"
#include "host/core/gaussians.h"
#include "host/core/nearest.h"
#include "host/core/scalar_math.h"
#include "host/device/kernel_call.h"
#include "host/io/ply_io.h"
#include "host/render/gaussian_buffers.h"
#include "train/baseline/free_train_settings.h"

namespace fs = std::filesystem;

namespace ag2gs {

namespace {

constexpr int kRest = 15;                   // SH rest coefficients per channel (degree 3)
constexpr double kSplitScaleDivisor = 1.6;  // 3DGS: 0.8 x the number of samples (2)

// A uniform double in (0, 1) from 53 bits of a hash.
double unit_open(uint64_t h) {
  return (static_cast<double>(h >> 11) + 0.5) * (1.0 / 9007199254740992.0);
}

}  // namespace

// ------------------------------------------------------------------ config
void FreeTrainConfig::validate() const {
  auto bad = [](const std::string& what) { throw std::invalid_argument("FreeTrainConfig: " + what); };
  // Each setting's own range (train/baseline/free_train_settings.cpp), then
  // what ties settings together.
  if (const std::string p = settings_problem(free_train_settings(), *this); !p.empty()) bad(p);
  if (!(init_opacity > 0 && init_opacity < 1)) bad("init_opacity must be in (0, 1)");
  if (position_lr_init > 0 && !(position_lr_final > 0))
    bad("position_lr_final must be > 0 when position_lr_init is (exponential decay)");
}

int FreeTrainConfig::effective_sh_interval() const {
  if (sh_interval > 0) return sh_interval;
  return std::max(1, std::min(1000, iterations / (sh_degree + 1)));
}

int FreeTrainConfig::effective_densify_until() const {
  return densify_until > 0 ? densify_until : static_cast<int>(static_cast<int64_t>(iterations) / 2);
}

bool FreeTrainConfig::densify_due(int it) const {
  return densify_every > 0 && it >= densify_from && it <= effective_densify_until() && it % densify_every == 0;
}

bool FreeTrainConfig::reset_due(int it) const {
  if (it > effective_densify_until()) return false;
  // 3DGS also resets once at the first densification on a white background.
  if (white_background && densify_every > 0 && it == densify_from) return true;
  return opacity_reset_every > 0 && it % opacity_reset_every == 0;
}

bool FreeTrainConfig::prune_big_at(int it) const {
  return opacity_reset_every > 0 && it > opacity_reset_every;
}

nlohmann::json FreeTrainConfig::to_json() const {
  return settings_to_json(free_train_settings(), *this);
}

// ------------------------------------------------------------------ parameters
void FreeGaussians::resize(size_t n) {
  mean.resize(n * 3);
  log_scale.resize(n * 3);
  quat.resize(n * 4);
  opacity_logit.resize(n);
  sh_dc.resize(n * 3);
  sh_rest.resize(n * kRest * 3);
}

FreeGaussians FreeGaussians::from_points(const std::vector<Eigen::Vector3d>& points,
                                         const std::vector<Eigen::Vector3<uint8_t>>& colors, float init_opacity) {
  std::vector<int> ids;
  for (size_t i = 0; i < points.size(); ++i)
    if (points[i].allFinite()) ids.push_back(static_cast<int>(i));
  const size_t n = ids.size();
  // Mean squared distance to the 3 nearest other points (3DGS's distCUDA2).
  const std::vector<double> nearest = nearest_squared_distances(points, 3);
  std::vector<double> dist2(n, 0.0);
  for (size_t i = 0; i < n; ++i) {
    double sum = 0;
    int k = 0;
    for (int j = 0; j < 3; ++j)
      if (const double b = nearest[static_cast<size_t>(ids[i]) * 3 + j]; std::isfinite(b)) sum += b, ++k;
    dist2[i] = k > 0 ? sum / k : 1.0;  // a lone point: unit scale
  }
  FreeGaussians g;
  g.resize(n);
  const float opacity = static_cast<float>(logit(init_opacity));
  for (size_t i = 0; i < n; ++i) {
    const Eigen::Vector3d& p = points[ids[i]];
    const double s = std::log(std::sqrt(std::max(dist2[i], 1e-7)));
    for (int c = 0; c < 3; ++c) {
      g.mean[i * 3 + c] = static_cast<float>(p[c]);
      g.log_scale[i * 3 + c] = static_cast<float>(s);
      const double colour = ids[i] < static_cast<int>(colors.size()) ? colors[ids[i]][c] / 255.0 : 0.5;
      g.sh_dc[i * 3 + c] = static_cast<float>((colour - 0.5) / kShC0);
    }
    g.quat[i * 4] = 1.f;
    g.opacity_logit[i] = opacity;
  }
  return g;
}

GaussianSet FreeGaussians::to_stored_set(int sh_degree) const {
  GaussianSet s;
  s.sh_degree = sh_degree;
  const size_t n = size();
  const int k = sh_coeffs_for_degree(sh_degree);
  s.resize(n);
  s.means = mean;
  s.scales = log_scale;
  s.quats = quat;
  s.opacities = opacity_logit;
  for (size_t i = 0; i < n; ++i) {
    for (int c = 0; c < 3; ++c) s.sh[(i * k) * 3 + c] = sh_dc[i * 3 + c];
    for (int j = 1; j < k; ++j)
      for (int c = 0; c < 3; ++c) s.sh[(i * k + j) * 3 + c] = sh_rest[(i * kRest + j - 1) * 3 + c];
  }
  return s;
}

// ------------------------------------------------------------------ densification
std::vector<int> DensifyPlan::adam_rows() const {
  std::vector<int> rows(source.size());
  for (size_t r = 0; r < source.size(); ++r) rows[r] = kind[r] == RowKind::kept ? source[r] : -1;
  return rows;
}

DensifyPlan plan_densification(const FreeGaussians& g, const DensifyStats& stats, const FreeTrainConfig& config,
                               double extent, bool prune_big) {
  const size_t n = g.size();
  if (stats.grad_sum.size() != n || stats.count.size() != n || stats.max_radius.size() != n)
    throw std::invalid_argument("plan_densification: statistics for " + std::to_string(stats.grad_sum.size()) +
                                " Gaussians, parameters for " + std::to_string(n));
  DensifyPlan plan;
  plan.before = n;
  const double dense_limit = config.percent_dense * extent;
  const double world_limit = config.max_world_size * extent;
  const bool screen = prune_big && config.max_screen_size > 0;
  const bool world = prune_big && config.max_world_size > 0;
  auto max_scale = [&](size_t i, double log_divisor) {
    float m = std::max({g.log_scale[i * 3], g.log_scale[i * 3 + 1], g.log_scale[i * 3 + 2]});
    return std::exp(static_cast<double>(m) - log_divisor);
  };
  // A row's fate under the prune: opacity (the same for a row and its
  // copies), and when prune_big the radius (0 for new rows) and world size.
  auto pruned = [&](size_t i, bool is_new, double log_divisor) {
    if (sigmoidf(g.opacity_logit[i]) < config.prune_opacity) return true;
    if (screen && !is_new && stats.max_radius[i] > config.max_screen_size) return true;
    if (world && max_scale(i, log_divisor) > world_limit) return true;
    return false;
  };
  std::vector<uint8_t> clone(n, 0), split(n, 0);
  for (size_t i = 0; i < n; ++i) {
    const double grad = stats.count[i] > 0 ? static_cast<double>(stats.grad_sum[i]) / stats.count[i] : 0.0;
    if (!(grad >= config.grad_threshold)) continue;
    if (max_scale(i, 0) <= dense_limit)
      clone[i] = 1, ++plan.cloned;
    else
      split[i] = 1, ++plan.split;
  }
  auto add = [&](size_t i, RowKind kind, int sample) {
    plan.source.push_back(static_cast<int>(i));
    plan.kind.push_back(kind);
    plan.split_sample.push_back(sample);
  };
  const double log_div = std::log(kSplitScaleDivisor);
  for (size_t i = 0; i < n; ++i) {
    if (split[i]) continue;
    if (pruned(i, false, 0))
      ++plan.pruned;
    else
      add(i, RowKind::kept, 0);
  }
  for (size_t i = 0; i < n; ++i) {
    if (!clone[i]) continue;
    if (pruned(i, true, 0))
      ++plan.pruned;
    else
      add(i, RowKind::clone, 0);
  }
  for (size_t i = 0; i < n; ++i) {
    if (!split[i]) continue;
    for (int s = 0; s < 2; ++s) {
      if (pruned(i, true, log_div))
        ++plan.pruned;
      else
        add(i, RowKind::split, s);
    }
  }
  plan.after = plan.source.size();
  return plan;
}

std::array<double, 3> split_normal(uint64_t seed, int iteration, int row, int sample) {
  // Box-Muller on counter-based uniforms: pairs (u1, u2) from hashes of
  // (seed, iteration, row, sample, draw).
  const uint64_t base =
      splitmix64(splitmix64(splitmix64(seed ^ 0x73706c69745f6761ull) ^ static_cast<uint64_t>(iteration)) ^
                 static_cast<uint64_t>(row)) ^
      static_cast<uint64_t>(sample);
  std::array<double, 3> z{};
  for (int d = 0; d < 2; ++d) {
    const double u1 = unit_open(splitmix64(base + 2 * d + 1));
    const double u2 = unit_open(splitmix64(base + 2 * d + 2));
    const double r = std::sqrt(-2 * std::log(u1));
    const double t = 2 * M_PI * u2;
    if (d == 0) {
      z[0] = r * std::cos(t);
      z[1] = r * std::sin(t);
    } else {
      z[2] = r * std::cos(t);
    }
  }
  return z;
}

FreeGaussians apply_densification(const FreeGaussians& g, const DensifyPlan& plan, uint64_t seed, int iteration) {
  FreeGaussians out;
  const size_t m = plan.source.size();
  out.resize(m);
  const float log_div = static_cast<float>(std::log(kSplitScaleDivisor));
  for (size_t r = 0; r < m; ++r) {
    const size_t i = static_cast<size_t>(plan.source[r]);
    std::copy_n(&g.mean[i * 3], 3, &out.mean[r * 3]);
    std::copy_n(&g.log_scale[i * 3], 3, &out.log_scale[r * 3]);
    std::copy_n(&g.quat[i * 4], 4, &out.quat[r * 4]);
    out.opacity_logit[r] = g.opacity_logit[i];
    std::copy_n(&g.sh_dc[i * 3], 3, &out.sh_dc[r * 3]);
    std::copy_n(&g.sh_rest[i * kRest * 3], kRest * 3, &out.sh_rest[r * kRest * 3]);
    if (plan.kind[r] != RowKind::split) continue;
    // Sample from the source Gaussian: mean + R(q) diag(s) z (3DGS draws
    // normal(0, s) per axis and rotates it).
    const std::array<double, 3> z = split_normal(seed, iteration, static_cast<int>(i), plan.split_sample[r]);
    Eigen::Quaterniond q(g.quat[i * 4], g.quat[i * 4 + 1], g.quat[i * 4 + 2], g.quat[i * 4 + 3]);
    const double qn = q.norm();
    const Eigen::Matrix3d R = qn > 0 ? Eigen::Matrix3d(q.normalized()) : Eigen::Matrix3d::Identity();
    Eigen::Vector3d local;
    for (int c = 0; c < 3; ++c) local[c] = std::exp(static_cast<double>(g.log_scale[i * 3 + c])) * z[c];
    const Eigen::Vector3d p = R * local;
    for (int c = 0; c < 3; ++c) {
      out.mean[r * 3 + c] = static_cast<float>(g.mean[i * 3 + c] + p[c]);
      out.log_scale[r * 3 + c] = g.log_scale[i * 3 + c] - log_div;
    }
  }
  return out;
}

// ------------------------------------------------------------------ trainer
FreeTrainer::FreeTrainer(Runtime& rt, Scene& scene, const FreeTrainConfig& config)
    : rt_(rt), scene_(scene), config_(config), gaussians_(rt), renderer_(rt), image_loss_(rt), adam_(rt, config.adam) {
  config_.validate();
  scene_.require_points();
  train_views_ = scene_.train_views();
  if (train_views_.empty()) throw std::runtime_error("scene " + scene_.dir() + " has no training views");
  extent_ = scene_.bounds().camera_radius > 0 ? scene_.bounds().camera_radius : scene_.bounds().longest_extent();
  if (!(extent_ > 0) || !std::isfinite(extent_)) extent_ = 1;
  for (DeviceBuffer* b :
       {&mean_, &log_scale_, &quat_, &opacity_logit_, &sh_dc_, &sh_rest_, &v_log_scale_, &v_opacity_logit_, &v_sh_dc_,
        &v_sh_rest_, &grad_sum_, &count_, &max_radius_, &target_dev_, &grad_rgb_dev_})
    b->bind(&rt_);
  const FreeGaussians g = FreeGaussians::from_points(scene_.points(), scene_.colors(), config_.init_opacity);
  if (g.size() == 0)
    throw std::runtime_error("scene " + scene_.dir() + ": none of the " + std::to_string(scene_.points().size()) +
                             " SfM points in " + scene_.points_path() + " is finite; re-run the reconstruction");
  upload(g);
}

FreeTrainer::~FreeTrainer() = default;

int FreeTrainer::active_sh_degree() const {
  return std::min(config_.sh_degree, iteration_ / config_.effective_sh_interval());
}

double FreeTrainer::position_lr(int it) const {
  return extent_ * exp_decay_lr(config_.position_lr_init, config_.position_lr_final,
                                static_cast<double>(it) / config_.iterations);
}

int FreeTrainer::view_for_iteration(int it) const {
  return epoch_shuffled_view(train_views_, config_.seed, it);
}

void FreeTrainer::upload_params(const FreeGaussians& g) {
  n_ = g.size();
  mean_.upload(g.mean);
  log_scale_.upload(g.log_scale);
  quat_.upload(g.quat);
  opacity_logit_.upload(g.opacity_logit);
  sh_dc_.upload(g.sh_dc);
  sh_rest_.upload(g.sh_rest);
}

void FreeTrainer::upload(const FreeGaussians& g) {
  const bool same = groups_ && g.size() == n_;
  upload_params(g);
  if (!same)
    groups_ = std::make_unique<ParamGroups>(
        rt_,
        std::vector<ParamGroupSpec>{
            {"means", 3}, {"scaling", 3}, {"rotation", 4}, {"opacity", 1}, {"sh_dc", 3}, {"sh_rest", 3 * kRest}},
        n_, 0);
  reset_stats();
}

void FreeTrainer::reset_stats() {
  const size_t bytes = std::max<size_t>(n_ * 4, 4);
  grad_sum_.fill_zero(bytes);
  count_.fill_zero(bytes);
  max_radius_.fill_zero(bytes);
}

FreeGaussians FreeTrainer::download() {
  FreeGaussians g;
  mean_.download(g.mean, n_ * 3);
  log_scale_.download(g.log_scale, n_ * 3);
  quat_.download(g.quat, n_ * 4);
  opacity_logit_.download(g.opacity_logit, n_);
  sh_dc_.download(g.sh_dc, n_ * 3);
  sh_rest_.download(g.sh_rest, n_ * kRest * 3);
  return g;
}

DensifyStats FreeTrainer::download_stats() {
  DensifyStats s;
  grad_sum_.download(s.grad_sum, n_);
  count_.download(s.count, n_);
  max_radius_.download(s.max_radius, n_);
  return s;
}

void FreeTrainer::activate(int sh_degree) {
  const int sh_out = sh_coeffs_for_degree(sh_degree);
  gaussians_.n = n_;
  gaussians_.sh_degree = sh_degree;
  const size_t nb = std::max<size_t>(n_, 1) * sizeof(float);
  gaussians_.means.reserve(nb * 3);
  gaussians_.scales.reserve(nb * 3);
  gaussians_.quats.reserve(nb * 4);
  gaussians_.opacities.reserve(nb);
  gaussians_.sh.reserve(nb * 3 * sh_out);
  gaussians_.features.reserve(nb * 3);
  cl::Kernel k = rt_.kernel("free_trainer.cl", "free_activate", {});
  const size_t f4 = sizeof(float);
  KernelCall call(k);
  call.arg("n", static_cast<cl_int>(n_))
      .buffer("mean", mean_, n_ * 3 * f4)
      .buffer("log_scale", log_scale_, n_ * 3 * f4)
      .buffer("quat", quat_, n_ * 4 * f4)
      .buffer("opacity_logit", opacity_logit_, n_ * f4)
      .buffer("sh_dc", sh_dc_, n_ * 3 * f4)
      .buffer("sh_rest", sh_rest_, sh_out > 1 ? n_ * kRest * 3 * f4 : 0)
      .arg("sh_out", static_cast<cl_int>(sh_out));
  gaussian_buffers(call, gaussians_).done();
  rt_.launch("free_activate", k, cl::NDRange(std::max<size_t>(n_, 1)), cl::NDRange(64));
}

void FreeTrainer::activate_backward(const DeviceGaussianGrads& rg) {
  const size_t nb = std::max<size_t>(n_, 1) * sizeof(float);
  v_log_scale_.reserve(nb * 3);
  v_opacity_logit_.reserve(nb);
  v_sh_dc_.reserve(nb * 3);
  v_sh_rest_.reserve(nb * 3 * kRest);
  cl::Kernel k = rt_.kernel("free_trainer.cl", "free_activate_bwd", {});
  const int sh_in = sh_coeffs_for_degree(rg.sh_degree);
  const size_t f4 = sizeof(float);
  KernelCall(k)
      .arg("n", static_cast<cl_int>(n_))
      .buffer("log_scale", log_scale_, n_ * 3 * f4)
      .buffer("opacity_logit", opacity_logit_, n_ * f4)
      .buffer("v_scales", *rg.scales, n_ * 3 * f4)
      .buffer("v_opacities", *rg.opacities, n_ * f4)
      .buffer("v_sh", *rg.sh, n_ * sh_in * 3 * f4)
      .arg("sh_in", static_cast<cl_int>(sh_in))
      .buffer("v_log_scale", v_log_scale_, n_ * 3 * f4)
      .buffer("v_opacity_logit", v_opacity_logit_, n_ * f4)
      .buffer("v_sh_dc", v_sh_dc_, n_ * 3 * f4)
      .buffer("v_sh_rest", v_sh_rest_, n_ * kRest * 3 * f4)
      .done();
  rt_.launch("free_activate_bwd", k, cl::NDRange(std::max<size_t>(n_, 1)), cl::NDRange(64));
}

void FreeTrainer::accumulate_densify_stats(const DeviceGaussianGrads& rg, int width, int height) {
  if (n_ == 0) return;
  cl::Kernel k = rt_.kernel("free_trainer.cl", "free_densify_accumulate", {});
  KernelCall(k)
      .arg("n", static_cast<cl_int>(n_))
      .buffer("v_means2d", *rg.means2d, n_ * 2 * sizeof(float))
      .buffer("radii", renderer_.device_radii(), n_ * sizeof(int))
      .arg("scale_x", 0.5f * width)
      .arg("scale_y", 0.5f * height)
      .buffer("grad_sum", grad_sum_, n_ * sizeof(float))
      .buffer("count", count_, n_ * sizeof(int))
      .buffer("max_radius", max_radius_, n_ * sizeof(int))
      .done();
  rt_.launch("free_densify_acc", k, cl::NDRange(n_), cl::NDRange(64));
}

FreeStepStats FreeTrainer::step(const std::function<void()>& before_rounds) {
  FreeStepStats st;
  const int it = iteration_;
  st.iteration = it + 1;
  st.view = view_for_iteration(it);
  st.sh_degree = active_sh_degree();
  const SceneView& view = scene_.views()[st.view];
  std::shared_ptr<const Image> target = scene_.image(st.view);
  const int w = view.camera.width, h = view.camera.height;
  activate(st.sh_degree);
  RenderSettings settings;
  const float bg = config_.white_background ? 1.f : 0.f;
  settings.background = {bg, bg, bg};
  settings.features = false;  // free Gaussians carry no semantic feature
  renderer_.forward(gaussians_, view.camera, settings);

  upload_target(*target, 1, target_planar_, target_dev_);
  image_loss_.enqueue(renderer_.device_rgb(), target_dev_, w, h, config_.lambda_ssim, &grad_rgb_dev_, nullptr,
                      ImageLayout::kPlanar);
  Renderer::DeviceOutputGrads og;
  og.rgb = &grad_rgb_dev_;
  renderer_.backward(og);
  const ImageLossResult lr = image_loss_.result();
  st.l1 = lr.l1;
  st.ssim = lr.ssim;
  st.psnr = lr.psnr();
  st.loss = lr.loss;

  const DeviceGaussianGrads rg = renderer_.device_grads();
  activate_backward(rg);

  const std::vector<GroupStep> updates = {{kMeans, &mean_, rg.means, position_lr(it)},
                                          {kScaling, &log_scale_, &v_log_scale_, config_.scaling_lr},
                                          {kRotation, &quat_, rg.quats, config_.rotation_lr},
                                          {kOpacity, &opacity_logit_, &v_opacity_logit_, config_.opacity_lr},
                                          {kShDc, &sh_dc_, &v_sh_dc_, config_.sh_dc_lr},
                                          {kShRest, &sh_rest_, &v_sh_rest_, config_.sh_rest_lr}};
  st.skipped = !groups_->step_if_finite(adam_, updates, st.iteration, st.loss, &st.nonfinite);
  if (!st.skipped) {
    if (st.iteration <= config_.effective_densify_until()) accumulate_densify_stats(rg, w, h);
  }
  if (before_rounds) before_rounds();
  iteration_ = it + 1;
  if (config_.densify_due(st.iteration)) densify(st);
  if (config_.reset_due(st.iteration)) {
    reset_opacity();
    st.opacity_reset = true;
  }
  return st;
}

void FreeTrainer::densify(FreeStepStats& st) {
  const FreeGaussians g = download();
  const DensifyStats stats = download_stats();
  const DensifyPlan plan = plan_densification(g, stats, config_, extent_, config_.prune_big_at(st.iteration));
  st.densified = true;
  st.cloned = plan.cloned;
  st.split = plan.split;
  st.pruned = plan.pruned;
  if (plan.after == 0)
    throw std::runtime_error("iteration " + std::to_string(st.iteration) + ": densification removed every Gaussian (" +
                             std::to_string(plan.pruned) + " pruned); lower --prune-opacity");
  const FreeGaussians next = apply_densification(g, plan, config_.seed, st.iteration);
  const std::vector<int> rows = plan.adam_rows();
  groups_->gather(rows, {});
  upload_params(next);
  reset_stats();
}

void FreeTrainer::reset_opacity() {
  std::vector<float> o;
  opacity_logit_.download(o, n_);
  cap_opacity_logits(o);
  opacity_logit_.upload(o);
  (*groups_)[kOpacity].zero_moments();
}

EvalStats FreeTrainer::evaluate(const std::vector<int>& views) {
  if (views.empty()) return {};
  activate(active_sh_degree());
  RenderSettings settings;
  const float bg = config_.white_background ? 1.f : 0.f;
  settings.background = {bg, bg, bg};
  return evaluate_views(renderer_, image_loss_, gaussians_, scene_, views, settings, config_.lambda_ssim);
}

void FreeTrainer::save(const std::string& model_dir) {
  fs::create_directories(model_dir);
  const GaussianSet set = download().to_stored_set(active_sh_degree());
  write_ply((fs::path(model_dir) / "point_cloud.ply").string(), set, false, PlyValues::stored);
}

}  // namespace ag2gs
