#include "host/render/sky.h"

#include <Eigen/Cholesky>
#include <algorithm>
#include <cmath>
#include <cstring>
#include <map>
#include <opencv2/imgproc.hpp>
#include <optional>
#include <stdexcept>
#include <string>

#include "host/device/kernel_call.h"

namespace ag2gs {

namespace {

// The kernels' camera arguments: rows of R^T (camera -> world) and (fx, fy, cx, cy).
struct SkyCamera {
  cl_float4 r[3];
  cl_float4 intr;
};

bool same_camera(const float (&a)[16], const SkyCamera& c, int w, int h, int cw, int ch) {
  return w == cw && h == ch && std::memcmp(a, &c, sizeof(a)) == 0;
}

SkyCamera sky_camera(const Camera& c) {
  SkyCamera s{};
  const Eigen::Matrix3d rt = c.R.transpose();
  for (int i = 0; i < 3; ++i) {
    s.r[i] = {{static_cast<float>(rt(i, 0)), static_cast<float>(rt(i, 1)), static_cast<float>(rt(i, 2)), 0.f}};
  }
  s.intr = {{static_cast<float>(c.fx), static_cast<float>(c.fy), static_cast<float>(c.cx), static_cast<float>(c.cy)}};
  return s;
}

// A sky kernel's call with its leading parameters set: the image size, the
// pixels per partial row (the kernels that write partial rows) and the view.
KernelCall sky_call(cl::Kernel& k, const Camera& camera, const SkyCamera& sc, std::optional<size_t> chunk = {}) {
  KernelCall call(k);
  call.arg("w", static_cast<cl_int>(camera.width)).arg("h", static_cast<cl_int>(camera.height));
  if (chunk) call.arg("chunk", static_cast<cl_int>(*chunk));
  call.arg("r0", sc.r[0]).arg("r1", sc.r[1]).arg("r2", sc.r[2]).arg("intr", sc.intr);
  return call;
}

}  // namespace

std::vector<float> sky_constant(int degree, const std::array<float, 3>& colour) {
  if (degree < 0 || degree > kSkyMaxDegree)
    throw std::invalid_argument("sky degree " + std::to_string(degree) + " is outside 0.." +
                                std::to_string(kSkyMaxDegree));
  std::vector<float> c(static_cast<size_t>(sh_coeffs_for_degree(degree)) * 3, 0.f);
  for (int i = 0; i < 3; ++i) c[i] = static_cast<float>(colour[i] / kShC0);
  return c;
}

int sky_degree_for(size_t values) {
  for (int d = 0; d <= kSkyMaxDegree; ++d)
    if (static_cast<size_t>(sh_coeffs_for_degree(d)) * 3 == values) return d;
  return -1;
}

void sky_to_archive(ModelArchive& archive, const std::vector<float>& coefficients) {
  archive.put("sky/sh", coefficients, {static_cast<int64_t>(coefficients.size() / 3), 3});
}

std::optional<std::vector<float>> sky_from_archive(const ModelArchive& archive) {
  if (!archive.has("sky/sh")) return std::nullopt;
  std::vector<float> c = archive.get<float>("sky/sh", {-1, 3});
  if (sky_degree_for(c.size()) < 0)
    throw std::runtime_error(archive.source + ": sky/sh holds " + std::to_string(c.size() / 3) +
                             " coefficients per channel; a sky of degree 0..3 has 1, 4, 9 or 16");
  for (size_t i = 0; i < c.size(); ++i)
    if (!std::isfinite(c[i]))
      throw std::runtime_error(archive.source + ": array 'sky/sh': element " + std::to_string(i) +
                               " is not a finite number; the file is damaged: train the model again");
  return c;
}

Sky::Sky(Runtime& rt) : rt_(rt) {
  for (DeviceBuffer* b : {&coef_, &grad_, &partial_, &out_, &sky_}) b->bind(&rt_);
  static_assert(sizeof(SkyCamera) == sizeof(Composed::args), "the kept camera holds the kernels' arguments");
}

std::map<std::string, std::string> Sky::defines() const {
  return {{"SKY_K", std::to_string(values_ / 3)}};
}

void Sky::set(int degree, const std::vector<float>& coefficients) {
  if (degree < 0 || degree > kSkyMaxDegree)
    throw std::invalid_argument("sky degree " + std::to_string(degree) + " is outside 0.." +
                                std::to_string(kSkyMaxDegree));
  const size_t values = static_cast<size_t>(sh_coeffs_for_degree(degree)) * 3;
  if (coefficients.size() != values)
    throw std::invalid_argument("a sky of degree " + std::to_string(degree) + " has " + std::to_string(values) +
                                " coefficient values, not " + std::to_string(coefficients.size()));
  degree_ = degree;
  values_ = values;
  composed_ = {};
  coef_.upload(coefficients);
  grad_.reserve(values * sizeof(float));
  grad_.fill_zero(values * sizeof(float));
}

std::vector<float> Sky::download() const {
  std::vector<float> c;
  coef_.download(c, values_);
  return c;
}

const DeviceBuffer& Sky::compose(const DeviceBuffer& rgb, const DeviceBuffer& alpha, const Camera& camera) {
  if (!enabled()) throw std::logic_error("Sky::compose without coefficients (Sky::set)");
  const size_t npix = static_cast<size_t>(camera.width) * camera.height;
  out_.reserve(npix * 3 * sizeof(float));
  sky_.reserve(npix * 3 * sizeof(float));
  const SkyCamera sc = sky_camera(camera);
  cl::Kernel k = rt_.kernel("sky.cl", "sky_compose", defines());
  const size_t f4 = sizeof(float);
  sky_call(k, camera, sc)
      .buffer("coef", coef_, values_ * f4)
      .buffer("rgb", rgb, npix * 3 * f4)
      .buffer("alpha", alpha, npix * f4)
      .buffer("out", out_, npix * 3 * f4)
      .buffer("sky_out", sky_, npix * 3 * f4)
      .done();
  rt_.launch("sky_compose", k, cl::NDRange((npix + 63) / 64 * 64), cl::NDRange(64));
  composed_.width = camera.width;
  composed_.height = camera.height;
  std::memcpy(composed_.args, &sc, sizeof(sc));
  return out_;
}

void Sky::backward(const DeviceBuffer& grad_out, const DeviceBuffer& alpha, const Camera& camera,
                   DeviceBuffer& grad_alpha, bool add, const DeviceBuffer* weight) {
  if (!enabled()) throw std::logic_error("Sky::backward without coefficients (Sky::set)");
  const size_t npix = static_cast<size_t>(camera.width) * camera.height;
  // At most 1024 partial rows of at least 64 pixels each: the sum's order is
  // a function of the image size alone.
  const size_t chunk = std::max<size_t>(64, (npix + 1023) / 1024);
  const size_t rows = (npix + chunk - 1) / chunk;
  grad_alpha.reserve(npix * sizeof(float));
  partial_.reserve(std::max<size_t>(rows, 1) * values_ * sizeof(float));
  const SkyCamera sc = sky_camera(camera);
  const size_t f4 = sizeof(float);
  if (!same_camera(composed_.args, sc, camera.width, camera.height, composed_.width, composed_.height)) {
    sky_.reserve(npix * 3 * sizeof(float));
    cl::Kernel c = rt_.kernel("sky.cl", "sky_colours", defines());
    sky_call(c, camera, sc).buffer("coef", coef_, values_ * f4).buffer("sky_out", sky_, npix * 3 * f4).done();
    rt_.launch("sky_compose", c, cl::NDRange((npix + 63) / 64 * 64), cl::NDRange(64));
    composed_.width = camera.width;
    composed_.height = camera.height;
    std::memcpy(composed_.args, &sc, sizeof(sc));
  }
  cl::Kernel k = rt_.kernel("sky.cl", "sky_grad_partial", defines());
  sky_call(k, camera, sc, chunk)
      .buffer("sky", sky_, npix * 3 * f4)
      .buffer("grad_out", grad_out, npix * 3 * f4)
      .buffer("alpha", alpha, npix * f4)
      .arg("use_weight", static_cast<cl_int>(weight ? 1 : 0))
      .buffer("weight", weight ? *weight : coef_, weight ? npix * f4 : 0)
      .arg("add_base", static_cast<cl_int>(add ? 1 : 0))
      .buffer("grad_alpha", grad_alpha, npix * f4)
      .arg("rows", static_cast<cl_int>(rows))
      .buffer("partial", partial_, rows * values_ * f4)
      .done();
  rt_.launch("sky_grad_partial", k, cl::NDRange((rows + 63) / 64 * 64), cl::NDRange(64));
  cl::Kernel r = rt_.kernel("sky.cl", "sky_grad_reduce", defines());
  set_kernel_args(r, static_cast<cl_int>(rows), static_cast<cl_int>(values_), partial_, grad_);
  rt_.launch("sky_grad_reduce", r, cl::NDRange(64), cl::NDRange(64));
}

void Sky::add_fit(const DeviceBuffer& image, const Camera& camera, Eigen::MatrixXd& gram, Eigen::MatrixXd& rhs,
                  const DeviceBuffer* weight, Eigen::Vector3d* squares) {
  if (!enabled()) throw std::logic_error("Sky::add_fit without a degree (Sky::set)");
  const int k_count = static_cast<int>(values_ / 3);
  const size_t npix = static_cast<size_t>(camera.width) * camera.height;
  const size_t chunk = std::max<size_t>(64, (npix + 1023) / 1024);
  const size_t rows = (npix + chunk - 1) / chunk;
  const size_t values = static_cast<size_t>(k_count) * k_count + 3 * static_cast<size_t>(k_count) + 3;
  partial_.reserve(std::max<size_t>(rows, 1) * values * sizeof(float));
  DeviceBuffer sums(&rt_);
  sums.reserve(values * sizeof(float));
  const SkyCamera sc = sky_camera(camera);
  cl::Kernel k = rt_.kernel("sky.cl", "sky_fit_partial", defines());
  const size_t f4 = sizeof(float);
  sky_call(k, camera, sc, chunk)
      .buffer("image", image, npix * 3 * f4)
      .arg("use_weight", static_cast<cl_int>(weight ? 1 : 0))
      .buffer("weight", weight ? *weight : coef_, weight ? npix * f4 : 0)
      .arg("rows", static_cast<cl_int>(rows))
      .buffer("partial", partial_, rows * values * f4)
      .done();
  rt_.launch("sky_fit_partial", k, cl::NDRange((rows + 63) / 64 * 64), cl::NDRange(64));
  cl::Kernel r = rt_.kernel("sky.cl", "sky_grad_reduce", defines());
  set_kernel_args(r, static_cast<cl_int>(rows), static_cast<cl_int>(values), partial_, sums);
  rt_.launch("sky_grad_reduce", r, cl::NDRange((values + 63) / 64 * 64), cl::NDRange(64));
  std::vector<float> v;
  sums.download(v, values);
  if (gram.rows() != k_count) gram = Eigen::MatrixXd::Zero(k_count, k_count);
  if (rhs.rows() != k_count) rhs = Eigen::MatrixXd::Zero(k_count, 3);
  for (int a = 0; a < k_count; ++a) {
    for (int b = 0; b < k_count; ++b) gram(a, b) += v[static_cast<size_t>(a) * k_count + b];
    for (int c = 0; c < 3; ++c) rhs(a, c) += v[static_cast<size_t>(k_count) * k_count + 3 * a + c];
  }
  if (squares)
    for (int c = 0; c < 3; ++c) (*squares)[c] += v[static_cast<size_t>(k_count) * k_count + 3 * k_count + c];
}

double Sky::fit_residual_rms(const Eigen::MatrixXd& gram, const Eigen::MatrixXd& rhs, const Eigen::Vector3d& squares,
                             const std::vector<float>& coefficients) {
  const Eigen::Index k = gram.rows();
  const double weight = k > 0 ? gram(0, 0) / (kShC0 * kShC0) : 0.0;  // Y_0 is the constant C0
  if (!(weight > 0) || coefficients.size() != static_cast<size_t>(k) * 3) return 0.0;
  double e = 0;
  for (int c = 0; c < 3; ++c) {
    Eigen::VectorXd x(k);
    for (Eigen::Index i = 0; i < k; ++i) x(i) = coefficients[static_cast<size_t>(i) * 3 + c];
    e += squares[c] - 2.0 * x.dot(rhs.col(c)) + x.dot(gram * x);
  }
  return std::sqrt(std::max(0.0, e / (3.0 * weight)));
}

std::vector<float> Sky::solve_fit(const Eigen::MatrixXd& gram, const Eigen::MatrixXd& rhs,
                                  const std::vector<float>& start, double min_ridge_pixels) {
  const Eigen::Index k = gram.rows();
  std::vector<float> out(static_cast<size_t>(k) * 3, 0.f);
  if (start.size() == out.size()) out = start;
  const double lambda = std::max(1e-3 * gram.trace() / std::max<Eigen::Index>(k, 1), min_ridge_pixels * kShC0 * kShC0);
  if (k == 0 || !(lambda > 0)) return out;
  Eigen::MatrixXd b = rhs;
  for (Eigen::Index i = 0; i < k; ++i)
    for (int c = 0; c < 3; ++c) b(i, c) += lambda * out[static_cast<size_t>(i) * 3 + c];
  const Eigen::MatrixXd x = (gram + Eigen::MatrixXd::Identity(k, k) * lambda).ldlt().solve(b);
  for (Eigen::Index i = 0; i < k; ++i)
    for (int c = 0; c < 3; ++c)
      if (std::isfinite(x(i, c))) out[static_cast<size_t>(i) * 3 + c] = static_cast<float>(x(i, c));
  return out;
}

std::vector<uint8_t> open_sky_pixels(const Camera& cam, const std::vector<Eigen::Vector3d>& points, int radius) {
  const int w = cam.width, h = cam.height;
  cv::Mat hit = cv::Mat::zeros(h, w, CV_8U);
  for (const Eigen::Vector3d& x : points) {
    const Eigen::Vector3d c = cam.R * x + cam.t;
    if (!(c.z() > 1e-9)) continue;
    const double u = cam.fx * c.x() / c.z() + cam.cx, v = cam.fy * c.y() / c.z() + cam.cy;
    if (!(u >= 0 && v >= 0 && u < w && v < h)) continue;
    hit.at<uint8_t>(static_cast<int>(v), static_cast<int>(u)) = 1;
  }
  if (radius > 0) {
    // The disc x^2 + y^2 <= radius^2 around each hit pixel.
    cv::Mat disc = cv::Mat::zeros(2 * radius + 1, 2 * radius + 1, CV_8U);
    for (int y = -radius; y <= radius; ++y)
      for (int x = -radius; x <= radius; ++x)
        if (x * x + y * y <= radius * radius) disc.at<uint8_t>(y + radius, x + radius) = 1;
    cv::dilate(hit, hit, disc, cv::Point(radius, radius), 1, cv::BORDER_CONSTANT, cv::Scalar(0));
  }
  std::vector<uint8_t> open(static_cast<size_t>(w) * h);
  for (int y = 0; y < h; ++y)
    for (int x = 0; x < w; ++x) open[static_cast<size_t>(y) * w + x] = hit.at<uint8_t>(y, x) ? 0 : 1;
  return open;
}

int open_sky_radius(const Camera& cam) {
  return std::max(2, static_cast<int>(std::lround(0.03 * std::max(cam.width, cam.height))));
}

double far_shell_radius(const std::vector<Eigen::Vector3d>& points, const Eigen::Vector3d& centre, double least) {
  std::vector<double> dist;
  dist.reserve(points.size());
  for (const Eigen::Vector3d& p : points)
    if (p.allFinite()) dist.push_back((p - centre).norm());
  if (dist.empty()) return least;
  const size_t k = std::min(dist.size() - 1, static_cast<size_t>(0.98 * static_cast<double>(dist.size())));
  std::nth_element(dist.begin(), dist.begin() + static_cast<std::ptrdiff_t>(k), dist.end());
  return std::max(dist[k], least);
}

void far_shell_points(const Camera& cam, const std::vector<uint8_t>& open, const std::vector<float>& rgb,
                      const Eigen::Vector3d& centre, double radius, int stride, std::vector<Eigen::Vector3d>& points,
                      std::vector<Eigen::Vector3<uint8_t>>& colors) {
  const size_t npix = static_cast<size_t>(cam.width) * cam.height;
  if (open.size() != npix || rgb.size() != 3 * npix)
    throw std::invalid_argument("far_shell_points: the open mask or the photo does not match the camera");
  const int step = std::max(1, stride);
  const Eigen::Vector3d o = cam.center(), oc = o - centre;
  const Eigen::Matrix3d to_world = cam.R.transpose();
  for (int y = step / 2; y < cam.height; y += step)
    for (int x = step / 2; x < cam.width; x += step) {
      const size_t p = static_cast<size_t>(y) * cam.width + x;
      if (!open[p]) continue;
      const Eigen::Vector3d d =
          (to_world * Eigen::Vector3d((x + 0.5 - cam.cx) / cam.fx, (y + 0.5 - cam.cy) / cam.fy, 1.0)).normalized();
      // |oc + t d| = radius, the larger root (the camera is inside).
      const double b = oc.dot(d), disc = b * b - (oc.squaredNorm() - radius * radius);
      if (!(disc >= 0)) continue;
      const double t = -b + std::sqrt(disc);
      if (!(t > 0)) continue;
      points.push_back(o + t * d);
      Eigen::Vector3<uint8_t> c;
      for (int k = 0; k < 3; ++k)
        c[k] = static_cast<uint8_t>(std::clamp(std::lround(255.0 * rgb[3 * p + k]), 0L, 255L));
      colors.push_back(c);
    }
}

void open_sky_weights(const std::vector<uint8_t>& open, int width, int height, int factor, std::vector<float>& out) {
  const int f = std::max(1, factor);
  const int w = std::max(1, width / f), h = std::max(1, height / f);
  const int bx = std::min(f, width), by = std::min(f, height);
  out.assign(static_cast<size_t>(w) * h, 0.f);
  for (int y = 0; y < h; ++y)
    for (int x = 0; x < w; ++x) {
      int n = 0;
      for (int j = 0; j < by; ++j)
        for (int i = 0; i < bx; ++i) n += open[static_cast<size_t>(y * f + j) * width + (x * f + i)];
      out[static_cast<size_t>(y) * w + x] = static_cast<float>(n) / static_cast<float>(bx * by);
    }
}

}  // namespace ag2gs
