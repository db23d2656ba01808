#include "apps/removal/removal_settings.h"

#include <stdexcept>
#include <string>

#include "apps/removal/removal.h"

namespace ag2gs {
namespace {

template <class T>
constexpr auto field = &RemovalSetting::of<T>;  // a row's field from a lambda
using C = RemovalSettings;

const char* inpaint_name(InpaintMethod m) {
  return m == InpaintMethod::kTelea ? "telea" : m == InpaintMethod::kNavierStokes ? "ns" : "none";
}

// --inpaint: the method by name (parse_inpaint_method names the choices).
RemovalSetting::Custom inpaint_field() {
  return {[](const C& c) { return nlohmann::json(inpaint_name(c.inpaint)); },
          [](C& c, const nlohmann::json& v) { c.inpaint = parse_inpaint_method(v.get<std::string>()); },
          [](C& c, const std::string& text) { c.inpaint = parse_inpaint_method(text); }};
}

// --tune-targets: a switch spelled as the two things the fine-tune can fit.
void set_tune_targets(C& c, const std::string& name) {
  if (name != "inpainted" && name != "fill")
    throw std::invalid_argument("--tune-targets is '" + name + "'; give inpainted or fill");
  c.tune_to_fill = name == "fill";
}

RemovalSetting::Custom tune_targets_field() {
  return {[](const C& c) { return nlohmann::json(c.tune_to_fill ? "fill" : "inpainted"); },
          [](C& c, const nlohmann::json& v) { set_tune_targets(c, v.get<std::string>()); }, set_tune_targets};
}

void add_hole_and_fill_rows(SettingRows<C>& add) {
  add(field<int>([](C& c) -> int& { return c.holes.dilate; }), "holes.dilate", "--dilate",
      "Grow each hole by this many pixels (default 5: the object's blurred rim and contact shadow)")
      .range(0, 64);
  add(field<int>([](C& c) -> int& { return c.iters; }), "iters", "--iters",
      "Fine-tune the fill and the anchors near it for N iterations against the photos outside the object and the "
      "inpainted targets in the holes (default 0: the fill as placed, measured better with per-view inpainting)")
      .range(0, 100000000);
  add(field<int>([](C& c) -> int& { return c.fill.min_views; }), "fill.min_views", "--fill-views",
      "A fill anchor needs hole pixels of this many views in its voxel (default 2)")
      .range(1, 1000000);
  add(field<float>([](C& c) -> float& { return c.fill.max_alpha; }), "fill.max_alpha", "--fill-alpha",
      "Hole pixels the model without the object still covers with this alpha or more get no fill (default 0.5; 1: "
      "every hole pixel)")
      .range(1e-6, 1);
  add(field<float>([](C& c) -> float& { return c.fill.colour_quantile; }), "fill.colour_quantile", "--fill-quantile",
      "The fill's colour: of the views' colour estimates at a fill voxel, ranked by brightness, the one at this "
      "quantile (default 0.75: shadows only darken; 0.5 the median)")
      .range(0, 1);
  add(field<float>([](C& c) -> float& { return c.fill.opacity; }), "fill.opacity", "--fill-opacity",
      "Opacity of the fill's children (default 0.3)")
      .range(1e-4, 0.9999);
  add(field<float>([](C& c) -> float& { return c.fill.near; }), "fill.near", "--fill-near",
      "Kept anchors within this many of their voxel edges of the holes' 3D footprint are fine-tuned with the fill "
      "(default 1.5; 0: the fill alone)")
      .range(0, 1000);
}

void add_stray_and_hidden_rows(SettingRows<C>& add) {
  add(field<bool>([](C& c) -> bool& { return c.clear_stray; }), "clear_stray", "!--keep-stray",
      "Keep the children of kept anchors that sit among the object's Gaussians with its colour (by default they are "
      "cleared with it)");
  add(field<float>([](C& c) -> float& { return c.stray_colour; }), "stray_colour", "--stray-colour",
      "A kept child near the object's Gaussians is the object's when its colour is within this of theirs (mean "
      "absolute difference, 0..1) and nearer to it than to the kept Gaussians' there (default 0.2)")
      .range(0, 1);
  add(field<int>([](C& c) -> int& { return c.stray_reach; }), "stray_reach", "--stray-reach",
      "How near: finest-layer voxels within this many of a kept child's own along each axis (default 3; 0: its own "
      "voxel)")
      .range(0, 16);
  add(field<bool>([](C& c) -> bool& { return c.clear_hidden; }), "clear_hidden", "!--keep-hidden",
      "Keep the kept anchors near the object (within --stray-reach) that the training views saw only through it (by "
      "default they are removed with it, and the fill may take their voxels)");
  add(field<double>([](C& c) -> double& { return c.hidden_fraction; }), "hidden_fraction", "--hidden-fraction",
      "Such an anchor is hidden when, for each of its visible children, the views saw less than this fraction of it "
      "outside the object's silhouette (default 0.1)")
      .range(0, 1);
}

std::vector<RemovalSetting> build_table() {
  SettingRows<C> add;
  add(inpaint_field(), "inpaint", "--inpaint",
      "Fill the holes of the targets by telea (default), ns (Navier-Stokes) or none");
  add_hole_and_fill_rows(add);
  add_stray_and_hidden_rows(add);
  add(tune_targets_field(), "tune_targets", "--tune-targets",
      "What the fine-tune fits inside the holes: inpainted (the targets/ images) or fill (the filled model's own "
      "render, so only the seams around the holes move)")
      .one_of({"inpainted", "fill"});
  add(field<bool>([](C& c) -> bool& { return c.fill_holes; }), "fill_holes", "!--no-fill",
      "Delete only: no fill anchors and no fine-tune");
  add(field<uint64_t>([](C& c) -> uint64_t& { return c.seed; }), "seed", "--seed", "Random seed of the fill (default 1)")
      .seed();
  // Library-only settings (no flag): the benchmarks and the tests set them.
  add(field<uint64_t>([](C& c) -> uint64_t& { return c.fill.max_anchors; }), "fill.max_anchors", "",
      "At most this many fill anchors (0: as many as were removed)")
      .non_negative();
  add(field<float>([](C& c) -> float& { return c.fill.prune_opacity; }), "fill.prune_opacity", "",
      "After the fine-tune, fill anchors whose children's mean opacity is below this are dropped")
      .range(0, 0.999999);
  add(field<float>([](C& c) -> float& { return c.holes.object_weight; }), "holes.object_weight", "",
      "A pixel is the object's where the removed Gaussians' weights sum to this or more")
      .range(1e-6, 0.999999);
  add(field<float>([](C& c) -> float& { return c.holes.alpha_min; }), "holes.alpha_min", "",
      "After deletion, an object pixel is a hole where the kept Gaussians' opacity is below this")
      .range(1e-6, 0.999999);
  add(field<float>([](C& c) -> float& { return c.holes.behind; }), "holes.behind", "",
      "... or where the first surface it shows lies more than this many object diameters behind the object")
      .positive();
  return add.t;
}

}  // namespace

const std::vector<RemovalSetting>& removal_settings() {
  static const std::vector<RemovalSetting> table = build_table();
  return table;
}

}  // namespace ag2gs
