// Up and the main plane of a capture (host/scene/scene_up.h), and the ground
// under an object (apps/simulation/simulation.h support_height), on constructed
// point sets and camera rigs whose true up is known.
#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <cmath>
#include <random>
#include <vector>

#include "apps/simulation/simulation.h"
#include "host/scene/scene_up.h"
#include "tests/test_util.h"

namespace ag2gs {
namespace {

using Eigen::Vector3d;

// A table top at z = 1 (2x2, 600 points, +-1 mm), a wall at x = -1.5 behind
// it (300 points), an object on the table (200 points).
std::vector<Vector3d> table_scene(bool with_table = true) {
  std::mt19937 rng(5);
  std::uniform_real_distribution<double> u(-1, 1);
  std::vector<Vector3d> p;
  if (with_table)
    for (int i = 0; i < 600; ++i) p.emplace_back(u(rng), u(rng), 1.0 + 0.001 * u(rng));
  for (int i = 0; i < 300; ++i) p.emplace_back(-1.5 + 0.001 * u(rng), 1.5 * u(rng), 1.0 + 0.8 * (u(rng) + 1));
  for (int i = 0; i < 200; ++i) p.emplace_back(0.1 * u(rng), 0.1 * u(rng), 1.0 + 0.15 * (u(rng) + 1));
  return p;
}

// Cameras on an arc in front of the wall, 1 m above the table, looking at
// the object; each rolled about its own axis by `roll` radians (pi/2: the
// photos are stored sideways) plus a few degrees of hand-held wobble.
std::vector<Camera> arc_cameras(double roll) {
  std::vector<Camera> cams;
  for (int i = 0; i < 9; ++i) {
    const double a = -0.9 + 0.225 * i;
    Camera c = test::look_at(Vector3d(2.5 * std::cos(a), 2.5 * std::sin(a), 2.0), Vector3d(0, 0, 1.1), 64, 48, 60);
    const double r = roll + 0.06 * std::sin(3.0 * i);
    c.R = Eigen::AngleAxisd(r, Vector3d::UnitZ()).toRotationMatrix() * c.R;  // about the camera's optical axis
    c.t = -c.R * Vector3d(2.5 * std::cos(a), 2.5 * std::sin(a), 2.0);
    cams.push_back(c);
  }
  return cams;
}

double degrees_between(const Vector3d& a, const Vector3d& b) {
  return std::acos(std::clamp(a.normalized().dot(b.normalized()), -1.0, 1.0)) * 180 / M_PI;
}

TEST(SceneUp, MainPlaneIsTheTableTop) {
  const std::vector<Vector3d> points = table_scene();
  const std::optional<Plane> plane = main_plane(points);
  ASSERT_TRUE(plane);
  EXPECT_LT(
      std::min(degrees_between(plane->normal, Vector3d::UnitZ()), degrees_between(-plane->normal, Vector3d::UnitZ())),
      0.5);
  EXPECT_NEAR(std::abs(plane->offset), 1.0, 0.005);
  EXPECT_GE(plane->inliers, 590u);  // the table (the object's bottom points are near it too)
  EXPECT_LE(plane->inliers, 700u);
  // The same points give the same plane, bit for bit; other seeds the same plane within noise.
  const std::optional<Plane> again = main_plane(points);
  EXPECT_EQ(again->normal, plane->normal);
  EXPECT_EQ(again->offset, plane->offset);
  const std::optional<Plane> other = main_plane(points, 7);
  EXPECT_GT(std::abs(other->normal.dot(plane->normal)), 0.9999);
  // Too few points, or none on one plane: no plane.
  EXPECT_FALSE(main_plane(std::vector<Vector3d>(points.begin(), points.begin() + 20)));
  std::mt19937 rng(2);
  std::uniform_real_distribution<double> u(-1, 1);
  std::vector<Vector3d> cloud;
  for (int i = 0; i < 500; ++i) cloud.emplace_back(u(rng), u(rng), u(rng));
  EXPECT_FALSE(main_plane(cloud));
}

TEST(SceneUp, UprightAndSidewaysPhotosOfATableGiveTheTableNormal) {
  const std::vector<Vector3d> points = table_scene();
  for (double roll : {0.0, M_PI / 2, -M_PI / 2, M_PI}) {
    const std::vector<Camera> cams = arc_cameras(roll);
    const SceneUp su = scene_up(cams, points);
    EXPECT_TRUE(su.from_plane) << "roll " << roll;
    EXPECT_LT(degrees_between(su.up, Vector3d::UnitZ()), 0.5) << "roll " << roll << ": " << su.describe();
    EXPECT_EQ(su.plane->normal, su.up);
    EXPECT_NEAR(su.plane->offset, 1.0, 0.005);
  }
  EXPECT_EQ(scene_up(arc_cameras(0), points).image_axis, "-y");
  EXPECT_EQ(scene_up(arc_cameras(M_PI), points).image_axis, "+y");
  // Sideways: the cameras' -y mean lies along the table, 90 degrees off,
  // which is what up from the cameras alone gave.
  const std::vector<Camera> sideways = arc_cameras(M_PI / 2);
  EXPECT_GT(degrees_between(up_from_cameras(sideways), Vector3d::UnitZ()), 80);
  EXPECT_TRUE(scene_up(sideways, points).image_axis == "+x" || scene_up(sideways, points).image_axis == "-x");
}

TEST(SceneUp, AWallBehindTheObjectLeavesUpToTheCameras) {
  // Without the table the wall is the main plane; its normal lies along the
  // cameras' view, not along an image axis, so up comes from the cameras.
  const std::vector<Vector3d> points = table_scene(false);
  const std::vector<Camera> cams = arc_cameras(0);
  const SceneUp su = scene_up(cams, points);
  ASSERT_TRUE(su.plane);
  EXPECT_GT(std::abs(su.plane->normal.x()), 0.99);  // the wall
  EXPECT_FALSE(su.from_plane);
  EXPECT_EQ(su.up, up_from_cameras(cams));
  EXPECT_LT(degrees_between(su.up, Vector3d::UnitZ()), 25);  // the arc looks down at 22 degrees
  // No points at all: the cameras.
  EXPECT_EQ(scene_up(cams, {}).up, up_from_cameras(cams));
}

TEST(SceneUp, SupportHeightIsTheTableUnderAnObjectStandingOnIt) {
  std::vector<Vector3d> points = table_scene();
  const SceneUp su = scene_up(arc_cameras(M_PI / 2), points);
  ASSERT_TRUE(su.from_plane);
  // A cup: a cylinder's surface from the table (z = 1) to z = 1.4, with SfM
  // points on it down to the table. ground_below alone takes the points
  // under the cup's lowest tenth, which include the cup's own lower part.
  std::vector<Vector3d> cup;
  for (int i = 0; i < 400; ++i) {
    const double a = 0.1 * i, z = 1.0 + 0.4 * (i % 40) / 40.0;
    cup.emplace_back(0.1 * std::cos(a), 0.1 * std::sin(a), z);
  }
  std::vector<Vector3d> with_cup = points;
  with_cup.insert(with_cup.end(), cup.begin(), cup.end());
  EXPECT_NEAR(support_height(with_cup, cup, su.up, su.plane), 1.0, 0.003);
  // An object floating well above the plane: the points under it decide.
  std::vector<Vector3d> high = cup;
  for (Vector3d& p : high) p.z() += 1.0;
  EXPECT_NEAR(support_height(with_cup, high, su.up, su.plane), ground_below(with_cup, high, su.up), 1e-12);
  // No plane: ground_below.
  EXPECT_EQ(support_height(with_cup, cup, su.up, std::nullopt), ground_below(with_cup, cup, su.up));
}

}  // namespace
}  // namespace ag2gs
