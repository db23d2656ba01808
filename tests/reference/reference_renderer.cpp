// Double-precision reference rasterizer; semantics in docs/rasterizer.md.
// Every differentiable helper sits beside its vector-Jacobian product (v_<name>
// is dLoss/d<name>).
#include "tests/reference/reference_renderer.h"

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <string>

namespace ag2gs::ref {

using Eigen::Matrix2d;
using Eigen::Matrix3d;
using Eigen::Vector3d;
using Mat23 = Eigen::Matrix<double, 2, 3>;

namespace {

constexpr double kMinAlpha = 1.0 / 255.0;   // skip / cull threshold
constexpr double kMaxAlpha = 0.99;          // alpha clamp
constexpr double kMinTransmittance = 1e-4;  // early stop
constexpr double kMinQuatNorm2 = 1e-20;

// ---------------------------------------------------------------------------
// Input checks and conversion.

void check_size(const char* name, size_t got, size_t want) {
  if (got != want)
    throw std::invalid_argument(std::string("ag2gs::ref: array '") + name + "' has " + std::to_string(got) +
                                " values, expected " + std::to_string(want));
}

void check_sizes(const RefGaussians& g) {
  if (g.sh_degree < 0 || g.sh_degree > 3)
    throw std::invalid_argument("ag2gs::ref: sh_degree must be 0..3, got " + std::to_string(g.sh_degree));
  const size_t n = g.size();
  check_size("means", g.means.size(), 3 * n);
  check_size("scales", g.scales.size(), 3 * n);
  check_size("quats", g.quats.size(), 4 * n);
  check_size("sh", g.sh.size(), 3 * n * static_cast<size_t>(g.sh_coeffs()));
  check_size("features", g.features.size(), 3 * n);
}

void check_camera(const Camera& cam) {
  if (cam.width <= 0 || cam.height <= 0 || !(cam.fx > 0) || !(cam.fy > 0))
    throw std::invalid_argument("ag2gs::ref: camera needs width, height, fx, fy > 0");
}

// An upstream gradient image: empty means zero.
double grad_at(const std::vector<float>& g, size_t i) {
  return g.empty() ? 0.0 : g[i];
}

void check_grad_size(const char* name, const std::vector<float>& g, size_t want) {
  if (!g.empty()) check_size(name, g.size(), want);
}

bool all_finite(const std::vector<double>& a, size_t begin, size_t count) {
  for (size_t i = begin; i < begin + count; ++i)
    if (!std::isfinite(a[i])) return false;
  return true;
}

// Step 1: any non-finite input of Gaussian n (all SH coefficients, active or not).
bool gaussian_finite(const RefGaussians& g, size_t n) {
  const size_t k = static_cast<size_t>(g.sh_coeffs());
  return all_finite(g.means, 3 * n, 3) && all_finite(g.scales, 3 * n, 3) && all_finite(g.quats, 4 * n, 4) &&
         all_finite(g.opacities, n, 1) && all_finite(g.sh, 3 * k * n, 3 * k) && all_finite(g.features, 3 * n, 3);
}

// ---------------------------------------------------------------------------
// Normalisation: y = x / |x|.
//   dy/dx = (I - y y^T) / |x|  =>  v_x = (v_y - y (y . v_y)) / |x|.

Vector3d normalize_vjp(const Vector3d& x, const Vector3d& v_y) {
  const double len = x.norm();
  if (len == 0) return Vector3d::Zero();
  const Vector3d y = x / len;
  return (v_y - y * y.dot(v_y)) / len;
}

Eigen::Vector4d normalize4_vjp(const Eigen::Vector4d& x, const Eigen::Vector4d& v_y) {
  const double len = x.norm();
  const Eigen::Vector4d y = x / len;
  return (v_y - y * y.dot(v_y)) / len;
}

// ---------------------------------------------------------------------------
// Rotation matrix of a unit quaternion q = (w, x, y, z).

Matrix3d quat_to_rotmat(const Eigen::Vector4d& q) {
  const double w = q[0], x = q[1], y = q[2], z = q[3];
  Matrix3d R;
  R << 1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),  //
      2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),   //
      2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y);
  return R;
}

// v_q_i = sum_rc v_R(r,c) dR(r,c)/dq_i, entry by entry from quat_to_rotmat.
Eigen::Vector4d quat_to_rotmat_vjp(const Eigen::Vector4d& q, const Matrix3d& G) {
  const double w = q[0], x = q[1], y = q[2], z = q[3];
  Eigen::Vector4d v_q;
  v_q[0] = 2 * (-z * G(0, 1) + y * G(0, 2) + z * G(1, 0) - x * G(1, 2) - y * G(2, 0) + x * G(2, 1));
  v_q[1] = 2 * (y * G(0, 1) + z * G(0, 2) + y * G(1, 0) - 2 * x * G(1, 1) - w * G(1, 2) + z * G(2, 0) + w * G(2, 1) -
                2 * x * G(2, 2));
  v_q[2] = 2 * (-2 * y * G(0, 0) + x * G(0, 1) + w * G(0, 2) + x * G(1, 0) + z * G(1, 2) - w * G(2, 0) + z * G(2, 1) -
                2 * y * G(2, 2));
  v_q[3] = 2 * (-2 * z * G(0, 0) - w * G(0, 1) + x * G(0, 2) + w * G(1, 0) - 2 * z * G(1, 1) + y * G(1, 2) +
                x * G(2, 0) + y * G(2, 1));
  return v_q;
}

