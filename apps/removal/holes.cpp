#include "apps/removal/holes.h"

#include <algorithm>
#include <cmath>
#include <opencv2/imgproc.hpp>
#include <opencv2/photo.hpp>
#include <stdexcept>

#include "train/train_common.h"

namespace ag2gs {

void HoleSettings::validate() const {
  auto in01 = [](float v) { return std::isfinite(v) && v > 0.f && v < 1.f; };
  if (!in01(object_weight))
    throw std::invalid_argument("hole settings: object_weight must be in (0, 1), got " + std::to_string(object_weight));
  if (!in01(alpha_min))
    throw std::invalid_argument("hole settings: alpha_min must be in (0, 1), got " + std::to_string(alpha_min));
  if (!(std::isfinite(behind) && behind > 0.f))
    throw std::invalid_argument("hole settings: behind must be > 0, got " + std::to_string(behind));
  if (dilate < 0 || dilate > 64)
    throw std::invalid_argument("--dilate must be in [0, 64] pixels, got " + std::to_string(dilate));
}

double object_diameter(const GaussianSet& removed) {
  const size_t n = removed.size();
  if (n == 0) return 0.0;
  double centre[3];
  std::vector<double> v(n);
  for (int k = 0; k < 3; ++k) {
    for (size_t i = 0; i < n; ++i) v[i] = removed.means[3 * i + k];
    std::nth_element(v.begin(), v.begin() + n / 2, v.end());
    centre[k] = v[n / 2];
  }
  for (size_t i = 0; i < n; ++i) {
    double d2 = 0;
    for (int k = 0; k < 3; ++k) {
      const double d = removed.means[3 * i + k] - centre[k];
      d2 += d * d;
    }
    v[i] = std::sqrt(d2);
  }
  const size_t q = std::min(n - 1, static_cast<size_t>(0.95 * static_cast<double>(n)));
  std::nth_element(v.begin(), v.begin() + q, v.end());
  return 2.0 * v[q];
}

HoleFinder::HoleFinder(const GaussianSet& kept, const GaussianSet& removed)
    : kept_(kept), removed_(removed), diameter_(object_diameter(removed)) {
  if (kept.sh_degree != removed.sh_degree)
    throw std::invalid_argument("HoleFinder: kept and removed Gaussians have different SH degrees");
  full_ = kept;
  const size_t nk = kept.size(), nr = removed.size();
  full_.resize(nk + nr);
  std::copy(removed.means.begin(), removed.means.end(), full_.means.begin() + 3 * nk);
  std::copy(removed.scales.begin(), removed.scales.end(), full_.scales.begin() + 3 * nk);
  std::copy(removed.quats.begin(), removed.quats.end(), full_.quats.begin() + 4 * nk);
  std::copy(removed.opacities.begin(), removed.opacities.end(), full_.opacities.begin() + nk);
  std::copy(removed.sh.begin(), removed.sh.end(), full_.sh.begin() + nk * full_.sh_coeffs() * 3);
  std::fill(full_.features.begin(), full_.features.end(), 0.f);
  for (size_t i = 0; i < nr; ++i) full_.features[3 * (nk + i)] = 1.f;
}

ViewHole HoleFinder::find(Renderer& renderer, const Camera& cam, const HoleSettings& s, const RenderSettings& render,
                          Sky* sky) {
  s.validate();
  ViewHole h;
  h.width = cam.width;
  h.height = cam.height;
  const size_t npix = static_cast<size_t>(cam.width) * cam.height;
  const size_t nk = kept_.size(), nr = removed_.size();
  for (size_t i = 0; i < nr; ++i) {
    const Eigen::Vector3d m(removed_.means[3 * i], removed_.means[3 * i + 1], removed_.means[3 * i + 2]);
    full_.features[3 * (nk + i) + 1] = static_cast<float>((cam.R * m + cam.t).z());
  }
  RenderSettings with_features = render;
  with_features.features = true;
  const RenderOutput before = renderer.render(full_, cam, with_features);

  RenderSettings plain = render;
  plain.features = false;
  RenderOutput after = renderer.render(kept_, cam, plain);
  if (sky) composite_sky(renderer, *sky, cam, after);
  h.rgb_after = after.rgb;
  h.alpha_after = after.alpha;
  h.depth_after.assign(npix, 0.f);
  for (size_t p = 0; p < npix; ++p)
    if (after.alpha[p] > 0.f) h.depth_after[p] = after.depth[p] / after.alpha[p];
  h.object_depth.assign(npix, 0.f);

  h.object.assign(npix, 0);
  cv::Mat hole(cam.height, cam.width, CV_8UC1, cv::Scalar(0));
  for (size_t p = 0; p < npix; ++p) {
    const float w = before.feature[3 * p];
    if (!(w >= s.object_weight)) continue;
    h.object[p] = 1;
    ++h.object_pixels;
    const double object_depth = before.feature[3 * p + 1] / w;
    h.object_depth[p] = static_cast<float>(object_depth);
    const float a = after.alpha[p];
    bool is_hole = a < s.alpha_min;
    if (!is_hole) {
      const double depth = after.depth[p] / a;
      is_hole = depth > object_depth + s.behind * diameter_;
    }
    if (is_hole) {
      hole.data[p] = 1;
      ++h.undilated_hole_pixels;
    }
  }
  h.hole.assign(hole.data, hole.data + npix);
  if (s.dilate > 0 && h.undilated_hole_pixels > 0) h.hole = dilate_mask(h.hole, cam.width, cam.height, s.dilate);
  for (uint8_t b : h.hole) h.hole_pixels += b;
  return h;
}

std::vector<uint8_t> dilate_mask(const std::vector<uint8_t>& mask, int width, int height, int steps) {
  if (mask.size() != static_cast<size_t>(width) * height)
    throw std::invalid_argument("dilate_mask: " + std::to_string(mask.size()) + " values for " + std::to_string(width) +
                                "x" + std::to_string(height));
  if (steps <= 0) return mask;
  cv::Mat m(height, width, CV_8UC1, const_cast<uint8_t*>(mask.data())), out;
  cv::dilate(m, out, cv::getStructuringElement(cv::MORPH_CROSS, cv::Size(3, 3)), cv::Point(-1, -1), steps);
  return std::vector<uint8_t>(out.data, out.data + mask.size());
}

InpaintMethod parse_inpaint_method(const std::string& name) {
  if (name == "telea") return InpaintMethod::kTelea;
  if (name == "ns") return InpaintMethod::kNavierStokes;
  if (name == "none") return InpaintMethod::kNone;
  throw std::invalid_argument("--inpaint '" + name + "': expected telea, ns or none");
}

std::vector<float> inpaint_hole(const std::vector<float>& rgb, const std::vector<uint8_t>& hole, int width, int height,
                                InpaintMethod method) {
  const size_t npix = static_cast<size_t>(width) * height;
  if (rgb.size() != npix * 3 || hole.size() != npix)
    throw std::invalid_argument("inpaint_hole: image and hole sizes do not match " + std::to_string(width) + "x" +
                                std::to_string(height));
  if (method == InpaintMethod::kNone) return rgb;
  // OpenCV inpaints 8-bit images; the filled pixels are rounded to 1/255,
  // the rest are copied back exactly.
  cv::Mat img(height, width, CV_8UC3), mask(height, width, CV_8UC1);
  for (size_t p = 0; p < npix; ++p) {
    for (int c = 0; c < 3; ++c)
      img.data[3 * p + c] = static_cast<uint8_t>(std::lround(std::clamp(rgb[3 * p + c], 0.f, 1.f) * 255.f));
    mask.data[p] = hole[p] ? 255 : 0;
  }
  cv::Mat out;
  cv::inpaint(img, mask, out, 3.0, method == InpaintMethod::kTelea ? cv::INPAINT_TELEA : cv::INPAINT_NS);
  std::vector<float> filled = rgb;
  for (size_t p = 0; p < npix; ++p)
    if (hole[p])
      for (int c = 0; c < 3; ++c) filled[3 * p + c] = out.data[3 * p + c] / 255.f;
  return filled;
}

}  // namespace ag2gs
