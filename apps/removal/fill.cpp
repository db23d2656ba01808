#include "apps/removal/fill.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <opencv2/imgproc.hpp>
#include <opencv2/photo.hpp>
#include <set>
#include <stdexcept>

#include "host/core/counter_rng.h"
#include "host/core/gaussians.h"
#include "host/core/quantile.h"
#include "host/core/scalar_math.h"
#include "train/train_common.h"

namespace ag2gs {
namespace {}  // namespace

void FillSettings::validate() const {
  if (min_views < 1) throw std::invalid_argument("fill: min_views must be >= 1, got " + std::to_string(min_views));
  if (!(std::isfinite(opacity) && opacity > 0.f && opacity < 1.f))
    throw std::invalid_argument("fill: opacity must be in (0, 1), got " + std::to_string(opacity));
  if (!(std::isfinite(near) && near >= 0.f))
    throw std::invalid_argument("fill: near must be >= 0, got " + std::to_string(near));
  if (!(std::isfinite(prune_opacity) && prune_opacity >= 0.f && prune_opacity < 1.f))
    throw std::invalid_argument("fill: prune_opacity must be in [0, 1), got " + std::to_string(prune_opacity));
  if (!(std::isfinite(max_alpha) && max_alpha > 0.f && max_alpha <= 1.f))
    throw std::invalid_argument("--fill-alpha must be in (0, 1], got " + std::to_string(max_alpha));
  if (!(std::isfinite(colour_quantile) && colour_quantile >= 0.f && colour_quantile <= 1.f))
    throw std::invalid_argument("--fill-quantile must be in [0, 1], got " + std::to_string(colour_quantile));
}

// ------------------------------------------------------------------ footprint
HoleFootprint::HoleFootprint(const VoxelGrid& grid, double object_diameter, float behind, float max_alpha)
    : grid_(grid), diameter_(object_diameter), behind_(behind), max_alpha_(max_alpha) {}

void HoleFootprint::add_view(const Camera& cam, const ViewHole& h, const std::vector<float>& target) {
  const int w = h.width, ht = h.height;
  const size_t npix = static_cast<size_t>(w) * ht;
  if (h.hole_pixels == 0) return;
  if (target.size() != npix * 3 || h.depth_after.size() != npix)
    throw std::invalid_argument("HoleFootprint::add_view: image sizes disagree with the hole's");
  ++views_;
  // The depth the hole's surroundings continue with: the kept model's depth
  // where it is opaque and outside the hole, inpainted across the rest as
  // inverse depth (which is affine in the pixel coordinates on a plane, so a
  // smooth fill continues a floor or a wall as the plane itself). Open
  // pixels (alpha below 0.1: sky or background) count as surfaces at
  // infinity, inverse depth 0, so a hole bordering on the sky continues it.
  cv::Mat inv_depth(ht, w, CV_32FC1), unknown(ht, w, CV_8UC1);
  double deepest = 0;  // the farthest opaque surface of the view
  for (size_t p = 0; p < npix; ++p) {
    const float a = h.alpha_after[p];
    const bool opaque = a >= 0.5f && h.depth_after[p] > 0.f, open = a < 0.1f;
    if (opaque) deepest = std::max(deepest, static_cast<double>(h.depth_after[p]));
    const bool known = !h.hole[p] && (opaque || open);
    reinterpret_cast<float*>(inv_depth.data)[p] = known && opaque ? 1.f / h.depth_after[p] : 0.f;
    unknown.data[p] = known ? 0 : 255;
  }
  cv::Mat filled;
  cv::inpaint(inv_depth, unknown, filled, 3.0, cv::INPAINT_NS);
  const Eigen::Matrix3d Rt = cam.R.transpose();
  const int finest = grid_.layers - 1;
  const double far = behind_ * diameter_;
  for (int y = 0; y < ht; ++y)
    for (int x = 0; x < w; ++x) {
      const size_t p = static_cast<size_t>(y) * w + x;
      if (!h.hole[p]) continue;
      // Pixels that show enough of the kept model (alpha >= max_alpha) and
      // not a far surface through it are left to it: the fill takes the
      // open part of the hole.
      const double zo = h.object_depth[p];
      if (h.alpha_after[p] >= max_alpha_ && !(zo > 0 && h.depth_after[p] > zo + far)) continue;
      const double inv = reinterpret_cast<const float*>(filled.data)[p];
      if (!(std::isfinite(inv) && inv > 0)) continue;
      double z = 1.0 / inv;
      // Behind the object's own surface. A surface continued to beyond
      // `behind` diameters behind it (the far wall the hole rule rejected,
      // or the sky) gets no fill: the hole shows what lies there.
      if (zo > 0) {
        if (z > zo + far) continue;
        z = std::max(z, zo);
      } else if (z > deepest) {
        continue;  // a rim pixel continuing the sky
      }
      const Eigen::Vector3d pc((x + 0.5 - cam.cx) / cam.fx * z, (y + 0.5 - cam.cy) / cam.fy * z, z);
      const Eigen::Vector3d pw = Rt * (pc - cam.t);
      const Eigen::Vector3i c = grid_.cell_of(finest, pw);
      if ((c.array().abs() >= kMaxAnchorCell).any()) continue;
      Cell& cell = cells_[anchor_voxel_key(finest, c)];
      for (int k = 0; k < 3; ++k) cell.sum[k] += pw[k];
      ++cell.points;
      if (cell.last_view != views_) {
        cell.last_view = views_;
        cell.per_view.push_back({0, 0, 0, 0});
      }
      for (int k = 0; k < 3; ++k) cell.per_view.back()[k] += target[3 * p + k];
      cell.per_view.back()[3] += 1;
      ++points_;
    }
}

// ------------------------------------------------------------------ fill anchors
FillResult add_fill_anchors(AnchorModel& model, const HoleFootprint& footprint, const FillSettings& settings,
                            size_t removed_anchors, uint64_t seed) {
  settings.validate();
  FillResult r;
  const size_t kept = model.size();
  const std::vector<float>& pos = model.pos();
  const std::vector<float>& edge = model.voxel();
  const VoxelGrid& grid = model.grid();
  auto nearest = [&](const Eigen::Vector3d& p) {
    int best = -1;
    double best_d = std::numeric_limits<double>::infinity();
    for (size_t a = 0; a < kept; ++a) {
      const double dx = pos[3 * a] - p.x(), dy = pos[3 * a + 1] - p.y(), dz = pos[3 * a + 2] - p.z();
      const double d = dx * dx + dy * dy + dz * dz;
      if (d < best_d) {
        best_d = d;
        best = static_cast<int>(a);
      }
    }
    return best;
  };
  // Footprint voxels regrouped at the layer of their nearest kept anchor.
  struct Candidate {
    int layer = 0;
    Eigen::Vector3i cell;
    int parent = -1;
    std::vector<std::array<double, 3>> estimates;  // one colour per footprint voxel and view that reaches it
    size_t points = 0;
    int views = 0;  // the most views of one of its footprint voxels
  };
  std::map<uint64_t, Candidate> cand;
  std::vector<Eigen::Vector3d> points;  // footprint voxel means, for the trainable test
  const int min_views = footprint.views_with_holes() == 1 ? 1 : settings.min_views;
  for (const auto& [key, c] : footprint.cells()) {
    const Eigen::Vector3d p(c.sum[0] / c.points, c.sum[1] / c.points, c.sum[2] / c.points);
    points.push_back(p);
    if (kept == 0) continue;
    const int a = nearest(p);
    const int layer = model.layer()[a];
    const Eigen::Vector3i cell = grid.cell_of(layer, p);
    if (model.find(layer, cell) >= 0) continue;  // the surface has an anchor there already
    Candidate& d = cand[anchor_voxel_key(layer, cell)];
    if (d.points == 0) {
      d.layer = layer;
      d.cell = cell;
      d.parent = a;
    }
    for (const auto& v : c.per_view) d.estimates.push_back({v[0] / v[3], v[1] / v[3], v[2] / v[3]});
    d.points += c.points;
    d.views = std::max(d.views, c.views());
  }
  std::vector<const Candidate*> order;
  for (const auto& [key, d] : cand)
    if (d.views >= min_views) order.push_back(&d);
  r.candidates = order.size();
  const size_t cap = settings.max_anchors > 0 ? settings.max_anchors : removed_anchors;
  if (order.size() > cap) {
    // The best-supported voxels; ties in key order (stable).
    std::stable_sort(order.begin(), order.end(),
                     [](const Candidate* x, const Candidate* y) { return x->points > y->points; });
    order.resize(cap);
    std::sort(order.begin(), order.end(), [&](const Candidate* x, const Candidate* y) {
      return anchor_voxel_key(x->layer, x->cell) < anchor_voxel_key(y->layer, y->cell);
    });
  }
  const int K = model.children();
  const float op = static_cast<float>(logit(settings.opacity));
  // The estimate at the colour quantile by brightness (ties in the order the
  // views came: stable).
  auto fill_colour = [&](const Candidate& d) {
    std::vector<std::pair<double, size_t>> bright;
    for (size_t i = 0; i < d.estimates.size(); ++i)
      bright.push_back({d.estimates[i][0] + d.estimates[i][1] + d.estimates[i][2], i});
    std::sort(bright.begin(), bright.end());
    return d.estimates[bright[quantile_rank(bright.size(), settings.colour_quantile)].second];
  };
  for (const Candidate* d : order) {
    const int id = model.add_anchor(d->layer, d->cell, static_cast<int64_t>(d->parent) * K, seed);
    if (id < 0) continue;
    const std::array<double, 3> colour = fill_colour(*d);
    for (int i = 0; i < K; ++i) {
      const size_t g = static_cast<size_t>(id) * K + i;
      float* sh = model.sh().data() + g * kAnchorShCoeffs * 3;
      std::fill(sh, sh + kAnchorShCoeffs * 3, 0.f);
      for (int k = 0; k < 3; ++k) sh[k] = static_cast<float>((colour[k] - 0.5) / kShC0);
      model.opacity_logit()[g] = op;
    }
    r.added.push_back(id);
    r.parent.push_back(d->parent);
  }
  // Trainable: the fill, and the kept anchors within `near` of their own
  // voxel edges of a footprint point.
  r.trainable.assign(model.size(), 0);
  for (int id : r.added) r.trainable[id] = 1;
  if (!points.empty()) {
    // Points hashed on a grid of the largest reach, so each anchor looks at
    // the 27 cells around its own.
    double reach = 0;
    for (size_t a = 0; a < kept; ++a) reach = std::max(reach, static_cast<double>(settings.near * edge[a]));
    if (reach > 0) {
      std::map<std::array<int64_t, 3>, std::vector<int>> hash;
      auto key_of = [&](const Eigen::Vector3d& p) {
        return std::array<int64_t, 3>{static_cast<int64_t>(std::floor(p.x() / reach)),
                                      static_cast<int64_t>(std::floor(p.y() / reach)),
                                      static_cast<int64_t>(std::floor(p.z() / reach))};
      };
      for (size_t i = 0; i < points.size(); ++i) hash[key_of(points[i])].push_back(static_cast<int>(i));
      for (size_t a = 0; a < kept; ++a) {
        const Eigen::Vector3d q(pos[3 * a], pos[3 * a + 1], pos[3 * a + 2]);
        const double r2 = std::pow(settings.near * edge[a], 2.0);
        const std::array<int64_t, 3> k = key_of(q);
        bool hit = false;
        for (int dx = -1; dx <= 1 && !hit; ++dx)
          for (int dy = -1; dy <= 1 && !hit; ++dy)
            for (int dz = -1; dz <= 1 && !hit; ++dz) {
              auto it = hash.find({k[0] + dx, k[1] + dy, k[2] + dz});
              if (it == hash.end()) continue;
              for (int i : it->second)
                if ((points[i] - q).squaredNorm() <= r2) {
                  hit = true;
                  break;
                }
            }
        if (hit) {
          r.trainable[a] = 1;
          ++r.trainable_kept;
        }
      }
    }
  }
  return r;
}

// ------------------------------------------------------------------ stray children
std::vector<size_t> stray_children(const AnchorModel& model, const std::vector<uint8_t>& selected, float max_colour,
                                   int reach) {
  if (selected.size() != model.size())
    throw std::invalid_argument("stray_children: " + std::to_string(selected.size()) + " flags for " +
                                std::to_string(model.size()) + " anchors");
  if (reach < 0 || reach > 16) throw std::invalid_argument("stray_children: reach must be in 0..16 voxels");
  const GaussianSet g = expand_reference(model, 0);
  const int K = model.children();
  const int finest = model.grid().layers - 1;
  const size_t coeffs = static_cast<size_t>(g.sh_coeffs()) * 3;
  auto cell_of = [&](size_t i) {
    return model.grid().cell_of(finest, Eigen::Vector3d(g.means[3 * i], g.means[3 * i + 1], g.means[3 * i + 2]));
  };
  auto colour = [&](size_t i, int c) { return 0.5 + kShC0 * g.sh[i * coeffs + c]; };
  auto visible = [&](size_t i) { return g.opacities[i] >= kStrayMinOpacity; };
  struct Sum {
    double c[3] = {0, 0, 0};
    size_t n = 0;
    void add(const Sum& o) {
      for (int k = 0; k < 3; ++k) c[k] += o.c[k];
      n += o.n;
    }
  };
  // Colour sums of the visible Gaussians per finest voxel, removed and kept apart.
  std::map<uint64_t, Sum> removed, kept;
  for (size_t i = 0; i < g.size(); ++i) {
    if (!visible(i)) continue;
    Sum& s = (selected[i / K] ? removed : kept)[anchor_voxel_key(finest, cell_of(i))];
    for (int c = 0; c < 3; ++c) s.c[c] += colour(i, c);
    ++s.n;
  }
  auto mean_abs = [&](size_t i, const Sum& s) {
    double d = 0;
    for (int c = 0; c < 3; ++c) d += std::abs(colour(i, c) - s.c[c] / static_cast<double>(s.n));
    return d / 3;
  };
  // The sums over a voxel's neighbourhood, once per voxel: its children share them.
  std::map<uint64_t, std::pair<Sum, Sum>> hoods;
  auto hood_of = [&](const Eigen::Vector3i& c0) -> const std::pair<Sum, Sum>& {
    auto [it, fresh] = hoods.try_emplace(anchor_voxel_key(finest, c0));
    if (!fresh) return it->second;
    for (int dx = -reach; dx <= reach; ++dx)
      for (int dy = -reach; dy <= reach; ++dy)
        for (int dz = -reach; dz <= reach; ++dz) {
          const uint64_t key = anchor_voxel_key(finest, c0 + Eigen::Vector3i(dx, dy, dz));
          if (auto r = removed.find(key); r != removed.end()) it->second.first.add(r->second);
          if (auto k = kept.find(key); k != kept.end()) it->second.second.add(k->second);
        }
    return it->second;
  };
  std::vector<size_t> out;
  for (size_t i = 0; i < g.size(); ++i) {
    if (selected[i / K] || !visible(i)) continue;
    const auto& [near_removed, hood_kept] = hood_of(cell_of(i));
    if (near_removed.n == 0) continue;
    Sum near_kept = hood_kept;
    for (int c = 0; c < 3; ++c) near_kept.c[c] -= colour(i, c);  // the others, not itself
    --near_kept.n;
    const double to_removed = mean_abs(i, near_removed);
    if (to_removed > max_colour) continue;
    if (near_kept.n > 0 && !(to_removed < mean_abs(i, near_kept))) continue;
    out.push_back(i);
  }
  return out;
}

std::vector<double> seen_weight(Renderer& renderer, const GaussianSet& set, const std::vector<Camera>& cameras,
                                const RenderSettings& settings, const std::vector<uint8_t>* object) {
  std::vector<double> seen(set.size(), 0.0);
  if (set.size() == 0) return seen;
  if (object && object->size() != set.size())
    throw std::invalid_argument("seen_weight: " + std::to_string(object->size()) + " object flags for " +
                                std::to_string(set.size()) + " Gaussians");
  RenderSettings rs = settings;
  rs.features = true;
  rs.sh_degree = 0;  // no colour is read: the SH terms past the constant one would be wasted
  // The weights do not depend on the features: they carry the object's flag
  // (its blending weight per pixel) when there is one.
  GaussianSet flagged = set;
  for (size_t i = 0; i < set.size(); ++i)
    for (int k = 0; k < 3; ++k) flagged.features[3 * i + k] = k == 0 && object && (*object)[i] ? 1.f : 0.f;
  std::vector<float> sums;
  for (const Camera& cam : cameras) {
    const RenderOutput out = renderer.render(flagged, cam, rs);
    // The weights of the pixels the object does not own: the feature
    // channel's gradient for this upstream plane, without a backward pass.
    std::vector<float> up(out.feature.size() / 3);
    for (size_t p = 0; p < up.size(); ++p) up[p] = object && out.feature[3 * p] > 0.5f ? 0.f : 1.f;
    renderer.blend_weights(up);
    renderer.device_weight_sums().download(sums, set.size());
    for (size_t i = 0; i < seen.size(); ++i) seen[i] += sums[i];
  }
  return seen;
}

std::vector<int> hidden_anchors(Renderer& renderer, const AnchorModel& model, int sh_degree,
                                const std::vector<uint8_t>& selected, const std::vector<Camera>& cameras,
                                const RenderSettings& settings, int reach, double max_fraction) {
  if (selected.size() != model.size())
    throw std::invalid_argument("hidden_anchors: " + std::to_string(selected.size()) + " flags for " +
                                std::to_string(model.size()) + " anchors");
  if (reach < 0 || reach > 16) throw std::invalid_argument("hidden_anchors: reach must be in 0..16 voxels");
  const GaussianSet g = expand_reference(model, sh_degree);
  const int K = model.children();
  const int finest = model.grid().layers - 1;
  auto cell_of = [&](size_t i) {
    return model.grid().cell_of(finest, Eigen::Vector3d(g.means[3 * i], g.means[3 * i + 1], g.means[3 * i + 2]));
  };
  auto visible = [&](size_t i) { return g.opacities[i] >= kStrayMinOpacity; };
  std::set<uint64_t> object;
  for (size_t i = 0; i < g.size(); ++i)
    if (selected[i / K] && visible(i)) object.insert(anchor_voxel_key(finest, cell_of(i)));
  auto near_object = [&](const Eigen::Vector3i& c0) {
    for (int dx = -reach; dx <= reach; ++dx)
      for (int dy = -reach; dy <= reach; ++dy)
        for (int dz = -reach; dz <= reach; ++dz)
          if (object.count(anchor_voxel_key(finest, c0 + Eigen::Vector3i(dx, dy, dz)))) return true;
    return false;
  };
  std::vector<size_t> candidates;
  for (size_t i = 0; i < g.size(); ++i)
    if (!selected[i / K] && visible(i) && near_object(cell_of(i))) candidates.push_back(i);
  if (candidates.empty()) return {};
  // Rendered with the object's Gaussians only (what else hides a candidate
  // only makes it look more seen here, never less), then alone.
  std::vector<size_t> rows;
  std::vector<uint8_t> object_rows;
  for (size_t i = 0; i < g.size(); ++i)
    if (selected[i / K]) {
      rows.push_back(i);
      object_rows.push_back(1);
    }
  rows.insert(rows.end(), candidates.begin(), candidates.end());
  object_rows.resize(rows.size(), 0);
  const size_t first = rows.size() - candidates.size();
  const std::vector<double> outside = seen_weight(renderer, g.rows(rows), cameras, settings, &object_rows);
  const std::vector<double> alone = seen_weight(renderer, g.rows(candidates), cameras, settings);
  std::vector<uint8_t> hidden(g.size(), 0);
  for (size_t k = 0; k < candidates.size(); ++k) hidden[candidates[k]] = outside[first + k] < max_fraction * alone[k];
  // Only anchors the photos do not see at all: a child hidden beside a seen
  // sibling belongs to a surface the photos show (a neighbour's face that
  // the object hid), and its anchor's feature and colours were trained.
  std::vector<int> out;
  for (size_t a = 0; a < model.size(); ++a) {
    if (selected[a]) continue;
    bool any = false, all = true;
    for (int i = 0; i < K; ++i) {
      const size_t row = a * K + i;
      if (!visible(row)) continue;
      any = any || hidden[row];
      all = all && hidden[row];
    }
    if (any && all) out.push_back(static_cast<int>(a));
  }
  return out;
}

// ------------------------------------------------------------------ fine-tune
FillTuner::FillTuner(Runtime& rt, const AnchorModel& model, const std::vector<uint8_t>& trainable,
                     const FineTuneConfig& config, const std::vector<float>* sky_coefficients)
    : rt_(rt),
      config_(config),
      model_(model),
      anchors_(rt),
      grads_(rt),
      gaussians_(rt),
      expander_(rt),
      renderer_(rt),
      loss_(rt),
      sky_(rt),
      adam_(rt) {
  if (trainable.size() != model.size())
    throw std::invalid_argument("FillTuner: the trainable mask has " + std::to_string(trainable.size()) +
                                " entries for " + std::to_string(model.size()) + " anchors");
  if (config.iterations < 0) throw std::invalid_argument("FillTuner: iterations must be >= 0");
  anchors_.upload(model_);
  const size_t n = model_.gaussians();
  groups_ = std::make_unique<ParamGroups>(
      rt_,
      std::vector<ParamGroupSpec>{
          {"offset", 3}, {"scaling", 3}, {"rotation", 4}, {"opacity", 1}, {"sh_dc", 3}, {"sh_rest", 3 * kShRestCoeffs}},
      n, model_.size());
  std::vector<int32_t> on(n);
  const int K = model_.children();
  for (size_t g = 0; g < n; ++g) on[g] = trainable[g / K] ? 1 : 0;
  for (DeviceBuffer* b : {&rows_on_, &target_dev_, &grad_rgb_, &grad_alpha_}) b->bind(&rt_);
  rows_on_.upload(on);
  if (sky_coefficients && !sky_coefficients->empty())
    sky_.set(sky_degree_for(sky_coefficients->size()), *sky_coefficients);
}

FillTuner::~FillTuner() = default;

void FillTuner::add_target(const Camera& camera, std::vector<float> rgb) {
  if (rgb.size() != static_cast<size_t>(camera.width) * camera.height * 3)
    throw std::invalid_argument("FillTuner::add_target: " + std::to_string(rgb.size()) + " values for a " +
                                std::to_string(camera.width) + "x" + std::to_string(camera.height) + " view");
  cameras_.push_back(camera);
  Image img;
  img.width = camera.width;
  img.height = camera.height;
  img.rgb = std::move(rgb);
  targets_.push_back(std::move(img));
}

FillTuner::Step FillTuner::step() {
  if (targets_.empty()) throw std::logic_error("FillTuner::step: no targets");
  Step st;
  std::vector<int> ids(targets_.size());
  for (size_t i = 0; i < ids.size(); ++i) ids[i] = static_cast<int>(i);
  const int v = epoch_shuffled_view(ids, config_.seed, iteration_);
  const Camera& cam = cameras_[v];
  RenderSettings settings;
  settings.background = sky_.enabled() ? std::array<float, 3>{0.f, 0.f, 0.f} : config_.background;
  settings.features = false;
  expander_.forward(anchors_, gaussians_, config_.sh_degree);
  renderer_.forward(gaussians_, cam, settings);
  const DeviceBuffer& rgb =
      sky_.enabled() ? sky_.compose(renderer_.device_rgb(), renderer_.device_alpha(), cam) : renderer_.device_rgb();
  upload_target(targets_[v], 1, planar_, target_dev_);
  loss_.enqueue(rgb, target_dev_, cam.width, cam.height, config_.lambda_ssim, &grad_rgb_, nullptr,
                ImageLayout::kPlanar);
  Renderer::DeviceOutputGrads og;
  og.rgb = &grad_rgb_;
  if (sky_.enabled()) {
    // The sky stays as trained; its composite still passes a gradient to alpha.
    sky_.backward(grad_rgb_, renderer_.device_alpha(), cam, grad_alpha_, false);
    og.alpha = &grad_alpha_;
  }
  renderer_.backward(og);
  expander_.backward(anchors_, renderer_.device_grads(), grads_);
  const ImageLossResult lr = loss_.result();
  st.iteration = ++iteration_;
  st.loss = lr.loss;
  st.psnr = lr.psnr();
  const std::vector<GroupStep> updates = {
      {0, &anchors_.offset, &grads_.offset, config_.offset_lr, &rows_on_},
      {1, &anchors_.scale_logit, &grads_.scale_logit, config_.scaling_lr, &rows_on_},
      {2, &anchors_.quat, &grads_.quat, config_.rotation_lr, &rows_on_},
      {3, &anchors_.opacity_logit, &grads_.opacity_logit, config_.opacity_lr, &rows_on_},
      {4, &anchors_.sh_dc, &grads_.sh_dc, config_.sh_dc_lr, &rows_on_},
      {5, &anchors_.sh_rest, &grads_.sh_rest, config_.sh_rest_lr, &rows_on_}};
  uint64_t nonfinite = 0;
  st.skipped = !groups_->step_if_finite(adam_, updates, st.iteration, st.loss, &nonfinite);
  return st;
}

AnchorModel FillTuner::model() {
  anchors_.download(model_);
  return model_;
}

}  // namespace ag2gs
