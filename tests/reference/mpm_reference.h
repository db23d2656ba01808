// Double-precision reference of one MLS-MPM substep (host/physics/mpm.h,
// kernels/mpm.cl), written from the method's definition rather than from the
// device's structure: each particle's Kirchhoff stress after the return
// mapping (Eigen's SVD in double, the materials of host/physics/mpm.h), then
// particle-to-grid by scattering into a dense grid, the grid update (gravity,
// damping, walls, the ground with Coulomb friction), and grid-to-particle
// (velocity, APIC C, F, position). Every sum is in double; the particles'
// state is rounded to float between substeps, as the device stores it. The
// base cell is computed in float, as the kernel does, so that both pick the
// same 27 nodes.
#pragma once

#include <vector>

#include "host/physics/mpm.h"

namespace ag2gs::ref {

// Advances `p` by one substep of dt; forces: add each material's force.
void mpm_substep(MpmParticles& p, const MpmConfig& cfg, const std::vector<MpmMaterial>& mats, double dt, bool forces);

}  // namespace ag2gs::ref
