#include "train/stage3/stage3_settings.h"

#include <limits>

#include "train/stage3/language.h"

namespace ag2gs {
namespace {

template <class T>
constexpr auto field = &Stage3Setting::of<T>;  // a row's field from a lambda
using C = Stage3Config;

std::vector<Stage3Setting> build_table() {
  SettingRows<C> add;
  add(field<float>([](C& c) -> float& { return c.cluster.max_distance; }), "cluster_distance", "--cluster-distance",
      "Stage 3: join graph neighbours whose feature distance is below this (default 0.01)")
      .range(1e-9, 1e6);
  add(field<int>([](C& c) -> int& { return c.cluster.min_cluster_size; }), "min_cluster_size", "--min-cluster-size",
      "Stage 3: clusters with fewer anchors are skipped (default 5)")
      .range(1, std::numeric_limits<int>::max());
  add(field<float>([](C& c) -> float& { return c.language.min_score; }), "match_score", "--match-score",
      "Stage 3: a cluster takes a mask's CLIP feature when their score S exceeds this (default 0.3)")
      .range(-1, 1);
  add(field<float>([](C& c) -> float& { return c.language.softmax_scale; }), "match_softmax", "--match-softmax",
      "Stage 3: the matches' weights are softmax(scale * S) (default 10)")
      .range(0.001, 80);
  add(field<float>([](C& c) -> float& { return c.language.instance_fraction; }), "instance_fraction",
      "--instance-fraction", "Stage 3: a pixel belongs to a cluster holding at least this share of its weight (default 0.5)")
      .range(0.5, 0.999);
  return add.t;
}

}  // namespace

const std::vector<Stage3Setting>& stage3_settings() {
  static const std::vector<Stage3Setting> table = build_table();
  return table;
}

nlohmann::json stage3_to_json(const Stage3Config& c) { return settings_to_json(stage3_settings(), c); }

void stage3_from_json(const nlohmann::json& j, Stage3Config& c) {
  for (const Stage3Setting& s : stage3_settings())
    if (j.contains(s.pointer())) s.set(c, j.at(s.pointer()));
}

}  // namespace ag2gs