// ---------------------------------------------------------------------------
// 3D covariance: Sigma = M M^T with M = R_q diag(s).
//   dL = <v_Sigma, dM M^T + M dM^T> = <(v_Sigma + v_Sigma^T) M, dM>
//   v_M = (v_Sigma + v_Sigma^T) M;  v_R_q = v_M diag(s);  v_s_i = (R_q^T v_M)_ii.

Matrix3d scale_rot_to_cov3d(const Vector3d& s, const Matrix3d& Rq) {
  const Matrix3d M = Rq * s.asDiagonal();
  return M * M.transpose();
}

void scale_rot_to_cov3d_vjp(const Vector3d& s, const Matrix3d& Rq, const Matrix3d& v_Sigma, Vector3d& v_s,
                            Matrix3d& v_Rq) {
  const Matrix3d M = Rq * s.asDiagonal();
  const Matrix3d v_M = (v_Sigma + v_Sigma.transpose()) * M;
  v_Rq = v_M * s.asDiagonal();
  for (int i = 0; i < 3; ++i) v_s[i] = Rq.col(i).dot(v_M.col(i));
}

// ---------------------------------------------------------------------------
// Clamped projection Jacobian (step 5). With z = p.z and
//   tx = clamp(p.x/z, -lim_xn, lim_xp) z   (free: tx = p.x; clamped: tx = L z)
//   J = [[fx/z, 0, -fx tx/z^2], [0, fy/z, -fy ty/z^2]].

struct ClampLimits {
  double lim_xp, lim_xn, lim_yp, lim_yn;
};

ClampLimits clamp_limits(const Camera& cam) {
  const double tan_x = 0.5 * cam.width / cam.fx;
  const double tan_y = 0.5 * cam.height / cam.fy;
  return {(cam.width - cam.cx) / cam.fx + 0.3 * tan_x, cam.cx / cam.fx + 0.3 * tan_x,
          (cam.height - cam.cy) / cam.fy + 0.3 * tan_y, cam.cy / cam.fy + 0.3 * tan_y};
}

// Signed limit L of one axis: ratio > lim_p -> (+1, lim_p), < -lim_n -> (-1, -lim_n).
int clamp_state(double ratio, double lim_p, double lim_n, double& L) {
  if (ratio > lim_p) {
    L = lim_p;
    return 1;
  }
  if (ratio < -lim_n) {
    L = -lim_n;
    return -1;
  }
  L = 0;
  return 0;
}

Mat23 persp_jacobian(const Vector3d& p, const Camera& cam, const ClampLimits& lim, int& clamp_x, int& clamp_y) {
  const double z = p.z();
  double Lx, Ly;
  clamp_x = clamp_state(p.x() / z, lim.lim_xp, lim.lim_xn, Lx);
  clamp_y = clamp_state(p.y() / z, lim.lim_yp, lim.lim_yn, Ly);
  const double tx = clamp_x ? Lx * z : p.x();
  const double ty = clamp_y ? Ly * z : p.y();
  Mat23 J;
  J << cam.fx / z, 0, -cam.fx * tx / (z * z),  //
      0, cam.fy / z, -cam.fy * ty / (z * z);
  return J;
}

// v_p from v_J; the clamp states are those of the forward pass.
//   dJ00/dz = -fx/z^2,  dJ02/dtx = -fx/z^2,  dJ02/dz|tx = 2 fx tx/z^3,
//   then tx = p.x (v_px += v_tx) or tx = L z (v_z += L v_tx).
Vector3d persp_jacobian_vjp(const Vector3d& p, const Camera& cam, const ClampLimits& lim, const Mat23& v_J) {
  const double z = p.z(), z2 = z * z, z3 = z2 * z;
  double Lx, Ly;
  const int cx = clamp_state(p.x() / z, lim.lim_xp, lim.lim_xn, Lx);
  const int cy = clamp_state(p.y() / z, lim.lim_yp, lim.lim_yn, Ly);
  const double tx = cx ? Lx * z : p.x();
  const double ty = cy ? Ly * z : p.y();
  Vector3d v_p = Vector3d::Zero();
  v_p.z() += -cam.fx / z2 * v_J(0, 0) - cam.fy / z2 * v_J(1, 1);
  v_p.z() += 2 * cam.fx * tx / z3 * v_J(0, 2) + 2 * cam.fy * ty / z3 * v_J(1, 2);
  const double v_tx = -cam.fx / z2 * v_J(0, 2);
  const double v_ty = -cam.fy / z2 * v_J(1, 2);
  if (cx)
    v_p.z() += Lx * v_tx;
  else
    v_p.x() += v_tx;
  if (cy)
    v_p.z() += Ly * v_ty;
  else
    v_p.y() += v_ty;
  return v_p;
}

// ---------------------------------------------------------------------------
// 2D covariance: cov2d = J Sigma_c J^T + lowpass I (RenderSettings::lowpass, 0.3 px^2 by default).
// With V = [[v_a, v_b/2], [v_b/2, v_c]] (b appears twice in the matrix):
//   v_Sigma_c = J^T V J,  v_J = V J Sigma_c^T + V^T J Sigma_c = 2 V J Sigma_c.

