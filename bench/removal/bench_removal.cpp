// Scores an object removal against the exact ground truth of a generated
// scene (`ag2gs synth --removal-gt`) at its test views: the renders of the
// original model, of the model after `ag2gs remove`, and a per-view 2D
// inpainting of the original render inside the object's mask.
//
//   ag2gs_bench_removal SCENE_DIR --category C --original RENDERS --removed RENDERS
//                       [--deleted RENDERS] [--json OUT.json]
//
// RENDERS: folders written by `ag2gs render --views test` (rgb/ is read)
// at full size (-r 1). Per method and view, with M the category's exact mask
// (gt/ ids of its objects):
//   hole PSNR: inside M, against removal_gt/C/;
//   kept PSNR: outside M, against the same image;
//   residue:   the share of M's decidable pixels (where the original render
//              and the truth differ by at least 0.15 in mean absolute colour)
//              at which the render still looks like the original: closer to
//              it than a quarter of that difference. A fill that continues
//              the ground under the object is not residue (the truth shows
//              that ground); what is left of the object is.
// With --deleted (renders of the model after deleting only, written with
// `--outputs rgb,alpha --bg 0,0,0`, so that rgb is the kept Gaussians' own
// colour K with nothing behind them), a fourth row, "ceiling": the best any
// fill behind the kept surfaces can do. Such a fill shows through what the
// kept model leaves open, 1 - alpha, so a pixel renders K + (1 - alpha) f
// for a fill colour f in [0, 1]; the ceiling takes, per pixel of M, the f
// nearest to the truth: clamp((truth - K) / (1 - alpha), 0, 1). What it
// cannot reach is what other views photographed in front of the fill (the
// removed object's shadow, for one, which the truth lacks). A fill in front
// of a far surface seen through unseen ground (the backdrop behind a floor
// no view saw, which `remove` also fills) can do better than this. The row
// has no kept PSNR (nan; null in the JSON).
#include <CLI/CLI.hpp>
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <opencv2/photo.hpp>
#include <set>
#include <vector>

#include "host/io/atomic_file.h"
#include "host/io/npy_io.h"
#include "queries/semantic_eval.h"

using namespace ag2gs;
namespace fs = std::filesystem;

