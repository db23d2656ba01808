#include "host/scene/scene_up.h"

#include <Eigen/Eigenvalues>
#include <algorithm>
#include <cmath>
#include <sstream>
#include <stdexcept>

#include "host/core/counter_rng.h"
#include "host/core/quantile.h"

namespace ag2gs {

namespace {

constexpr int kPlaneTrials = 512;
constexpr double kPlaneTolerance = 0.01;   // of the points' spread
constexpr double kMinPlaneShare = 0.10;    // of the points
constexpr double kAxisAlignment = 0.7071;  // cos 45 degrees

// The least-squares plane of `points` (the smallest principal axis).
Plane fit_plane(const std::vector<Eigen::Vector3d>& points) {
  Eigen::Vector3d mean = Eigen::Vector3d::Zero();
  for (const Eigen::Vector3d& p : points) mean += p;
  mean /= static_cast<double>(points.size());
  Eigen::Matrix3d cov = Eigen::Matrix3d::Zero();
  for (const Eigen::Vector3d& p : points) cov += (p - mean) * (p - mean).transpose();
  Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> eig(cov);
  Plane plane;
  plane.normal = eig.eigenvectors().col(0).normalized();
  plane.offset = plane.normal.dot(mean);
  return plane;
}

size_t count_within(const std::vector<Eigen::Vector3d>& points, const Plane& plane, double tolerance) {
  size_t n = 0;
  for (const Eigen::Vector3d& p : points) n += std::abs(plane.height(p)) < tolerance;
  return n;
}

}  // namespace

std::optional<Plane> main_plane(const std::vector<Eigen::Vector3d>& points, uint64_t seed) {
  const size_t n = points.size();
  if (n < 30) return std::nullopt;
  // The spread: the 90th percentile of the distances from the median point.
  Eigen::Vector3d median;
  for (int a = 0; a < 3; ++a) {
    std::vector<double> v(n);
    for (size_t i = 0; i < n; ++i) v[i] = points[i](a);
    median(a) = quantile(std::move(v), 0.5);
  }
  std::vector<double> dist(n);
  for (size_t i = 0; i < n; ++i) dist[i] = (points[i] - median).norm();
  const double tolerance = kPlaneTolerance * quantile(std::move(dist), 0.9);
  if (!(tolerance > 0)) return std::nullopt;

  Plane best;
  for (int t = 0; t < kPlaneTrials; ++t) {
    size_t idx[3];
    for (int j = 0; j < 3; ++j)
      idx[j] = static_cast<size_t>(splitmix64(splitmix64(seed ^ 0x706c616e65ull) ^ (3 * t + j)) % n);
    const Eigen::Vector3d nrm = (points[idx[1]] - points[idx[0]]).cross(points[idx[2]] - points[idx[0]]);
    if (!(nrm.norm() > 0)) continue;
    Plane p;
    p.normal = nrm.normalized();
    p.offset = p.normal.dot(points[idx[0]]);
    p.inliers = count_within(points, p, tolerance);
    if (p.inliers > best.inliers) best = p;  // ties keep the earlier trial
  }
  if (best.inliers < 3) return std::nullopt;
  for (int r = 0; r < 2; ++r) {  // refit to the inliers
    std::vector<Eigen::Vector3d> in;
    for (const Eigen::Vector3d& p : points)
      if (std::abs(best.height(p)) < tolerance) in.push_back(p);
    if (in.size() < 3) break;
    Plane refit = fit_plane(in);
    if (refit.normal.dot(best.normal) < 0) {
      refit.normal = -refit.normal;
      refit.offset = -refit.offset;
    }
    refit.inliers = count_within(points, refit, tolerance);
    best = refit;
  }
  best.tolerance = tolerance;
  if (static_cast<double>(best.inliers) < kMinPlaneShare * static_cast<double>(n)) return std::nullopt;
  return best;
}

Eigen::Vector3d mean_camera_right(const std::vector<Camera>& cameras) {
  Eigen::Vector3d v = Eigen::Vector3d::Zero();
  for (const Camera& c : cameras) v += c.R.row(0).transpose();
  return cameras.empty() ? v : v / static_cast<double>(cameras.size());
}

Eigen::Vector3d mean_camera_up(const std::vector<Camera>& cameras) {
  Eigen::Vector3d v = Eigen::Vector3d::Zero();
  for (const Camera& c : cameras) v -= c.R.row(1).transpose();
  return cameras.empty() ? v : v / static_cast<double>(cameras.size());
}

Eigen::Vector3d up_from_cameras(const std::vector<Camera>& cameras) {
  Eigen::Vector3d up = Eigen::Vector3d::Zero();
  for (const Camera& c : cameras) up -= c.R.row(1).transpose();
  if (!(up.norm() > 1e-6 * std::max<size_t>(cameras.size(), 1)))
    throw std::runtime_error(
        "the cameras do not agree on an up direction and the SfM points show no floor; give "
        "--up X,Y,Z");
  return up.normalized();
}

std::string SceneUp::describe() const {
  std::ostringstream s;
  s.precision(3);
  s << "up (" << up(0) << ", " << up(1) << ", " << up(2) << ") from ";
  if (from_plane)
    s << "the main plane of the SfM points (" << plane->inliers << " points; the images' " << image_axis << " axis)";
  else
    s << "the cameras' image -y axes";
  return s.str();
}

SceneUp scene_up(const std::vector<Camera>& cameras, const std::vector<Eigen::Vector3d>& points) {
  SceneUp out;
  const Eigen::Vector3d right = mean_camera_right(cameras), cam_up = mean_camera_up(cameras);
  out.plane = main_plane(points);
  if (out.plane && !cameras.empty()) {
    const Eigen::Vector3d n = out.plane->normal;
    struct Axis {
      Eigen::Vector3d v;
      const char* name;
    };
    const Axis axes[] = {{cam_up, "-y"}, {-cam_up, "+y"}, {right, "+x"}, {-right, "-x"}};
    double best = kAxisAlignment;
    for (const Axis& a : axes) {
      const double len = a.v.norm();
      if (!(len > 1e-6)) continue;
      const double c = a.v.dot(n) / len;  // the signed alignment: the axis and the normal point the same way
      if (c > best) {
        best = c;
        out.image_axis = a.name;
      }
    }
    if (!out.image_axis.empty()) {
      // The side of the plane the cameras are on is up.
      std::vector<double> side;
      for (const Camera& c : cameras) side.push_back(out.plane->height(c.center()));
      if (quantile(std::move(side), 0.5) < 0) {
        out.plane->normal = -out.plane->normal;
        out.plane->offset = -out.plane->offset;
      }
      out.up = out.plane->normal;
      out.from_plane = true;
      // Name the image axis the final up lies along.
      for (const Axis& a : axes)
        if (a.v.norm() > 1e-6 && a.v.dot(out.up) / a.v.norm() > kAxisAlignment) out.image_axis = a.name;
      return out;
    }
  }
  out.up = up_from_cameras(cameras);
  return out;
}

}  // namespace ag2gs