Matrix2d project_cov(const Mat23& J, const Matrix3d& Sigma_c, double lowpass) {
  return J * Sigma_c * J.transpose() + lowpass * Matrix2d::Identity();
}

void project_cov_vjp(const Mat23& J, const Matrix3d& Sigma_c, const Matrix2d& V, Matrix3d& v_Sigma_c, Mat23& v_J) {
  v_Sigma_c = J.transpose() * V * J;
  v_J = (V + V.transpose()) * J * Sigma_c;
}

// Conic K = cov2d^{-1}:  dK = -K dcov K  =>  v_cov = -K v_K K (K symmetric).
// (v_A, v_B, v_C) -> symmetric V_K = [[v_A, v_B/2], [v_B/2, v_C]]; the result
// as a symmetric matrix V = [[v_a, v_b/2], [v_b/2, v_c]].
Matrix2d inverse_vjp(const Matrix2d& K, const Matrix2d& v_K) {
  return -K * v_K * K;
}

// ---------------------------------------------------------------------------
// Spherical harmonics, 3DGS constants and basis order. The basis is evaluated
// at a unit direction d = (x, y, z); db[k] = d basis_k / d d.

constexpr double C0 = 0.28209479177387814;
constexpr double C1 = 0.4886025119029199;
constexpr double C2[5] = {1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
                          0.5462742152960396};
constexpr double C3[7] = {-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
                          -0.4570457994644658, 1.445305721320277, -0.5900435899266435};

void sh_basis(int degree, const Vector3d& d, double b[16], Vector3d db[16]) {
  const double x = d.x(), y = d.y(), z = d.z();
  const double xx = x * x, yy = y * y, zz = z * z;
  b[0] = C0;
  db[0] = Vector3d::Zero();
  if (degree < 1) return;
  b[1] = -C1 * y;
  db[1] = Vector3d(0, -C1, 0);
  b[2] = C1 * z;
  db[2] = Vector3d(0, 0, C1);
  b[3] = -C1 * x;
  db[3] = Vector3d(-C1, 0, 0);
  if (degree < 2) return;
  b[4] = C2[0] * x * y;
  db[4] = C2[0] * Vector3d(y, x, 0);
  b[5] = C2[1] * y * z;
  db[5] = C2[1] * Vector3d(0, z, y);
  b[6] = C2[2] * (2 * zz - xx - yy);
  db[6] = C2[2] * Vector3d(-2 * x, -2 * y, 4 * z);
  b[7] = C2[3] * x * z;
  db[7] = C2[3] * Vector3d(z, 0, x);
  b[8] = C2[4] * (xx - yy);
  db[8] = C2[4] * Vector3d(2 * x, -2 * y, 0);
  if (degree < 3) return;
  b[9] = C3[0] * y * (3 * xx - yy);
  db[9] = C3[0] * Vector3d(6 * x * y, 3 * xx - 3 * yy, 0);
  b[10] = C3[1] * x * y * z;
  db[10] = C3[1] * Vector3d(y * z, x * z, x * y);
  b[11] = C3[2] * y * (4 * zz - xx - yy);
  db[11] = C3[2] * Vector3d(-2 * x * y, 4 * zz - xx - 3 * yy, 8 * y * z);
  b[12] = C3[3] * z * (2 * zz - 3 * xx - 3 * yy);
  db[12] = C3[3] * Vector3d(-6 * x * z, -6 * y * z, 6 * zz - 3 * xx - 3 * yy);
  b[13] = C3[4] * x * (4 * zz - xx - yy);
  db[13] = C3[4] * Vector3d(4 * zz - 3 * xx - yy, -2 * x * y, 8 * x * z);
  b[14] = C3[5] * z * (xx - yy);
  db[14] = C3[5] * Vector3d(2 * x * z, -2 * y * z, xx - yy);
  b[15] = C3[6] * x * (xx - 3 * yy);
  db[15] = C3[6] * Vector3d(3 * xx - 3 * yy, -6 * x * y, 0);
}

// Unit view direction of Gaussian n: d = (mean - campos)/|mean - campos|, 0 -> 0.
Vector3d view_dir(const Vector3d& mean, const Vector3d& campos) {
  const Vector3d r = mean - campos;
  const double len = r.norm();
  return len > 0 ? Vector3d(r / len) : Vector3d::Zero();
}

// rgb_c = sum_k basis_k(d) sh[k][c] + 0.5 before the clamp at 0.
Vector3d sh_to_color(const RefGaussians& g, size_t n, int degree, const Vector3d& d) {
  double b[16];
  Vector3d db[16];
  sh_basis(degree, d, b, db);
  const size_t K = static_cast<size_t>(g.sh_coeffs());
  Vector3d rgb = Vector3d::Constant(0.5);
  for (int k = 0; k < sh_coeffs_for_degree(degree); ++k)
    for (int c = 0; c < 3; ++c) rgb[c] += b[k] * g.sh[(n * K + k) * 3 + c];
  return rgb;
}

