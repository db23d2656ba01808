// info: describe a scene directory, a model folder or a Gaussian .ply.
#include <spdlog/spdlog.h>

#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <map>
#include <memory>

#include "cli/commands.h"
#include "host/io/colmap_reader.h"
#include "host/io/model_io.h"
#include "host/io/ply_io.h"
#include "host/scene/scene.h"
#include "train/graph/anchor_graph.h"
#include "train/stage3/clustering.h"
#include "train/stage3/language.h"

namespace fs = std::filesystem;

namespace ag2gs::cli {
namespace {

// A Gaussian file: counts, bounds and mean opacity of its valid Gaussians;
// invalid ones (host/io/ply_io.h) are counted, and make info fail.
void print_ply(const std::string& ply) {
  size_t dropped = 0;
  GaussianSet set = read_ply(ply, PlyValues::activated, InvalidGaussians::drop, &dropped);
  Eigen::Vector3f lo = Eigen::Vector3f::Constant(1e30f), hi = -lo;
  double mean_opacity = 0;
  for (size_t i = 0; i < set.size(); ++i) {
    Eigen::Vector3f p(set.means[3 * i], set.means[3 * i + 1], set.means[3 * i + 2]);
    lo = lo.cwiseMin(p);
    hi = hi.cwiseMax(p);
    mean_opacity += set.opacities[i];
  }
  std::printf("%s\n  Gaussians: %zu\n  SH degree: %d\n", ply.c_str(), set.size(), set.sh_degree);
  if (set.size())
    std::printf("  bounds: [%g %g %g] .. [%g %g %g]\n  mean opacity: %.4f\n", lo.x(), lo.y(), lo.z(), hi.x(), hi.y(),
                hi.z(), mean_opacity / set.size());
  if (dropped > 0) {
    // The error names the first offender: read again without dropping.
    try {
      read_ply(ply);
    } catch (const std::exception& e) {
      throw std::runtime_error(std::string(e.what()) + " (info counted the " + std::to_string(set.size()) +
                               " valid ones above)");
    }
  }
}

// Stage 2's anchor graph: edge count, degrees in power-of-two bins, and
// whether it still describes the stored anchors.
void print_graph(const ModelArchive& a) {
  const AnchorGraph g = AnchorGraph::from_archive(a);
  std::printf("  anchor graph: %zu anchors, %zu edges (cell scale %d), mean degree %.2f\n", g.anchors(), g.edges(),
              g.cell_scale(), g.anchors() ? 2.0 * g.edges() / g.anchors() : 0.0);
  const std::vector<int64_t> hist = g.degree_histogram();
  std::printf("  degree histogram:");
  for (size_t b = 0; b < hist.size(); ++b)
    if (b == 0)
      std::printf(" 0: %lld", static_cast<long long>(hist[b]));
    else
      std::printf(", %lld-%lld: %lld", 1LL << (b - 1), (1LL << b) - 1, static_cast<long long>(hist[b]));
  std::printf("\n");
  if (a.meta.contains("anchors") && !g.matches(AnchorModel::from_archive(a)))
    std::printf("  note: the graph does not match the stored anchors (stale: built before they changed)\n");
}

// Stage 3's clusters: count, sizes in power-of-two bins, skipped anchors and
// how many clusters carry a language feature.
void print_clusters(const ModelArchive& a) {
  const size_t anchors = AnchorModel::from_archive(a).size();
  const Clustering c = clustering_from_archive(a, anchors);
  std::printf("  clusters: %d over %zu anchors (%zu connected components; %zu anchors in skipped small clusters)\n",
              c.clusters(), anchors, c.components, c.skipped_anchors);
  std::vector<int64_t> hist;
  for (int32_t n : c.cluster_size) {
    size_t b = 0;
    while ((int64_t{1} << b) <= n) ++b;  // n in [2^(b-1), 2^b)
    if (hist.size() <= b) hist.resize(b + 1, 0);
    ++hist[b];
  }
  std::printf("  cluster size histogram:");
  for (size_t b = 1; b < hist.size(); ++b)
    std::printf("%s %lld-%lld: %lld", b > 1 ? "," : "", 1LL << (b - 1), (1LL << b) - 1,
                static_cast<long long>(hist[b]));
  std::printf("\n");
  if (a.meta.contains("language")) {
    const LanguageFeatures l = language_from_archive(a, c.clusters());
    std::printf("  language features: %d of %d clusters (%d-d CLIP)\n", l.with_language(), c.clusters(), l.dim);
  } else {
    std::printf("  language features: none (trained on a scene without CLIP features)\n");
  }
}

void print_model(const std::string& path) {
  const ModelArchive a = read_model_archive(path);
  std::printf("%s\n  format version: %u\n", path.c_str(), kModelFormatVersion);
  for (auto it = a.meta.begin(); it != a.meta.end(); ++it) {
    std::string v = it.value().dump();
    if (v.size() > 100) v = v.substr(0, 97) + "...";
    std::printf("  %s: %s\n", it.key().c_str(), v.c_str());
  }
  std::printf("  arrays:\n");
  for (const auto& [name, t] : a.arrays()) {
    std::string shape;
    for (size_t i = 0; i < t.shape.size(); ++i) shape += (i ? "x" : "") + std::to_string(t.shape[i]);
    std::printf("    %-24s %-4s %s\n", name.c_str(), dtype_name(t.dtype), shape.c_str());
  }
  // The verdict after the tolerant listing: a damaged array (a NaN, an index
  // out of range) is an error naming it, as every other subcommand says.
  if (a.meta.contains("anchors")) AnchorModel::from_archive(a);
  if (AnchorGraph::in_archive(a)) print_graph(a);
  if (a.meta.contains("clusters")) print_clusters(a);
  if (a.meta.contains("anchors")) check_model_archive(a);  // the rest: counts, sky, training record
  const fs::path ply = fs::path(path).parent_path() / "point_cloud.ply";
  if (fs::exists(ply)) print_ply(ply.string());
}

struct InfoArgs {
  std::string path, sparse;
  int resolution = 1;
  bool eval = false;
  std::vector<int> sam_levels{3};
  bool quick = false;
};

void print_scene(const InfoArgs& a) {
  std::printf("scene: %s\n", a.path.c_str());
  // First a tolerant read, so distorted models are described before the verdict.
  try {
    const fs::path sparse = find_colmap_model(a.path, a.sparse);
    const ColmapModel m = read_colmap_model(sparse.string(), true);
    std::map<std::string, int> models;
    for (const std::string& s : m.camera_models) ++models[s];
    std::printf("  COLMAP model: %s (%s)\n  camera models:", sparse.string().c_str(),
                fs::exists(sparse / "images.bin") ? "binary" : "text");
    for (const auto& [name, n] : models) std::printf(" %s x%d", name.c_str(), n);
    std::printf("\n");
  } catch (const std::exception&) {
    // Scene::open below reports it.
  }
  SceneOptions opt;
  opt.sparse = a.sparse;
  opt.resolution = a.resolution;
  opt.eval = a.eval;
  opt.sam_levels = a.sam_levels;
  std::unique_ptr<Scene> scene = Scene::open(a.path, opt);
  const auto& views = scene->views();
  int min_w = 1 << 30, max_w = 0, min_h = 1 << 30, max_h = 0, from_scaled = 0;
  for (const SceneView& v : views) {
    min_w = std::min(min_w, v.camera.width);
    max_w = std::max(max_w, v.camera.width);
    min_h = std::min(min_h, v.camera.height);
    max_h = std::max(max_h, v.camera.height);
    from_scaled += v.downscale ? 0 : (a.resolution > 1);
  }
  std::printf("  images: %zu", views.size());
  if (min_w == max_w && min_h == max_h)
    std::printf(" at %dx%d", min_w, min_h);
  else
    std::printf(" from %dx%d to %dx%d", min_w, min_h, max_w, max_h);
  if (a.resolution > 1) {
    std::printf(" (1/%d resolution; %d read from images_%d/, %zu downscaled on load)", a.resolution, from_scaled,
                a.resolution, views.size() - from_scaled);
  }
  std::printf("\n  split: %zu train, %zu test%s\n", scene->train_views().size(), scene->test_views().size(),
              a.eval ? " (every 8th image held out)" : " (pass --eval to hold out every 8th image)");
  const SceneBounds& b = scene->bounds();
  std::printf("  points: %d (%d inside the robust 1-99%% box)\n", b.points_total, b.points_kept);
  if (b.points_total > 0) {
    std::printf("  bounds: [%.3f %.3f %.3f] .. [%.3f %.3f %.3f], longest extent %.3f\n", b.lo.x(), b.lo.y(), b.lo.z(),
                b.hi.x(), b.hi.y(), b.hi.z(), b.longest_extent());
  }
  std::printf("  camera rig: centre [%.3f %.3f %.3f], radius %.3f\n", b.camera_center.x(), b.camera_center.y(),
              b.camera_center.z(), b.camera_radius);
  std::printf("  semantics: %s\n", to_string(scene->semantics()));

  std::vector<std::string> problems;
  if (!a.quick) {
    int with_masks = 0, min_m = 1 << 30, max_m = 0, dropped_c = 0, dropped_e = 0;
    long total_m = 0;
    for (const SceneView& v : views) {
      try {
        scene->image(v.index);
      } catch (const std::exception& e) {
        problems.push_back(e.what());
      }
      try {
        auto m = scene->masks(v.index);
        if (!m) continue;
        ++with_masks;
        min_m = std::min(min_m, m->count);
        max_m = std::max(max_m, m->count);
        total_m += m->count;
        dropped_c += m->dropped_contained;
        dropped_e += m->dropped_empty;
      } catch (const std::exception& e) {
        problems.push_back(e.what());
      }
    }
    if (with_masks > 0) {
      std::printf("  masks per view: min %d, mean %.1f, max %d over %d views", min_m,
                  static_cast<double>(total_m) / with_masks, max_m, with_masks);
      std::printf(" (dropped: %d contained in another mask, %d empty after rescaling)\n", dropped_c, dropped_e);
      if (scene->feature_dim() > 0) std::printf("  feature dimension: %d\n", scene->feature_dim());
    }
  } else {
    std::printf("  (--quick: images and masks not decoded)\n");
  }
  for (const std::string& n : scene->notes()) std::printf("  note: %s\n", n.c_str());
  if (!problems.empty()) {
    for (const std::string& p : problems) std::printf("  problem: %s\n", p.c_str());
    throw std::runtime_error(std::to_string(problems.size()) + " problem(s) found in " + a.path);
  }
  if (scene->points().empty()) scene->require_points();
  std::printf("  ok\n");
}

void cmd_info(const InfoArgs& a) {
  const fs::path p(a.path);
  if (fs::is_directory(p)) {
    if (fs::exists(p / "model.ag2gs")) return print_model((p / "model.ag2gs").string());
    if (fs::exists(p / "sparse") || fs::exists(p / "images") || !a.sparse.empty()) return print_scene(a);
    if (fs::exists(p / "point_cloud.ply")) return print_ply((p / "point_cloud.ply").string());
    throw std::runtime_error(a.path +
                             ": neither a scene (images/, sparse/0/ or sparse/) nor a model folder (model.ag2gs)");
  }
  if (!fs::exists(p)) throw std::runtime_error(a.path + ": no such file or folder");
  if (p.extension() == ".ply") return print_ply(a.path);
  return print_model(a.path);
}

}  // namespace

void register_info(CLI::App& app, GlobalOptions&) {
  auto ia = std::make_shared<InfoArgs>();
  auto* info = app.add_subcommand("info", "Describe a scene directory, a model folder or a Gaussian .ply");
  info->add_option("path", ia->path, "Scene directory, model folder (model.ag2gs) or .ply file")->required();
  info->add_option("-r,--resolution", ia->resolution, "Resolution factor to check the images at (default 1)");
  info->add_option("--sparse", ia->sparse,
                   "COLMAP model folder inside the scene (default sparse/0/, else sparse/ when it holds the model)");
  info->add_flag("--eval", ia->eval, "Show the every-8th-image train/test split");
  info->add_option("--sam-level", ia->sam_levels, "SAM level(s) of language_features/ (0..3, default 3)");
  info->add_flag("--quick", ia->quick, "Do not decode every image and mask");
  set_action(info, [ia] { cmd_info(*ia); });
}

}  // namespace ag2gs::cli
