#include "queries/query_settings.h"

#include "queries/query.h"

namespace ag2gs {
namespace {

template <class T>
constexpr auto field = &QuerySetting::of<T>;  // a row's field from a lambda

std::vector<QuerySetting> build_table() {
  SettingRows<QueryConfig> add;
  using C = QueryConfig;
  add(field<float>([](C& c) -> float& { return c.min_weight; }), "min_weight", "--min-weight",
      "Grow along edges with exp(-|fi-fj|^2/(2 tau^2)) above this (default 0.9)")
      .range(1e-6, 0.999999);
  add(field<float>([](C& c) -> float& { return c.tau; }), "tau", "--tau", "Bilateral weight scale tau (default 0.05)")
      .range(1e-6, 1e6);
  add(field<float>([](C& c) -> float& { return c.text_margin; }), "text_margin", "--text-margin",
      "Text seeds: clusters within this of the best score (0.1)")
      .range(0, 2);
  add(field<float>([](C& c) -> float& { return c.text_threshold; }), "text_threshold", "--text-threshold",
      "Text: a cluster is the phrase's only if their cosine is at least this (default -1: no floor; the "
      "vocabulary's other phrases decide, and a phrase no cluster suits better than they do selects nothing)")
      .range(-1, 1);
  add(field<int>([](C& c) -> int& { return c.graph_cell_scale; }), "graph_cell_scale", "--graph-scale",
      "Query graph neighbourhood in top voxels (default 2)")
      .range(1, 1024);
  add(field<int>([](C& c) -> int& { return c.click_candidates; }), "click_candidates", "--click-candidates",
      "Click seed: of this many anchors nearest the clicked point, the one whose feature is closest to the pixel's "
      "rendered feature (default 8; 1 = the nearest anchor)")
      .range(1, 4096);
  add(field<bool>([](C& c) -> bool& { return c.click_dominant; }), "click_dominant", "--click-dominant,!--click-mean",
      "Click depth and feature: of the feature group of anchors holding the most blending weight at the pixel "
      "(default), or --click-mean: the ray's mean depth and rendered feature");
  add(field<float>([](C& c) -> float& { return c.click_front_weight; }), "click_front_weight", "--click-front-weight",
      "With --click-dominant: the nearest feature group along the ray holding at least this much of the pixel's "
      "blending weight instead of the heaviest (default 0.3; 0 = the heaviest)")
      .range(0, 0.999);
  // Library-only settings (no flag): the viewer and the benchmarks set them.
  add(field<float>([](C& c) -> float& { return c.min_click_alpha; }), "min_click_alpha", "",
      "Clicks on pixels with less alpha are background (0.5)")
      .range(0, 1);
  add(field<float>([](C& c) -> float& { return c.mask_threshold; }), "mask_threshold", "",
      "A pixel is in the mask where the selection's weight exceeds this (0.5)")
      .range(0, 0.999999);
  add(field<bool>([](C& c) -> bool& { return c.grow; }), "grow", "",
      "false: the ablation without region growing (plain feature similarity)");
  return add.t;
}

}  // namespace

const std::vector<QuerySetting>& query_settings() {
  static const std::vector<QuerySetting> table = build_table();
  return table;
}

}  // namespace ag2gs