// v_sh[k][c] = basis_k v_rgb_c;  v_d = sum_k db_k sum_c sh[k][c] v_rgb_c.
Vector3d sh_to_color_vjp(const RefGaussians& g, size_t n, int degree, const Vector3d& d, const Vector3d& v_rgb,
                         std::vector<double>& v_sh) {
  double b[16];
  Vector3d db[16];
  sh_basis(degree, d, b, db);
  const size_t K = static_cast<size_t>(g.sh_coeffs());
  Vector3d v_d = Vector3d::Zero();
  for (int k = 0; k < sh_coeffs_for_degree(degree); ++k) {
    double v_bk = 0;
    for (int c = 0; c < 3; ++c) {
      v_sh[(n * K + k) * 3 + c] += b[k] * v_rgb[c];
      v_bk += g.sh[(n * K + k) * 3 + c] * v_rgb[c];
    }
    v_d += db[k] * v_bk;
  }
  return v_d;
}

// ---------------------------------------------------------------------------
// Distortion depth mapping m(z) = f/(f - n) (1 - n/z);  dm/dz = f/(f - n) n/z^2.

struct DepthMap {
  double n, f;
  double m(double z) const { return f / (f - n) * (1 - n / z); }
  double dm_dz(double z) const { return f / (f - n) * n / (z * z); }
};

DepthMap depth_map(const RenderSettings& s) {
  return {double(s.dist_near), double(s.dist_far)};
}

// ---------------------------------------------------------------------------
// Per-Gaussian quantities shared by the projection and its backward.

struct Geometry {
  Vector3d mean, p, scale;
  Eigen::Vector4d quat, q;  // input and normalised
  Matrix3d Rq, Sigma_c;
  Mat23 J;
  Matrix2d cov, conic;
};

Geometry geometry(const RefGaussians& g, size_t n, const Camera& cam, const ClampLimits& lim, double lowpass,
                  int& clamp_x, int& clamp_y) {
  Geometry G;
  G.mean = Vector3d(g.means[3 * n], g.means[3 * n + 1], g.means[3 * n + 2]);
  G.scale = Vector3d(g.scales[3 * n], g.scales[3 * n + 1], g.scales[3 * n + 2]);
  G.quat = Eigen::Vector4d(g.quats[4 * n], g.quats[4 * n + 1], g.quats[4 * n + 2], g.quats[4 * n + 3]);
  G.p = cam.R * G.mean + cam.t;
  G.q = G.quat / G.quat.norm();
  G.Rq = quat_to_rotmat(G.q);
  G.Sigma_c = cam.R * scale_rot_to_cov3d(G.scale, G.Rq) * cam.R.transpose();
  G.J = persp_jacobian(G.p, cam, lim, clamp_x, clamp_y);
  G.cov = project_cov(G.J, G.Sigma_c, lowpass);
  return G;
}

// Fates of a Gaussian at a pixel, for discrete_decisions.
enum Fate { kSkipSigma = 0, kSkipAlpha = 1, kBlended = 2, kBlendedClamped = 3, kStop = 4 };

// One blended Gaussian at a pixel.
struct BlendStep {
  int id;
  double alpha, T;  // T before this Gaussian
  double G;         // exp(-sigma)
  double dx, dy;    // u - px, v - py
  double m;         // distortion depth
  bool alpha_clamped;
};

struct PixelResult {
  double rgb[3] = {0, 0, 0}, feat[3] = {0, 0, 0}, depth = 0;
  double T = 1;
  double A = 0, mu = 0, M2 = 0;  // Welford state of the distortion
  int n = 0;
};

// Front-to-back blending of one pixel (docs/rasterizer.md, Blending).
PixelResult blend_pixel(const std::vector<int>& order, const std::vector<RefProjected>& P, double px, double py,
                        const DepthMap& dmap, const double bg[3], std::vector<BlendStep>* steps,
                        std::vector<int>* fates) {
  PixelResult r;
  for (int id : order) {
    const RefProjected& g = P[id];
    const double dx = g.u - px, dy = g.v - py;
    // sigma = 0.5 (A dx^2 + C dy^2) + B dx dy
    const double sigma = 0.5 * (g.conic[0] * dx * dx + g.conic[2] * dy * dy) + g.conic[1] * dx * dy;
    if (sigma < 0) {
      if (fates) fates->push_back(id * 8 + kSkipSigma);
      continue;
    }
    const double G = std::exp(-sigma);
    const double raw = g.opacity * G;
    const bool clamped = raw > kMaxAlpha;
    const double alpha = clamped ? kMaxAlpha : raw;
    if (alpha < kMinAlpha) {
      if (fates) fates->push_back(id * 8 + kSkipAlpha);
      continue;
    }
    const double T_next = r.T * (1 - alpha);
    if (T_next < kMinTransmittance) {
      if (fates) fates->push_back(id * 8 + kStop);
      break;
    }
    if (fates) fates->push_back(id * 8 + (clamped ? kBlendedClamped : kBlended));
    const double w = alpha * r.T;
    for (int c = 0; c < 3; ++c) {
      r.rgb[c] += w * g.rgb[c];
      r.feat[c] += w * g.feature[c];
    }
    r.depth += w * g.z;
    // Welford: A' = A + w; mu' = mu + (w/A')(m - mu); M2 += w (m - mu)(m - mu').
    const double m = dmap.m(g.z);
    const double A_new = r.A + w;
    const double mu_new = r.mu + (w / A_new) * (m - r.mu);
    r.M2 += w * (m - r.mu) * (m - mu_new);
    r.A = A_new;
    r.mu = mu_new;
    if (steps) steps->push_back({id, alpha, r.T, G, dx, dy, m, clamped});
    r.T = T_next;
    ++r.n;
  }
  for (int c = 0; c < 3; ++c) r.rgb[c] += r.T * bg[c];
  return r;
}

