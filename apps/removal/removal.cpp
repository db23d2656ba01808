#include "apps/removal/removal.h"

#include <spdlog/spdlog.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <optional>
#include <stdexcept>
#include <utility>

#include "apps/backdrop.h"
#include "apps/removal/removal_settings.h"
#include "host/core/timing.h"
#include "host/render/renderer.h"
#include "host/render/sky.h"
#include "queries/query.h"  // gaussians_of_anchors
#include "train/train_common.h"
#include "train/train_config.h"

namespace ag2gs {
namespace {

// The opacity logit of a cleared child: sigmoid(-30) ~ 1e-13, below
// what the renderer draws.
constexpr float kClearedLogit = -30.f;

double seconds_since(std::chrono::steady_clock::time_point t0) { return ms_since(t0) / 1000.0; }

// What every step of a removal reads. The fine-tune continues with the
// model's own training settings when its archive records them.
struct Context {
  const RemovalRequest& req;
  const RemovalSettings& s;
  Renderer renderer;
  ModelBackdrop look;
  Sky& sky;
  const RenderSettings& render_settings;
  const TrainConfig& tc;
  std::function<void(const std::string&)> check_stop;

  Context(Runtime& rt, const RemovalRequest& r)
      : req(r),
        s(r.settings),
        renderer(rt),
        look(rt, *r.object.archive, r.object.model_file, "the fine-tune uses the default rates"),
        sky(look.sky),
        render_settings(look.settings),
        tc(look.train) {
    check_stop = r.check_stop ? r.check_stop : [](const std::string&) {};
  }
};

// Per training view, the hole and the target; and the fine-tune's targets:
// the inpainted image in the hole, the render after deletion on the object's
// other pixels (the model already shows what lies behind there), the photo
// elsewhere.
struct Holes {
  std::vector<std::pair<Camera, std::vector<float>>> tune_targets;
  std::vector<std::vector<uint8_t>> tune_holes;
  nlohmann::json views = nlohmann::json::array();
  size_t pixels = 0;
};

Holes find_holes(Context& c, HoleFinder& holes, HoleFootprint& footprint) {
  Holes out;
  Scene& scene = *c.req.object.scene;
  const std::vector<int> train_views = scene.train_views();
  const auto t0 = std::chrono::steady_clock::now();
  for (size_t i = 0; i < train_views.size(); ++i) {
    const SceneView& sv = scene.views()[train_views[i]];
    const ViewHole h =
        holes.find(c.renderer, sv.camera, c.s.holes, c.render_settings, c.sky.enabled() ? &c.sky : nullptr);
    const std::vector<float> target =
        c.req.inpainted ? c.req.inpainted(i) : inpaint_hole(h.rgb_after, h.hole, h.width, h.height, c.s.inpaint);
    if (c.req.on_view) c.req.on_view(i, h, target);
    if (c.s.fill_holes) footprint.add_view(sv.camera, h, target);
    if (c.s.iters > 0) {
      const std::vector<uint8_t> around = dilate_mask(h.object, h.width, h.height, c.s.holes.dilate);
      const std::shared_ptr<const Image> photo = scene.image(train_views[i]);
      std::vector<float> t = photo->rgb;
      for (size_t p = 0; p < h.hole.size(); ++p) {
        const std::vector<float>* from = h.hole[p] ? &target : around[p] ? &h.rgb_after : nullptr;
        if (from)
          for (int ch = 0; ch < 3; ++ch) t[3 * p + ch] = (*from)[3 * p + ch];
      }
      out.tune_targets.emplace_back(sv.camera, std::move(t));
      out.tune_holes.push_back(h.hole);
    }
    out.pixels += h.hole_pixels;
    out.views.push_back({{"view", sv.name},
                         {"object_pixels", h.object_pixels},
                         {"hole_pixels", h.hole_pixels},
                         {"hole_pixels_undilated", h.undilated_hole_pixels}});
    const double el = seconds_since(t0);
    spdlog::info("[{}/{}] {}: object {} px, hole {} px  {:.1f} s elapsed, ETA {:.1f} s", i + 1, train_views.size(),
                 sv.name, h.object_pixels, h.hole_pixels, el, el / (i + 1) * (train_views.size() - i - 1));
    c.check_stop("the hole search");
  }
  return out;
}

// Fine-tunes the fill and the kept anchors near it; returns the iterations
// run and the mean PSNR against the targets over the last report interval.
std::pair<int, double> fine_tune(Runtime& rt, Context& c, AnchorModel& result, const std::vector<uint8_t>& trainable,
                                 Holes& h) {
  const RemovalSettings& s = c.s;
  const Scene& scene = *c.req.object.scene;
  FineTuneConfig fc;
  fc.iterations = s.iters;
  fc.seed = s.seed;
  fc.sh_degree = c.req.object.sh_degree;
  fc.background = c.render_settings.background;
  fc.lambda_ssim = c.tc.lambda_ssim;
  const double extent =
      scene.bounds().camera_radius > 0 ? scene.bounds().camera_radius : scene.bounds().longest_extent();
  fc.offset_lr = c.tc.offset_lr_final * (c.tc.offset_lr_extent ? extent : 1.0);
  fc.scaling_lr = c.tc.scaling_lr;
  fc.rotation_lr = c.tc.rotation_lr;
  fc.opacity_lr = c.tc.opacity_lr;
  fc.sh_dc_lr = c.tc.sh_dc_lr;
  fc.sh_rest_lr = c.tc.sh_rest_lr;
  if (s.tune_to_fill) {
    // The holes' targets are the filled model's own render: one colour per
    // voxel, agreed by the views, so the fine-tune fits the seams around the
    // holes to the photos without undoing the fill.
    const GaussianSet filled = expand_reference(result, c.req.object.sh_degree);
    for (size_t i = 0; i < h.tune_targets.size(); ++i) {
      auto& [cam, t] = h.tune_targets[i];
      RenderOutput o = c.renderer.render(filled, cam, c.render_settings);
      if (c.sky.enabled()) composite_sky(c.renderer, c.sky, cam, o);
      for (size_t p = 0; p < h.tune_holes[i].size(); ++p)
        if (h.tune_holes[i][p])
          for (int ch = 0; ch < 3; ++ch) t[3 * p + ch] = o.rgb[3 * p + ch];
    }
  }
  FillTuner tuner(rt, result, trainable, fc, c.look.sky_coefficients ? &*c.look.sky_coefficients : nullptr);
  for (auto& [cam, t] : h.tune_targets) tuner.add_target(cam, std::move(t));
  h.tune_targets.clear();
  const auto t0 = std::chrono::steady_clock::now();
  const int every = std::max(1, std::min(100, s.iters / 5));
  double psnr_sum = 0, final_psnr = 0;
  int psnr_n = 0, done = 0;
  for (int it = 1; it <= s.iters; ++it) {
    const FillTuner::Step st = tuner.step();
    psnr_sum += st.psnr;
    ++psnr_n;
    done = it;
    if (it % every == 0 || it == s.iters) {
      const double el = seconds_since(t0);
      final_psnr = psnr_sum / psnr_n;
      spdlog::info(
          "fine-tune it {:5d}/{}  loss {:.5f}  PSNR {:.2f} dB (against the targets, mean of the last {})  "
          "{:.1f} s elapsed, ETA {}",
          it, s.iters, st.loss, final_psnr, psnr_n, el, fmt_duration(el / it * (s.iters - it)));
      psnr_sum = 0;
      psnr_n = 0;
    }
    c.check_stop("the fine-tune");
  }
  result = tuner.model();
  return {done, final_psnr};
}

// Fill anchors that found nothing to show go again; returns how many stay.
size_t drop_empty_fill(AnchorModel& result, const FillResult& fill, float prune_opacity, std::vector<int>& source) {
  size_t kept = fill.added.size();
  if (fill.added.empty()) return kept;
  std::vector<uint8_t> keep(result.size(), 1);
  const int K = result.children();
  for (int id : fill.added) {
    double mean = 0;
    for (int i = 0; i < K; ++i)
      mean += 1.0 / (1.0 + std::exp(-result.opacity_logit()[static_cast<size_t>(id) * K + i]));
    if (prune_opacity > 0 && mean / K < prune_opacity) {
      keep[id] = 0;
      --kept;
    }
  }
  if (kept != fill.added.size()) {
    const std::vector<int> rows = result.remove_anchors(keep);
    std::vector<int> src;
    for (int r : rows) src.push_back(source[r]);
    source = std::move(src);
  }
  return kept;
}

nlohmann::json or_null(bool on, const nlohmann::json& v) { return on ? v : nlohmann::json(nullptr); }

}  // namespace

void RemovalSettings::validate() const {
  if (const std::string p = settings_problem(removal_settings(), *this); !p.empty()) throw std::invalid_argument(p);
  holes.validate();
  fill.validate();
  if (!fill_holes && iters > 0)
    throw std::invalid_argument("--no-fill deletes only; --iters " + std::to_string(iters) +
                                " would fine-tune a fill it does not place (leave one of them out)");
}

nlohmann::json RemovalSettings::to_json() const {
  return settings_to_json(removal_settings(), *this);
}

RemovalResult remove_object(Runtime& rt, const RemovalRequest& req) {
  req.object.check("remove_object");
  const RemovalSettings& s = req.settings;
  s.validate();
  const AnchorModel& model = *req.object.model;
  const size_t n_sel =
      static_cast<size_t>(std::count(req.object.selected.begin(), req.object.selected.end(), uint8_t{1}));
  if (n_sel == 0) throw std::invalid_argument("remove_object: nothing is selected");
  if (n_sel == model.size())
    throw std::runtime_error("the query selected all " + std::to_string(model.size()) +
                             " anchors: removing them would leave an empty model");
  Context c(rt, req);
  const std::vector<uint8_t>& in_sel = req.object.selected;

  // Anchors the object hid from every photo go with it; children of kept
  // anchors that show the object are cleared (opacity 0).
  std::vector<int> hidden;
  const auto t_hidden = std::chrono::steady_clock::now();
  if (s.clear_hidden) {
    std::vector<Camera> cameras;
    for (int v : req.object.scene->train_views()) cameras.push_back(req.object.scene->views()[v].camera);
    spdlog::info("which kept anchors near the object do the {} training views see? (two renders a view)",
                 cameras.size());
    hidden = hidden_anchors(c.renderer, model, req.object.sh_degree, in_sel, cameras, c.render_settings, s.stray_reach,
                            s.hidden_fraction);
    spdlog::info("{} kept anchors near the object are seen only through it: removed with it ({:.1f} s)",
                 hidden.size(), seconds_since(t_hidden));
  }
  const double hidden_s = seconds_since(t_hidden);
  std::vector<uint8_t> gone = in_sel;
  for (int h : hidden) gone[h] = 1;
  const size_t n_gone = n_sel + hidden.size();
  AnchorModel cleaned = model;
  std::vector<size_t> strays;
  if (s.clear_stray) strays = stray_children(model, gone, s.stray_colour, s.stray_reach);
  for (size_t g : strays) cleaned.opacity_logit()[g] = kClearedLogit;
  if (!strays.empty())
    spdlog::info("{} children of kept anchors sit among the object's Gaussians with its colour: cleared",
                 strays.size());
  const GaussianSet removed = gaussians_of_anchors(model, req.object.sh_degree, in_sel, true);
  const GaussianSet kept = gaussians_of_anchors(cleaned, req.object.sh_degree, gone, false);
  HoleFinder holes(kept, removed);
  std::vector<uint8_t> keep(model.size());
  for (size_t k = 0; k < keep.size(); ++k) keep[k] = !gone[k];
  RemovalResult out;
  out.model = cleaned;
  std::vector<int> source = out.model.remove_anchors(keep);  // new id -> old id
  HoleFootprint footprint(out.model.grid(), holes.diameter(), s.holes.behind, s.fill.max_alpha);
  const auto t_holes = std::chrono::steady_clock::now();
  Holes found = find_holes(c, holes, footprint);
  const double holes_s = seconds_since(t_holes);

  // ---- fill anchors and the fine-tune
  const auto t_fill = std::chrono::steady_clock::now();
  out.kept_anchors = out.model.size();
  FillResult fill;
  fill.trainable.assign(out.model.size(), 0);
  if (s.fill_holes) {
    fill = add_fill_anchors(out.model, footprint, s.fill, n_gone, s.seed);
    for (int p : fill.parent) source.push_back(source[p]);
    spdlog::info(
        "fill: {} anchors ({} Gaussians) where {} hole pixels of {} views meet the surfaces around them "
        "({} voxels with enough views); {} kept anchors lie near them",
        fill.added.size(), fill.added.size() * static_cast<size_t>(out.model.children()), footprint.points(),
        footprint.views_with_holes(), fill.candidates, fill.trainable_kept);
  }
  const size_t trainable = static_cast<size_t>(std::count(fill.trainable.begin(), fill.trainable.end(), uint8_t{1}));
  std::pair<int, double> tuned{0, 0.0};
  if (s.iters > 0 && trainable > 0)
    tuned = fine_tune(rt, c, out.model, fill.trainable, found);
  else if (s.iters > 0)
    spdlog::info("fine-tune: nothing to tune (no fill anchor and no kept anchor near the holes)");
  out.added_anchors = drop_empty_fill(out.model, fill, s.fill.prune_opacity, source);
  const double fill_s = seconds_since(t_fill);
  out.archive = archive_after_removal(*req.object.archive, out.model, source);

  // ---- the record
  // The kept anchors the fine-tune may change (their ids in the new model;
  // every other kept anchor has its bytes from the input model).
  std::vector<int> tuned_ids;
  if (tuned.first > 0)
    for (size_t k = 0; k < out.kept_anchors; ++k)
      if (fill.trainable[k]) tuned_ids.push_back(static_cast<int>(k));
  // The cleared children as (anchor id in the new model, child).
  std::vector<int> new_id(model.size(), -1);
  for (size_t r = 0; r < out.kept_anchors; ++r) new_id[source[r]] = static_cast<int>(r);
  nlohmann::json cleared = nlohmann::json::array();
  for (size_t g : strays) cleared.push_back({new_id[g / model.children()], static_cast<int>(g % model.children())});
  const size_t K = static_cast<size_t>(model.children());
  nlohmann::json& r = out.report;
  r["stray_children_cleared"] = cleared;
  r["hidden_anchors_removed"] = hidden;  // ids in the input model
  r["anchors_removed"] = n_gone;
  r["gaussians_removed"] = n_gone * K;
  r["anchors_kept"] = out.kept_anchors;
  r["gaussians_kept"] = out.kept_anchors * K;
  r["anchors_added"] = out.added_anchors;
  r["gaussians_added"] = out.added_anchors * K;
  r["anchors"] = out.model.size();
  r["gaussians"] = out.model.gaussians();
  r["iterations"] = tuned.first;
  r["seed"] = s.seed;
  r["fill"] = {{"enabled", s.fill_holes},
               {"footprint_points", footprint.points()},
               {"footprint_views", footprint.views_with_holes()},
               {"candidates", fill.candidates},
               {"anchors_placed", fill.added.size()},
               {"anchors_pruned", fill.added.size() - out.added_anchors},
               {"kept_anchors_near", fill.trainable_kept},
               {"kept_anchors_tuned", tuned_ids.size()},
               {"kept_anchors_tuned_ids", tuned_ids},
               {"min_views", s.fill.min_views},
               {"near_voxels", s.fill.near},
               {"start_opacity", s.fill.opacity},
               {"max_alpha", s.fill.max_alpha},
               {"colour_quantile", s.fill.colour_quantile},
               {"stray_colour", or_null(s.clear_stray, s.stray_colour)},
               {"stray_reach", or_null(s.clear_stray, s.stray_reach)},
               {"hidden_fraction", or_null(s.clear_hidden, s.hidden_fraction)},
               {"tune_targets", s.tune_to_fill ? "fill" : "inpainted"},
               {"final_target_psnr", tuned.second}};
  r["holes"] = {{"object_weight", s.holes.object_weight},
                {"alpha_min", s.holes.alpha_min},
                {"behind_diameters", s.holes.behind},
                {"object_diameter", holes.diameter()},
                {"dilate", s.holes.dilate},
                {"pixels", found.pixels},
                {"views", found.views}};
  r["seconds"] = {{"hidden", hidden_s}, {"holes", holes_s}, {"fill_and_fine_tune", fill_s}};
  return out;
}

ModelArchive archive_after_removal(const ModelArchive& in, const AnchorModel& result, const std::vector<int>& source) {
  ModelArchive out;
  result.to_archive(out);
  if (in.meta.contains("train")) out.meta["train"] = in.meta["train"];
  if (in.has("sky/sh")) out.put_tensor("sky/sh", in.tensor("sky/sh"));
  if (in.meta.contains("clusters") && in.has("clusters/anchor_cluster")) {
    const std::vector<int32_t> ids = in.get<int32_t>("clusters/anchor_cluster");
    std::vector<int32_t> size = in.get<int32_t>("clusters/size");
    std::vector<int32_t> kept_ids;
    size_t skipped = 0;
    std::fill(size.begin(), size.end(), 0);
    for (int a : source) {
      const int32_t id = ids.at(a);
      kept_ids.push_back(id);
      if (id >= 0)
        ++size[id];
      else
        ++skipped;
    }
    out.put("clusters/anchor_cluster", kept_ids, {static_cast<int64_t>(kept_ids.size())});
    out.put("clusters/size", size, {static_cast<int64_t>(size.size())});
    out.meta["clusters"] = in.meta["clusters"];
    out.meta["clusters"]["skipped_anchors"] = skipped;
    for (const char* name : {"clusters/language", "clusters/language_matches"})
      if (in.has(name)) out.put_tensor(name, in.tensor(name));
    if (in.meta.contains("language")) out.meta["language"] = in.meta["language"];
  }
  return out;
}

}  // namespace ag2gs