namespace {

cv::Mat read_or_throw(const fs::path& p, int flags) {
  cv::Mat m = cv::imread(p.string(), flags);
  if (m.empty()) throw std::runtime_error(p.string() + ": missing or unreadable");
  return m;
}

struct Sums {
  double se_in = 0, se_out = 0;
  size_t n_in = 0, n_out = 0, residue = 0, decidable = 0;
  void add(const cv::Mat& img, const cv::Mat& truth, const cv::Mat& mask) {
    for (int y = 0; y < img.rows; ++y)
      for (int x = 0; x < img.cols; ++x) {
        const cv::Vec3b a = img.at<cv::Vec3b>(y, x), b = truth.at<cv::Vec3b>(y, x);
        double se = 0;
        for (int c = 0; c < 3; ++c) se += std::pow((a[c] - b[c]) / 255.0, 2);
        if (mask.at<uint8_t>(y, x)) {
          se_in += se;
          n_in += 3;
        } else {
          se_out += se;
          n_out += 3;
        }
      }
  }
  static double psnr(double se, size_t n) { return n ? -10 * std::log10(std::max(se / n, 1e-12)) : NAN; }
  nlohmann::json to_json(size_t mask_pixels) const {
    return {{"hole_psnr", psnr(se_in, n_in)},
            {"kept_psnr", psnr(se_out, n_out)},
            {"residue", decidable ? double(residue) / decidable : 0.0},
            {"residue_pixels", decidable}};
  }
};

// Residue of `img` against the original render `orig` and the truth, over M.
void add_residue(Sums& s, const cv::Mat& img, const cv::Mat& orig, const cv::Mat& truth, const cv::Mat& mask) {
  auto dist = [](const cv::Vec3b& a, const cv::Vec3b& b) {
    return (std::abs(a[0] - b[0]) + std::abs(a[1] - b[1]) + std::abs(a[2] - b[2])) / (3.0 * 255.0);
  };
  for (int y = 0; y < mask.rows; ++y)
    for (int x = 0; x < mask.cols; ++x) {
      if (!mask.at<uint8_t>(y, x)) continue;
      const cv::Vec3b o = orig.at<cv::Vec3b>(y, x), t = truth.at<cv::Vec3b>(y, x), r = img.at<cv::Vec3b>(y, x);
      const double contrast = dist(o, t);
      if (contrast < 0.15) continue;
      ++s.decidable;
      if (dist(r, o) < 0.25 * contrast) ++s.residue;
    }
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"Score an object removal against a generated scene's exact removal ground truth"};
  std::string scene_dir, category, original, removed, json_out;
  app.add_option("scene_dir", scene_dir, "Scene written by `ag2gs synth --removal-gt`")->required();
  app.add_option("--category", category, "The removed category (a folder of removal_gt/)")->required();
  app.add_option("--original", original, "Renders of the original model (rgb/ of the test views)")->required();
  app.add_option("--removed", removed, "Renders of the model after removal")->required();
  std::string deleted;
  app.add_option("--deleted", deleted,
                 "Renders of the model after deleting only (`--outputs rgb,alpha --bg 0,0,0`): adds the fill's "
                 "ceiling row");
  app.add_option("--json", json_out, "Also write the numbers here");
  CLI11_PARSE(app, argc, argv);
  try {
    const fs::path scene(scene_dir), truth_dir = fs::path(scene_dir) / "removal_gt" / category;
    if (!fs::is_directory(truth_dir))
      throw std::runtime_error(truth_dir.string() + " is missing: generate the scene with `ag2gs synth --removal-gt`");
    std::set<int> ids;
    for (const auto& [id, cat] : read_synth_objects(scene_dir))
      if (cat == category) ids.insert(id);
    Sums s_orig, s_removed, s_2d, s_ceiling;
    size_t mask_pixels = 0;
    nlohmann::json views = nlohmann::json::array();
    std::vector<fs::path> files;
    for (const auto& e : fs::directory_iterator(truth_dir)) files.push_back(e.path());
    std::sort(files.begin(), files.end());
    for (const fs::path& truth_file : files) {
      const std::string stem = truth_file.stem().string();
      const cv::Mat truth = read_or_throw(truth_file, cv::IMREAD_COLOR);
      const cv::Mat gt = read_or_throw(scene / "gt" / (stem + ".png"), cv::IMREAD_UNCHANGED);
      cv::Mat mask(gt.size(), CV_8UC1, cv::Scalar(0));
      for (int y = 0; y < gt.rows; ++y)
        for (int x = 0; x < gt.cols; ++x) mask.at<uint8_t>(y, x) = ids.count(gt.at<uint16_t>(y, x)) ? 1 : 0;
      const size_t m = cv::countNonZero(mask);
      if (m == 0) continue;  // the category is not in this view
      const cv::Mat a = read_or_throw(fs::path(original) / "rgb" / (stem + ".png"), cv::IMREAD_COLOR);
      const cv::Mat b = read_or_throw(fs::path(removed) / "rgb" / (stem + ".png"), cv::IMREAD_COLOR);
      if (a.size() != truth.size() || b.size() != truth.size())
        throw std::runtime_error(stem + ": renders are not the size of the scene's images (render with -r 1)");
      // 2D inpainting alone: the original render, filled inside the mask
      // grown by 2 pixels (the object's blurred rim), as `remove` dilates.
      cv::Mat grown, inpainted;
      cv::dilate(mask * 255, grown, cv::getStructuringElement(cv::MORPH_CROSS, cv::Size(3, 3)), cv::Point(-1, -1), 2);
      cv::inpaint(a, grown, inpainted, 3.0, cv::INPAINT_TELEA);
      s_orig.add(a, truth, mask);
      s_removed.add(b, truth, mask);
      s_2d.add(inpainted, truth, mask);
      if (!deleted.empty()) {
        cv::Mat c = read_or_throw(fs::path(deleted) / "rgb" / (stem + ".png"), cv::IMREAD_COLOR);
        const fs::path alpha_file = fs::path(deleted) / "alpha" / (stem + ".npy");
        const NpyArray alpha = read_npy(alpha_file.string());
        if (c.size() != truth.size() || alpha.size() != mask.total())
          throw std::runtime_error(stem +
                                   ": --deleted renders are not the size of the scene's images (render with -r 1 "
                                   "--outputs rgb,alpha --bg 0,0,0)");
        for (int y = 0; y < mask.rows; ++y)
          for (int x = 0; x < mask.cols; ++x) {
            const double al = alpha.data[static_cast<size_t>(y) * mask.cols + x];
            cv::Vec3b& k = c.at<cv::Vec3b>(y, x);
            if (al <= 0 && (k[0] | k[1] | k[2]))
              throw std::runtime_error(stem + ": --deleted rgb is not black where alpha is 0 (render with --bg 0,0,0)");
            if (!mask.at<uint8_t>(y, x) || al >= 1) continue;
            const cv::Vec3b t = truth.at<cv::Vec3b>(y, x);
            for (int ch = 0; ch < 3; ++ch) {
              const double f = std::clamp((t[ch] - k[ch]) / (255.0 * (1 - al)), 0.0, 1.0);
              k[ch] = cv::saturate_cast<uint8_t>(k[ch] + 255.0 * (1 - al) * f);
            }
          }
        s_ceiling.add(c, truth, mask);
        add_residue(s_ceiling, c, a, truth, mask);
      }
      add_residue(s_orig, a, a, truth, mask);
      add_residue(s_removed, b, a, truth, mask);
      add_residue(s_2d, inpainted, a, truth, mask);
      mask_pixels += m;
      views.push_back({{"view", stem}, {"mask_pixels", m}});
    }
    if (mask_pixels == 0) throw std::runtime_error("\"" + category + "\" is visible in no test view");
    nlohmann::json j{{"category", category},
                     {"mask_pixels", mask_pixels},
                     {"views", views},
                     {"original", s_orig.to_json(mask_pixels)},
                     {"removed", s_removed.to_json(mask_pixels)},
                     {"inpaint_2d", s_2d.to_json(mask_pixels)}};
    std::vector<const char*> rows{"original", "removed", "inpaint_2d"};
    if (!deleted.empty()) {
      j["ceiling"] = s_ceiling.to_json(mask_pixels);
      j["ceiling"]["kept_psnr"] = NAN;  // its pixels outside M have no sky: not a score
      rows.push_back("ceiling");
    }
    for (const char* k : rows)
      std::printf("%-12s hole PSNR %6.2f  kept PSNR %6.2f  residue %.4f  (%zu px)  %s\n", k,
                  j[k]["hole_psnr"].get<double>(), j[k]["kept_psnr"].get<double>(), j[k]["residue"].get<double>(),
                  mask_pixels, category.c_str());
    if (!json_out.empty()) {
      AtomicFile f(json_out);
      f.write(j.dump(2) + "\n");
      f.commit();
    }
  } catch (const std::exception& e) {
    std::fprintf(stderr, "ag2gs_bench_removal: error: %s\n", e.what());
    return 1;
  }
  return 0;
}