// Visible Gaussians sorted by (z, index).
std::vector<int> depth_order(const std::vector<RefProjected>& P) {
  std::vector<int> order;
  for (size_t i = 0; i < P.size(); ++i)
    if (P[i].visible) order.push_back(static_cast<int>(i));
  std::stable_sort(order.begin(), order.end(),
                   [&](int a, int b) { return P[a].z < P[b].z || (P[a].z == P[b].z && a < b); });
  return order;
}

// The Gaussians of `order` whose alpha >= 1/255 box reaches the pixel row at
// py. Those outside have sigma > k/2 there, i.e. alpha < 1/255, and would be
// skipped anyway: filtering by row only saves time.
std::vector<int> row_order(const std::vector<int>& order, const std::vector<RefProjected>& P, double py) {
  std::vector<int> row;
  for (int id : order)
    if (std::abs(P[id].v - py) <= P[id].ry) row.push_back(id);
  return row;
}

}  // namespace

void sh_values(int degree, const Eigen::Vector3d& d, double b[16]) {
  Vector3d db[16];
  sh_basis(degree, d, b, db);
}

// ---------------------------------------------------------------------------

RefGaussians to_double(const GaussianSet& set) {
  RefGaussians g;
  g.sh_degree = set.sh_degree;
  g.means.assign(set.means.begin(), set.means.end());
  g.scales.assign(set.scales.begin(), set.scales.end());
  g.quats.assign(set.quats.begin(), set.quats.end());
  g.opacities.assign(set.opacities.begin(), set.opacities.end());
  g.sh.assign(set.sh.begin(), set.sh.end());
  g.features.assign(set.features.begin(), set.features.end());
  return g;
}

int active_sh_degree(int set_degree, const RenderSettings& settings) {
  return settings.sh_degree < 0 ? set_degree : std::min(settings.sh_degree, set_degree);
}

std::vector<RefProjected> project(const RefGaussians& g, const Camera& cam, const RenderSettings& settings) {
  check_sizes(g);
  check_camera(cam);
  const ClampLimits lim = clamp_limits(cam);
  const int degree = active_sh_degree(g.sh_degree, settings);
  const Vector3d campos = cam.center();
  std::vector<RefProjected> out(g.size());
  for (size_t n = 0; n < g.size(); ++n) {
    RefProjected& pr = out[n];
    // 1. non-finite inputs
    if (!gaussian_finite(g, n)) continue;
    // 2. near plane
    const Vector3d mean(g.means[3 * n], g.means[3 * n + 1], g.means[3 * n + 2]);
    const Vector3d p = cam.R * mean + cam.t;
    if (!(p.z() > double(settings.near_plane))) continue;
    // 3. degenerate quaternion
    const Eigen::Vector4d quat(g.quats[4 * n], g.quats[4 * n + 1], g.quats[4 * n + 2], g.quats[4 * n + 3]);
    if (!(quat.squaredNorm() >= kMinQuatNorm2)) continue;
    // 4-6. covariances, clamped Jacobian, conic
    int clamp_x = 0, clamp_y = 0;
    const Geometry G = geometry(g, n, cam, lim, double(settings.lowpass), clamp_x, clamp_y);
    const double a = G.cov(0, 0), b = G.cov(0, 1), c = G.cov(1, 1);
    const double det = a * c - b * b;
    if (!(det > 0) || !std::isfinite(det)) continue;
    // 7. mean2d (unclamped)
    const double u = cam.fx * p.x() / p.z() + cam.cx;
    const double v = cam.fy * p.y() / p.z() + cam.cy;
    // 8. opacity
    const double o = g.opacities[n];
    if (!(o >= kMinAlpha)) continue;
    // 9. extent of alpha >= 1/255: k = 2 ln(255 o), rx = sqrt(k a), ry = sqrt(k c).
    // Culled when no pixel centre (i + 0.5, j + 0.5) of the image lies in the box
    // [u - rx, u + rx] x [v - ry, v + ry] (no widening, see the header).
    const double k = 2 * std::log(255 * o);
    const double rx = std::sqrt(k * a), ry = std::sqrt(k * c);
    const double x0 = std::max(0.0, std::ceil(u - rx - 0.5));
    const double x1 = std::min(cam.width - 1.0, std::floor(u + rx - 0.5));
    const double y0 = std::max(0.0, std::ceil(v - ry - 0.5));
    const double y1 = std::min(cam.height - 1.0, std::floor(v + ry - 0.5));
    if (!(x0 <= x1 && y0 <= y1)) continue;
    // 10. colour
    const Vector3d d = view_dir(mean, campos);
    const Vector3d rgb = sh_to_color(g, n, degree, d);

    pr.visible = true;
    pr.u = u;
    pr.v = v;
    pr.cov2d[0] = a;
    pr.cov2d[1] = b;
    pr.cov2d[2] = c;
    pr.conic[0] = c / det;
    pr.conic[1] = -b / det;
    pr.conic[2] = a / det;
    pr.z = p.z();  // 11.
    pr.opacity = o;
    for (int ch = 0; ch < 3; ++ch) {
      pr.rgb_clamped[ch] = rgb[ch] < 0;
      pr.rgb[ch] = std::max(rgb[ch], 0.0);
      pr.feature[ch] = g.features[3 * n + ch];
    }
    pr.rx = rx;
    pr.ry = ry;
    pr.radius = static_cast<int>(std::ceil(std::max(rx, ry)));
    pr.clamp_x = clamp_x;
    pr.clamp_y = clamp_y;
  }
  return out;
}

