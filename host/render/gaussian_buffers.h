// A DeviceGaussians as kernel arguments: the six arrays in the order the
// kernels that read or write a whole set declare them (project_fwd reads
// them; expand_fwd and free_activate write them).
#pragma once

#include "host/device/kernel_call.h"
#include "host/render/renderer.h"

namespace ag2gs {

// means [N,3], scales [N,3], quats [N,4], opacities [N], sh [N,K,3] and
// features [N,3], N = g.n and K the coefficients of g.sh_degree.
inline KernelCall& gaussian_buffers(KernelCall& call, const DeviceGaussians& g) {
  const size_t n = g.n, f4 = sizeof(float), K = sh_coeffs_for_degree(g.sh_degree);
  return call.buffer("means", g.means, n * 3 * f4)
      .buffer("scales", g.scales, n * 3 * f4)
      .buffer("quats", g.quats, n * 4 * f4)
      .buffer("opacities", g.opacities, n * f4)
      .buffer("sh", g.sh, n * K * 3 * f4)
      .buffer("features", g.features, n * 3 * f4);
}

}  // namespace ag2gs
