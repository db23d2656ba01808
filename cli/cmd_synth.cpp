// synth: writes a synthetic scene with exact ground truth (synth/synth_scene.h)
// and prints a summary read back from the scene's synth.json.
#include <spdlog/spdlog.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <memory>
#include <nlohmann/json.hpp>

#include "cli/commands.h"
#include "cli/run_guard.h"
#include "synth/synth_scene.h"
#include "host/io/json_input.h"

namespace fs = std::filesystem;

namespace ag2gs::cli {
namespace {

struct SynthArgs {
  std::string out;
  bool force = false;  // --force: write into a folder that is not empty
  SynthOptions options;
};

void cmd_synth(const SynthArgs& a) {
  refuse_file_as_output_folder(a.out, "OUT_DIR");
  refuse_nonempty_dir(a.out, a.force, "what is there (synth deletes a scene's images/ and sparse/0/ first)");
  auto t0 = std::chrono::steady_clock::now();
  write_synth_scene(a.out, a.options);
  double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();

  fs::path root(a.out);
  const nlohmann::json s = read_json_file((root / "synth.json").string());
  std::printf("%s: synthetic scene, seed %llu%s, %.1f s\n", a.out.c_str(),
              static_cast<unsigned long long>(a.options.seed), a.options.hard ? " (hard)" : "", seconds);
  std::printf("  objects: %zu\n", s["objects"].size());
  for (const auto& o : s["objects"])
    std::printf("    %2d  %-16s %s\n", o["id"].get<int>(), o["category"].get<std::string>().c_str(),
                o["primitive"].get<std::string>().c_str());
  const auto& rel = s["relations"];
  if (!rel["touching"].empty() || !rel["similar_colour"].empty() || !rel["thin"].empty())
    std::printf("  hard cases: touching %s, similar colour %s, thin %s, %zu occluding pairs\n",
                rel["touching"].dump().c_str(), rel["similar_colour"].dump().c_str(), rel["thin"].dump().c_str(),
                s["occlusion_pairs"].size());
  std::printf("  views: %zu (%zu test: every 8th), %dx%d\n", s["cameras"].size(), s["test_views"].size(),
              a.options.width, a.options.height);
  std::printf("  points: %zu\n", s["points_written"].get<size_t>());
  double per_level[4] = {0, 0, 0, 0};
  for (const auto& v : s["views"])
    for (int l = 0; l < 4; ++l) per_level[l] += v["masks_per_level"][l].get<double>();
  double n = std::max<size_t>(1, s["views"].size());
  std::printf("  masks per view (default/small/medium/large): %.1f / %.1f / %.1f / %.1f at %dx%d\n", per_level[0] / n,
              per_level[1] / n, per_level[2] / n, per_level[3] / n, s["masks"]["width"].get<int>(),
              s["masks"]["height"].get<int>());
  uintmax_t bytes = 0;
  for (const auto& p : s["files"]) bytes += fs::file_size(root / p.get<std::string>());
  std::printf("  files written: %zu, %.2f MiB\n", s["files"].size(), bytes / 1048576.0);
}

}  // namespace

void register_synth(CLI::App& app, GlobalOptions& /*global*/) {
  auto a = std::make_shared<SynthArgs>();
  SynthOptions& o = a->options;
  auto* sub = app.add_subcommand("synth",
                                 "Write a synthetic scene with exact ground truth: images, COLMAP model, SAM-like "
                                 "masks, CLIP-like features, GT ids, labels, clicks, vocabulary");
  sub->add_option("out_dir", a->out, "Scene directory to write (created; a folder that is not empty is refused)")
      ->required();
  sub->add_flag("--force", a->force, "Write into a folder that is not empty (our files in it are replaced)");
  sub->add_option("--seed", o.seed, "Random seed; the same seed gives byte-identical files (default 1)")
      ->check(seed_number());
  sub->add_option("--width", o.width, "Image width in pixels (default 160)")->check(CLI::Range(8, 8192));
  sub->add_option("--height", o.height, "Image height in pixels (default 120)")->check(CLI::Range(8, 8192));
  sub->add_option("--views", o.views, "Cameras on the ring; every 8th is a test view (default 24)")
      ->check(CLI::Range(1, 999));
  sub->add_option("--objects", o.objects, "Objects on the ground (default 5; hard mode needs >= 5)")
      ->check(CLI::Range(1, 16));
  sub->add_option("--samples", o.samples, "Supersampling per pixel axis (default 2 = 4 rays per pixel)")
      ->check(CLI::Range(1, 16));
  sub->add_option("--points", o.points, "Sparse points in points3D (default 4000)")->check(CLI::Range(0, 10000000));
  sub->add_option("--mask-factor", o.mask_factor,
                  "Write the SAM-like masks at 1/F of the image size (default 1; must divide width and height)")
      ->check(CLI::Range(1, 64));
  sub->add_option("--feature-dim", o.feature_dim, "CLIP-like feature dimension (default 512)")
      ->check(CLI::Range(1, 4096));
  sub->add_flag("--hard", o.hard, "Hard cases: two objects touching, two of similar colour, a thin pole, occlusion");
  sub->add_flag("--background-masks", o.background_masks,
                "SAM-like masks on the background too (floor quarters cut differently in each view, wall halves, "
                "ceiling), as SAM's automatic mode gives them on real photos");
  sub->add_flag("--removal-gt", o.removal_gt,
                "Also trace every test view without each category's objects: removal_gt/<category>/<view>.png, the "
                "exact ground truth of removing that object");
  sub->add_flag("--text-model", o.text_model, "Write the COLMAP model as .txt instead of .bin");
  sub->add_flag_callback(
      "--no-backdrop", [a] { a->options.backdrop = false; },
      "No textured backdrop (wall, floor ring, ceiling): rays that miss the objects and the ground see an "
      "untextured sky");
  sub->add_flag_callback(
      "--no-wall-points", [a] { a->options.wall_points = false; },
      "No SfM points on the backdrop's textured wall, as the far walls of real rooms often have none (what "
      "train's far shell is for)");
  set_action(sub, [a] { cmd_synth(*a); });
}

}  // namespace ag2gs::cli