std::vector<RefProjected> project(const GaussianSet& set, const Camera& camera, const RenderSettings& settings) {
  return project(to_double(set), camera, settings);
}

// Images of w x h pixels, all zero (radii left empty).
static RefImages zero_images(int w, int h) {
  const size_t npix = static_cast<size_t>(w) * h;
  RefImages img;
  img.width = w;
  img.height = h;
  img.rgb.assign(3 * npix, 0);
  img.feature.assign(3 * npix, 0);
  img.depth.assign(npix, 0);
  img.alpha.assign(npix, 0);
  img.distortion.assign(npix, 0);
  img.n_contrib.assign(npix, 0);
  return img;
}

// Writes one blended pixel's outputs at index k of the images.
static void store_pixel(RefImages& img, size_t k, const PixelResult& r) {
  for (int c = 0; c < 3; ++c) {
    img.rgb[3 * k + c] = r.rgb[c];
    img.feature[3 * k + c] = r.feat[c];
  }
  img.depth[k] = r.depth;
  img.alpha[k] = 1 - r.T;
  img.distortion[k] = r.A * r.M2;
  img.n_contrib[k] = r.n;
}

RefImages blend(const std::vector<RefProjected>& P, const Camera& cam, const RenderSettings& settings) {
  check_camera(cam);
  const int W = cam.width, H = cam.height;
  RefImages img = zero_images(W, H);
  img.radii.resize(P.size());
  for (size_t i = 0; i < P.size(); ++i) img.radii[i] = P[i].visible ? P[i].radius : 0;

  const std::vector<int> order = depth_order(P);
  const DepthMap dmap = depth_map(settings);
  const double bg[3] = {settings.background[0], settings.background[1], settings.background[2]};
  for (int j = 0; j < H; ++j) {
    const std::vector<int> row = row_order(order, P, j + 0.5);
    for (int i = 0; i < W; ++i) {
      const size_t pix = static_cast<size_t>(j) * W + i;
      store_pixel(img, pix, blend_pixel(row, P, i + 0.5, j + 0.5, dmap, bg, nullptr, nullptr));
    }
  }
  return img;
}

RefImages render(const RefGaussians& set, const Camera& camera, const RenderSettings& settings) {
  return blend(project(set, camera, settings), camera, settings);
}

RefImages render(const GaussianSet& set, const Camera& camera, const RenderSettings& settings) {
  return render(to_double(set), camera, settings);
}

RefImages render_pixels(const GaussianSet& set, const Camera& cam, const RenderSettings& settings,
                        const std::vector<int>& pixels) {
  check_camera(cam);
  const std::vector<RefProjected> P = project(to_double(set), cam, settings);
  const std::vector<int> order = depth_order(P);
  const DepthMap dmap = depth_map(settings);
  const double bg[3] = {settings.background[0], settings.background[1], settings.background[2]};
  const size_t n = pixels.size();
  RefImages img = zero_images(static_cast<int>(n), 1);
  // Group the samples by row so each row's Gaussian list is built once.
  std::vector<size_t> idx(n);
  for (size_t k = 0; k < n; ++k) idx[k] = k;
  std::sort(idx.begin(), idx.end(), [&](size_t a, size_t b) { return pixels[a] < pixels[b]; });
  int current_row = -1;
  std::vector<int> row;
  for (size_t k : idx) {
    const int p = pixels[k];
    if (p < 0 || p >= cam.width * cam.height) throw std::invalid_argument("render_pixels: pixel index out of range");
    const int j = p / cam.width, i = p % cam.width;
    if (j != current_row) {
      row = row_order(order, P, j + 0.5);
      current_row = j;
    }
    store_pixel(img, k, blend_pixel(row, P, i + 0.5, j + 0.5, dmap, bg, nullptr, nullptr));
  }
  return img;
}

