// Plain-loop reference of the anchor graph: O(N^2) from the definition.
#include "tests/reference/anchor_graph_reference.h"

#include <Eigen/Core>
#include <cmath>

namespace ag2gs::ref {

std::vector<std::vector<int>> anchor_graph_rows_reference(const AnchorModel& m, int scale) {
  const size_t A = m.size();
  std::vector<Eigen::Vector3i> hood(A);
  for (size_t i = 0; i < A; ++i) {
    const Eigen::Vector3i cell(m.cell()[3 * i], m.cell()[3 * i + 1], m.cell()[3 * i + 2]);
    const Eigen::Vector3d t = (m.grid().centre(m.layer()[i], cell) - m.grid().origin) / (scale * m.grid().top_voxel);
    hood[i] = Eigen::Vector3i(static_cast<int>(std::floor(t.x())), static_cast<int>(std::floor(t.y())),
                              static_cast<int>(std::floor(t.z())));
  }
  std::vector<std::vector<int>> rows(A);
  for (size_t i = 0; i < A; ++i)
    for (size_t j = 0; j < A; ++j)
      if (i != j && (hood[i] - hood[j]).cwiseAbs().maxCoeff() <= 1) rows[i].push_back(static_cast<int>(j));
  return rows;
}

}  // namespace ag2gs::ref
