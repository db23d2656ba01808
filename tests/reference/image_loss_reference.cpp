// Double-precision reference of the photometric loss: direct 2D window sums.
#include "tests/reference/image_loss_reference.h"

#include <cmath>
#include <stdexcept>
#include <string>

namespace ag2gs::ref {

namespace {

constexpr int kRadius = 5;
constexpr double kC1 = 0.01 * 0.01, kC2 = 0.03 * 0.03;

// Raw moments of one channel at one pixel: sums over the 11x11 window of
// G(d) * (x, y, x^2, y^2, xy), pixels outside the image counting as 0.
struct Moments {
  double mx = 0, my = 0, exx = 0, eyy = 0, exy = 0;
};

}  // namespace

std::vector<double> ssim_window_1d() {
  const double sigma = 1.5;
  std::vector<double> g;
  double sum = 0;
  for (int i = 0; i < 2 * kRadius + 1; ++i) {
    const double d = i - kRadius;
    g.push_back(std::exp(-d * d / (2 * sigma * sigma)));
    sum += g.back();
  }
  for (double& v : g) v /= sum;
  return g;
}

RefImageLoss image_loss(const std::vector<double>& x, const std::vector<double>& y, int width, int height,
                        double lambda, bool with_grad, const std::vector<double>* weights) {
  if (width <= 0 || height <= 0) throw std::invalid_argument("ref::image_loss: empty image");
  const size_t npix = static_cast<size_t>(width) * height;
  if (x.size() != npix * 3 || y.size() != npix * 3 || (weights && weights->size() != npix))
    throw std::invalid_argument("ref::image_loss: array sizes do not match " + std::to_string(width) + "x" +
                                std::to_string(height));
  const std::vector<double> g1 = ssim_window_1d();
  double G[2 * kRadius + 1][2 * kRadius + 1];  // the 2D window g g^T
  for (int i = 0; i <= 2 * kRadius; ++i)
    for (int j = 0; j <= 2 * kRadius; ++j) G[i][j] = g1[i] * g1[j];
  auto w_at = [&](size_t p) { return weights ? (*weights)[p] : 1.0; };

  RefImageLoss out;
  out.ssim_map.assign(npix * 3, 0.0);
  // dS/d(mx, Exx, Exy) per pixel and channel, for the backward pass.
  std::vector<double> dmx(npix * 3), dexx(npix * 3), dexy(npix * 3);
  double wsum = 0, l1 = 0, ssim = 0, sq = 0;
  for (int r = 0; r < height; ++r)
    for (int col = 0; col < width; ++col) {
      const size_t p = static_cast<size_t>(r) * width + col;
      const double w = w_at(p);
      wsum += w;
      for (int c = 0; c < 3; ++c) {
        Moments m;
        for (int dr = -kRadius; dr <= kRadius; ++dr)
          for (int dc = -kRadius; dc <= kRadius; ++dc) {
            const int rr = r + dr, cc = col + dc;
            if (rr < 0 || rr >= height || cc < 0 || cc >= width) continue;
            const size_t i = (static_cast<size_t>(rr) * width + cc) * 3 + c;
            const double gw = G[dr + kRadius][dc + kRadius];
            m.mx += gw * x[i];
            m.my += gw * y[i];
            m.exx += gw * x[i] * x[i];
            m.eyy += gw * y[i] * y[i];
            m.exy += gw * x[i] * y[i];
          }
        // S = N / D, N = N1 N2, D = D1 D2, in the raw moments.
        const double n1 = 2 * m.mx * m.my + kC1;
        const double n2 = 2 * (m.exy - m.mx * m.my) + kC2;
        const double d1 = m.mx * m.mx + m.my * m.my + kC1;
        const double d2 = (m.exx - m.mx * m.mx) + (m.eyy - m.my * m.my) + kC2;
        const double N = n1 * n2, D = d1 * d2, S = N / D;
        const size_t i = p * 3 + c;
        out.ssim_map[i] = S;
        // Quotient rule: dN/dmx = 2 my (n2 - n1), dD/dmx = 2 mx (d2 - d1);
        // Exx enters D2 only, Exy enters N2 only.
        dmx[i] = (2 * m.my * (n2 - n1) * D - N * 2 * m.mx * (d2 - d1)) / (D * D);
        dexx[i] = -N * d1 / (D * D);
        dexy[i] = 2 * n1 / D;
        const double diff = x[i] - y[i];
        l1 += w * std::abs(diff);
        ssim += w * S;
        sq += w * diff * diff;
      }
    }
  if (wsum > 0) {
    out.l1 = l1 / (3 * wsum);
    out.ssim = ssim / (3 * wsum);
    out.mse = sq / (3 * wsum);
  }
  out.loss = (1 - lambda) * out.l1 + lambda * (1 - out.ssim);
  if (!with_grad) return out;

  out.grad.assign(npix * 3, 0.0);
  if (!(wsum > 0)) return out;
  const double inv = 1.0 / (3 * wsum);
  // dL/dx_q = sum_p dL/dS(p) dS(p)/dx_q + the L1 term, with
  // dS(p)/dx_q = G(q - p) (dS/dmx + 2 x_q dS/dExx + y_q dS/dExy)(p).
  for (int r = 0; r < height; ++r)
    for (int col = 0; col < width; ++col) {
      const size_t q = static_cast<size_t>(r) * width + col;
      for (int c = 0; c < 3; ++c) {
        const size_t iq = q * 3 + c;
        double acc = 0;
        for (int dr = -kRadius; dr <= kRadius; ++dr)
          for (int dc = -kRadius; dc <= kRadius; ++dc) {
            const int rr = r + dr, cc = col + dc;
            if (rr < 0 || rr >= height || cc < 0 || cc >= width) continue;
            const size_t p = static_cast<size_t>(rr) * width + cc, ip = p * 3 + c;
            const double dl_ds = -lambda * w_at(p) * inv;
            acc += G[dr + kRadius][dc + kRadius] * dl_ds * (dmx[ip] + 2 * x[iq] * dexx[ip] + y[iq] * dexy[ip]);
          }
        const double diff = x[iq] - y[iq];
        const double sign = diff > 0 ? 1.0 : (diff < 0 ? -1.0 : 0.0);
        out.grad[iq] = acc + (1 - lambda) * w_at(q) * sign * inv;
      }
    }
  return out;
}

RefImageLoss image_loss(const std::vector<float>& rendered, const std::vector<float>& target, int width, int height,
                        double lambda, bool with_grad, const std::vector<float>* weights) {
  std::vector<double> x(rendered.begin(), rendered.end()), y(target.begin(), target.end());
  if (!weights) return image_loss(x, y, width, height, lambda, with_grad, nullptr);
  std::vector<double> w(weights->begin(), weights->end());
  return image_loss(x, y, width, height, lambda, with_grad, &w);
}

}  // namespace ag2gs::ref