std::vector<RefProjectedGrads> blend_backward(const std::vector<RefProjected>& P, const Camera& cam,
                                              const RenderSettings& settings, const OutputGrads& grads) {
  check_camera(cam);
  const int W = cam.width, H = cam.height;
  const size_t npix = static_cast<size_t>(W) * H;
  check_grad_size("grads.rgb", grads.rgb, 3 * npix);
  check_grad_size("grads.feature", grads.feature, 3 * npix);
  check_grad_size("grads.depth", grads.depth, npix);
  check_grad_size("grads.alpha", grads.alpha, npix);
  check_grad_size("grads.distortion", grads.distortion, npix);

  std::vector<RefProjectedGrads> out(P.size());
  const std::vector<int> order = depth_order(P);
  const DepthMap dmap = depth_map(settings);
  const double bg[3] = {settings.background[0], settings.background[1], settings.background[2]};
  std::vector<BlendStep> steps;
  for (int j = 0; j < H; ++j) {
    const std::vector<int> row = row_order(order, P, j + 0.5);
    for (int i = 0; i < W; ++i) {
      const size_t pix = static_cast<size_t>(j) * W + i;
      steps.clear();
      const PixelResult r = blend_pixel(row, P, i + 0.5, j + 0.5, dmap, bg, &steps, nullptr);
      double v_rgb[3], v_feat[3];
      for (int c = 0; c < 3; ++c) {
        v_rgb[c] = grad_at(grads.rgb, 3 * pix + c);
        v_feat[c] = grad_at(grads.feature, 3 * pix + c);
      }
      const double v_depth = grad_at(grads.depth, pix);
      const double v_alpha_out = grad_at(grads.alpha, pix);
      const double v_dist = grad_at(grads.distortion, pix);

      // Totals of the forward pass; O_rgb includes T_final * background.
      const double A_T = r.A, mu_T = r.mu, M2_T = r.M2, T_final = r.T;
      // Prefix sums including the current Gaussian j.
      double P_rgb[3] = {0, 0, 0}, P_feat[3] = {0, 0, 0}, P_depth = 0, A_j = 0, Q_j = 0;
      for (const BlendStep& s : steps) {
        const RefProjected& g = P[s.id];
        RefProjectedGrads& vg = out[s.id];
        const double w = s.alpha * s.T;
        const double one_minus_alpha = 1 - s.alpha;
        for (int c = 0; c < 3; ++c) {
          P_rgb[c] += w * g.rgb[c];
          P_feat[c] += w * g.feature[c];
        }
        P_depth += w * g.z;
        A_j += w;
        Q_j += w * (s.m - mu_T) * (s.m - mu_T);

        // dO_c/dalpha_j = T_j c_j - (O_c - P_c,j)/(1 - alpha_j)
        double v_alpha = 0;
        for (int c = 0; c < 3; ++c) {
          v_alpha += v_rgb[c] * (s.T * g.rgb[c] - (r.rgb[c] - P_rgb[c]) / one_minus_alpha);
          v_alpha += v_feat[c] * (s.T * g.feature[c] - (r.feat[c] - P_feat[c]) / one_minus_alpha);
        }
        v_alpha += v_depth * (s.T * g.z - (r.depth - P_depth) / one_minus_alpha);
        // d(1 - T_final)/dalpha_j = T_final/(1 - alpha_j)
        v_alpha += v_alpha_out * T_final / one_minus_alpha;
        // Distortion D = A_T M2_T:
        //   e_j = dD/dw_j = M2_T + A_T (m_j - mu_T)^2
        //   S_j = sum_{k>j} w_k e_k = M2_T (A_T - A_j) + A_T (M2_T - Q_j)
        //   dD/dalpha_j = T_j e_j - S_j/(1 - alpha_j),  dD/dm_j = 2 w_j A_T (m_j - mu_T)
        const double e = M2_T + A_T * (s.m - mu_T) * (s.m - mu_T);
        const double S = M2_T * (A_T - A_j) + A_T * (M2_T - Q_j);
        v_alpha += v_dist * (s.T * e - S / one_minus_alpha);
        const double v_m = v_dist * 2 * w * A_T * (s.m - mu_T);

        // Direct dependencies of the weighted sums on colour, feature and z.
        for (int c = 0; c < 3; ++c) {
          vg.rgb[c] += v_rgb[c] * w;
          vg.feature[c] += v_feat[c] * w;
        }
        vg.z += v_depth * w + v_m * dmap.dm_dz(g.z);

        // alpha = o exp(-sigma): v_o = v_alpha G, v_sigma = -v_alpha alpha (0 when clamped).
        if (s.alpha_clamped) continue;
        vg.opacity += v_alpha * s.G;
        const double v_sigma = -v_alpha * s.alpha;
        // sigma = 0.5 (A dx^2 + C dy^2) + B dx dy, dx = u - px, dy = v - py.
        vg.conic[0] += v_sigma * 0.5 * s.dx * s.dx;
        vg.conic[1] += v_sigma * s.dx * s.dy;
        vg.conic[2] += v_sigma * 0.5 * s.dy * s.dy;
        vg.u += v_sigma * (g.conic[0] * s.dx + g.conic[1] * s.dy);
        vg.v += v_sigma * (g.conic[2] * s.dy + g.conic[1] * s.dx);
      }
    }
  }
  return out;
}

