// nearest_squared_distances against a brute-force double loop: random points,
// points on a plane across x (the sweep then runs along y or z), duplicates,
// non-finite points and a set too small for k.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <random>
#include <vector>

#include "host/core/nearest.h"
#include "tests/reference/nearest_reference.h"

namespace ag2gs {
namespace {

TEST(Nearest, EqualsBruteForce) {
  std::mt19937 rng(3);
  std::uniform_real_distribution<double> u(-1, 1);
  std::vector<Eigen::Vector3d> p;
  for (int i = 0; i < 400; ++i) p.emplace_back(u(rng), 3 * u(rng), 0.5 * u(rng));
  for (int i = 0; i < 300; ++i) p.emplace_back(2.0, u(rng), u(rng));  // a plane across x
  p.push_back(p[5]);                                                    // a duplicate: distance 0
  p.emplace_back(NAN, 0, 0);
  for (int k : {1, 3})
    EXPECT_EQ(nearest_squared_distances(p, k), ref::nearest_squared_distances_reference(p, k)) << "k " << k;
  // Along one axis only (a plane across the other two).
  std::vector<Eigen::Vector3d> line;
  for (int i = 0; i < 200; ++i) line.emplace_back(0, 0, u(rng));
  EXPECT_EQ(nearest_squared_distances(line, 2), ref::nearest_squared_distances_reference(line, 2));
  // Fewer points than k: infinity where there is no k-th neighbour.
  const std::vector<double> two = nearest_squared_distances({Eigen::Vector3d(0, 0, 0), Eigen::Vector3d(0, 3, 4)}, 2);
  EXPECT_EQ(two[0], 25.0);
  EXPECT_TRUE(std::isinf(two[1]));
  EXPECT_THROW(nearest_squared_distances(line, 0), std::invalid_argument);
}

}  // namespace
}  // namespace ag2gs
