// The learned sky as ordinary 3D Gaussians, so that a standard 3DGS file
// (point_cloud.ply) and any viewer that reads it show the picture ag2gs
// renders. The sky is a colour per viewing direction composited behind every
// Gaussian (host/render/sky.h); a viewer knows only Gaussians.
//
// The bake puts `count` isotropic Gaussians on a shell (radius R around
// `centre`) far behind everything else, at the points of a Fibonacci lattice
// (even spacing, deterministic). Each one carries the sky's whole SH function
// as its own colour: a Gaussian's colour is its SH at the direction from the
// camera to its mean, + 0.5, clamped at 0 (3DGS), so with
//   dc = sky_dc - 0.5 / C0,  rest = sky_rest
// it shows exactly sky(d) for the ray through its centre, from any camera
// (no parallax error, whatever R). Between centres the blend mixes the sky at
// neighbouring directions, a smoothing of about one lattice spacing, which a
// sky of SH degree <= 3 hardly feels. Each standard deviation is
// `sigma_spacing` lattice spacings and each opacity `opacity`, so that any
// ray from inside the shell crosses several of them and the shell is opaque
// (the renderer's transmittance falls below ~1e-3 behind it).
#pragma once

#include <Eigen/Core>
#include <vector>

#include "host/core/gaussians.h"

namespace ag2gs {

struct SkyBakeConfig {
  int count = 0;  // Gaussians on the shell; 0 = from the sky's degree (sky_bake_count)
  // Standard deviation in lattice spacings. Measured on a generated open-sky
  // scene (3,000 Gaussians): 0.65 -> 42.2 dB, 0.75 -> 47.6, 1.0 -> 41.9,
  // 1.5 -> 37.1 (wider ones blend the sky over more directions; at 0.55 the
  // shell has gaps and falls to 30.5).
  double sigma_spacing = 0.75;
  double opacity = 0.99;       // each Gaussian's opacity
  double radius_factor = 4.0;  // the shell's radius over the farthest Gaussian's or camera's distance
};

// The shell's centre and radius for a scene: centred on the cameras' mean
// centre, `radius_factor` times the largest distance from it to a camera or
// to any Gaussian of `objects` (at least 1, so an empty scene still has a
// shell), so the whole model lies well inside and, from every camera, each
// shell Gaussian lies behind every object Gaussian along its rays.
struct SkyShell {
  Eigen::Vector3d centre = Eigen::Vector3d::Zero();
  double radius = 1.0;
};
SkyShell sky_shell(const GaussianSet& objects, const std::vector<Camera>& cameras, const SkyBakeConfig& config = {});

// Lattice size from the sky's degree: a constant sky (degree 0) needs only
// enough Gaussians to close the shell; each degree above it varies faster
// with direction and gets a finer lattice (measured: docs/benchmarks.md,
// "The sky in the .ply").
int sky_bake_count(int degree);

// The sky [K, 3] coefficients (degree from K) as Gaussians on the shell, at
// SH degree `sh_degree_out` (>= the sky's degree; higher terms zero).
// Features are zero. std::invalid_argument for a coefficient count that is no
// degree, or sh_degree_out below the sky's degree or above 3.
GaussianSet bake_sky(const std::vector<float>& coefficients, const SkyShell& shell, int sh_degree_out,
                     const SkyBakeConfig& config = {});

// `a` followed by `b`, at the higher of their SH degrees (missing terms zero).
GaussianSet concat_gaussians(const GaussianSet& a, const GaussianSet& b);

}  // namespace ag2gs