RefGrads render_backward(const RefGaussians& g, const Camera& cam, const RenderSettings& settings,
                         const OutputGrads& grads) {
  const std::vector<RefProjected> P = project(g, cam, settings);
  const std::vector<RefProjectedGrads> vP = blend_backward(P, cam, settings, grads);

  const size_t N = g.size();
  const size_t K = static_cast<size_t>(g.sh_coeffs());
  RefGrads out;
  out.means.assign(3 * N, 0);
  out.scales.assign(3 * N, 0);
  out.quats.assign(4 * N, 0);
  out.opacities.assign(N, 0);
  out.sh.assign(3 * K * N, 0);
  out.features.assign(3 * N, 0);
  out.means2d.assign(2 * N, 0);

  const ClampLimits lim = clamp_limits(cam);
  const int degree = active_sh_degree(g.sh_degree, settings);
  const Vector3d campos = cam.center();
  for (size_t n = 0; n < N; ++n) {
    if (!P[n].visible) continue;
    const RefProjected& pr = P[n];
    const RefProjectedGrads& vp = vP[n];
    int clamp_x, clamp_y;
    const Geometry G = geometry(g, n, cam, lim, double(settings.lowpass), clamp_x, clamp_y);
    const double z = G.p.z();

    out.opacities[n] = vp.opacity;
    for (int c = 0; c < 3; ++c) out.features[3 * n + c] = vp.feature[c];
    out.means2d[2 * n] = vp.u;
    out.means2d[2 * n + 1] = vp.v;

    // Colour: rgb = max(SH(d) + 0.5, 0), d = normalize(mean - campos).
    Vector3d v_rgb(vp.rgb[0], vp.rgb[1], vp.rgb[2]);
    for (int c = 0; c < 3; ++c)
      if (pr.rgb_clamped[c]) v_rgb[c] = 0;
    const Vector3d dir = view_dir(G.mean, campos);
    const Vector3d v_dir = sh_to_color_vjp(g, n, degree, dir, v_rgb, out.sh);
    Vector3d v_mean = normalize_vjp(G.mean - campos, v_dir);

    // Conic -> cov2d -> (J, Sigma_c).
    Matrix2d v_conic;
    v_conic << vp.conic[0], 0.5 * vp.conic[1], 0.5 * vp.conic[1], vp.conic[2];
    const Matrix2d conic = G.cov.inverse();
    const Matrix2d v_cov = inverse_vjp(conic, v_conic);
    const Matrix2d V = 0.5 * (v_cov + v_cov.transpose());
    Matrix3d v_Sigma_c;
    Mat23 v_J;
    project_cov_vjp(G.J, G.Sigma_c, V, v_Sigma_c, v_J);

    // p: through J, through (u, v) = (fx x/z + cx, fy y/z + cy) and z itself.
    Vector3d v_p = persp_jacobian_vjp(G.p, cam, lim, v_J);
    v_p.x() += cam.fx / z * vp.u;
    v_p.y() += cam.fy / z * vp.v;
    v_p.z() += -cam.fx * G.p.x() / (z * z) * vp.u - cam.fy * G.p.y() / (z * z) * vp.v;
    v_p.z() += vp.z;
    // p = R mean + t
    v_mean += cam.R.transpose() * v_p;
    for (int c = 0; c < 3; ++c) out.means[3 * n + c] = v_mean[c];

    // Sigma_c = R Sigma R^T  =>  v_Sigma = R^T v_Sigma_c R.
    const Matrix3d v_Sigma = cam.R.transpose() * v_Sigma_c * cam.R;
    Vector3d v_scale;
    Matrix3d v_Rq;
    scale_rot_to_cov3d_vjp(G.scale, G.Rq, v_Sigma, v_scale, v_Rq);
    for (int c = 0; c < 3; ++c) out.scales[3 * n + c] = v_scale[c];
    const Eigen::Vector4d v_q = quat_to_rotmat_vjp(G.q, v_Rq);
    const Eigen::Vector4d v_quat = normalize4_vjp(G.quat, v_q);
    for (int c = 0; c < 4; ++c) out.quats[4 * n + c] = v_quat[c];
  }
  return out;
}

RefGrads render_backward(const GaussianSet& set, const Camera& camera, const RenderSettings& settings,
                         const OutputGrads& grads) {
  return render_backward(to_double(set), camera, settings, grads);
}

std::vector<int> discrete_decisions(const std::vector<RefProjected>& P, const Camera& cam,
                                    const RenderSettings& settings) {
  check_camera(cam);
  const std::vector<int> order = depth_order(P);
  std::vector<int> code = order;
  code.push_back(-1);
  const DepthMap dmap = depth_map(settings);
  const double bg[3] = {0, 0, 0};
  for (int j = 0; j < cam.height; ++j)
    for (int i = 0; i < cam.width; ++i) {
      blend_pixel(order, P, i + 0.5, j + 0.5, dmap, bg, nullptr, &code);
      code.push_back(-1);
    }
  return code;
}

std::vector<int> discrete_decisions(const RefGaussians& g, const Camera& cam, const RenderSettings& settings) {
  const std::vector<RefProjected> P = project(g, cam, settings);
  std::vector<int> code;
  for (const RefProjected& p : P) {
    code.push_back(p.visible);
    code.push_back(p.clamp_x);
    code.push_back(p.clamp_y);
    code.push_back(p.rgb_clamped[0] + 2 * p.rgb_clamped[1] + 4 * p.rgb_clamped[2]);
  }
  const std::vector<int> blending = discrete_decisions(P, cam, settings);
  code.insert(code.end(), blending.begin(), blending.end());
  return code;
}

}  // namespace ag2gs::ref
