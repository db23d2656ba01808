// Double-precision reference of the mask losses: membership lists and the
// chain rule written out step by step.
#include "tests/reference/mask_loss_reference.h"

#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>

namespace ag2gs::ref {

namespace {

double sgn(double x) {
  return x > 0 ? 1.0 : (x < 0 ? -1.0 : 0.0);
}

}  // namespace

RefMaskLoss mask_loss(const std::vector<double>& feature, const std::vector<double>* alpha,
                      const std::vector<int32_t>& labels, int layers, int count, int width, int height, bool with_grad,
                      double alpha_min) {
  if (width <= 0 || height <= 0 || layers < 0 || count < 0) throw std::invalid_argument("ref::mask_loss: bad sizes");
  const size_t npix = static_cast<size_t>(width) * height;
  if (feature.size() != npix * 3 || labels.size() != npix * layers || (alpha && alpha->size() != npix))
    throw std::invalid_argument("ref::mask_loss: array sizes do not match " + std::to_string(width) + "x" +
                                std::to_string(height));
  // G and validity per pixel.
  std::vector<double> G(npix * 3, 0.0);
  std::vector<bool> valid(npix, true);
  for (size_t p = 0; p < npix; ++p) {
    double a = 1.0;
    if (alpha) {
      a = (*alpha)[p];
      if (!(a >= alpha_min)) {
        valid[p] = false;
        continue;
      }
    }
    for (int c = 0; c < 3; ++c) G[p * 3 + c] = feature[p * 3 + c] / a;
  }
  // Membership: mask j holds pixel p when some layer labels p with j.
  std::vector<std::vector<size_t>> members(count);
  for (size_t p = 0; p < npix; ++p) {
    if (!valid[p]) continue;
    for (int j = 0; j < count; ++j) {
      bool in = false;
      for (int l = 0; l < layers; ++l) in = in || labels[static_cast<size_t>(l) * npix + p] == j;
      if (in) members[j].push_back(p);
    }
  }

  RefMaskLoss out;
  out.means.assign(static_cast<size_t>(count) * 3, 0.0);
  out.sizes.assign(count, 0);
  out.margin_is = out.margin_ic = std::numeric_limits<double>::infinity();
  for (int j = 0; j < count; ++j) {
    const size_t n = members[j].size();
    out.sizes[j] = static_cast<int64_t>(n);
    out.mask_pixels += static_cast<int64_t>(n);
    if (n == 0) continue;
    ++out.masks;
    for (int c = 0; c < 3; ++c) {
      double s = 0;
      for (size_t p : members[j]) s += G[p * 3 + c];
      out.means[j * 3 + c] = s / static_cast<double>(n);
    }
  }
  const double T = static_cast<double>(out.mask_pixels);
  const int m = out.masks;

  // Losses and their gradients with respect to G (direct) and the means.
  std::vector<double> dis_dG(npix * 3, 0.0), dis_dmean(count * 3, 0.0);
  std::vector<double> dic_dmean(count * 3, 0.0);
  for (int j = 0; j < count; ++j)
    for (size_t p : members[j])
      for (int c = 0; c < 3; ++c) {
        const double d = G[p * 3 + c] - out.means[j * 3 + c];
        out.l_is += std::abs(d) / T;
        dis_dG[p * 3 + c] += sgn(d) / T;
        dis_dmean[j * 3 + c] -= sgn(d) / T;
        out.margin_is = std::min(out.margin_is, std::abs(d));
      }
  if (m >= 2) {
    const double norm = 1.0 / (static_cast<double>(m) * (m - 1));
    for (int j = 0; j < count; ++j)
      for (int k = 0; k < count; ++k) {
        if (j == k || out.sizes[j] == 0 || out.sizes[k] == 0) continue;
        double dist = 0;
        for (int c = 0; c < 3; ++c) dist += std::abs(out.means[j * 3 + c] - out.means[k * 3 + c]);
        out.l_ic += norm / (dist + 1);
        // d/d(dist) of 1 / (dist + 1), then dist through both means.
        const double dterm = -norm / ((dist + 1) * (dist + 1));
        for (int c = 0; c < 3; ++c) {
          const double diff = out.means[j * 3 + c] - out.means[k * 3 + c];
          dic_dmean[j * 3 + c] += dterm * sgn(diff);
          dic_dmean[k * 3 + c] -= dterm * sgn(diff);
          out.margin_ic = std::min(out.margin_ic, std::abs(diff));
        }
      }
  }
  if (!with_grad) return out;

  // Means back to their pixels: dmean_jc / dG_c(p) = 1 / |M_j|.
  std::vector<double> dic_dG(npix * 3, 0.0);
  for (int j = 0; j < count; ++j)
    for (size_t p : members[j])
      for (int c = 0; c < 3; ++c) {
        const double inv_n = 1.0 / static_cast<double>(members[j].size());
        dis_dG[p * 3 + c] += dis_dmean[j * 3 + c] * inv_n;
        dic_dG[p * 3 + c] += dic_dmean[j * 3 + c] * inv_n;
      }
  // G = F / alpha: dG_c/dF_c = 1 / alpha, dG_c/dalpha = -F_c / alpha^2.
  out.grad_is.assign(npix * 3, 0.0);
  out.grad_ic.assign(npix * 3, 0.0);
  out.grad_alpha_is.assign(npix, 0.0);
  out.grad_alpha_ic.assign(npix, 0.0);
  for (size_t p = 0; p < npix; ++p) {
    if (!valid[p]) continue;
    const double a = alpha ? (*alpha)[p] : 1.0;
    for (int c = 0; c < 3; ++c) {
      const size_t i = p * 3 + c;
      out.grad_is[i] = dis_dG[i] / a;
      out.grad_ic[i] = dic_dG[i] / a;
      if (alpha) {
        out.grad_alpha_is[p] -= dis_dG[i] * feature[i] / (a * a);
        out.grad_alpha_ic[p] -= dic_dG[i] * feature[i] / (a * a);
      }
    }
  }
  return out;
}

RefMaskLoss mask_loss(const std::vector<float>& feature, const std::vector<float>* alpha,
                      const std::vector<int32_t>& labels, int layers, int count, int width, int height, bool with_grad,
                      double alpha_min) {
  std::vector<double> f(feature.begin(), feature.end());
  if (!alpha) return mask_loss(f, nullptr, labels, layers, count, width, height, with_grad, alpha_min);
  std::vector<double> a(alpha->begin(), alpha->end());
  return mask_loss(f, &a, labels, layers, count, width, height, with_grad, alpha_min);
}

}  // namespace ag2gs::ref
