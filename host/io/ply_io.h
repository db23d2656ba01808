// Reading and writing Gaussians in the standard 3D Gaussian Splatting
// point_cloud.ply layout, which every 3DGS viewer opens:
//
//   format binary_little_endian 1.0
//   element vertex N
//   property float x y z nx ny nz f_dc_0..2 f_rest_0..M-1 opacity scale_0..2 rot_0..3
//   [property float feat_0..2]   (ag2gs: the semantic feature; viewers ignore it)
//
// M = 3 (K - 1) with K = (degree + 1)^2, so M in {0, 9, 24, 45} gives the SH
// degree 0..3. f_dc_c = sh[n,0,c]; f_rest is channel-major:
// f_rest_{c (K-1) + (k-1)} = sh[n,k,c]. The file stores pre-activation values:
// opacity is a logit (ours = sigmoid of it), scale_i is a log (ours = exp of
// it), rot is (w, x, y, z) kept as stored, without normalisation. The
// activations and their inverses are computed in double and rounded to float.
#pragma once

#include <string>

#include "host/core/gaussians.h"

namespace ag2gs {

// What the opacity and scale arrays of a GaussianSet hold when it crosses a
// file: `activated` (opacity in [0,1], scale > 0; converted in double) or
// `stored` (the file's own logit and log values, copied bit for bit: the
// trainer's parameters, so an export and re-import is bit-exact).
enum class PlyValues { activated, stored };

// Reads a PLY in the layout above. Also accepts ascii PLYs, any scalar
// property type (double, int, ...), extra properties (ignored) and a missing
// nx/ny/nz or feat_0..2 (features read as zero). Throws std::runtime_error
// naming the file and what is wrong: not a PLY, big-endian, truncated data,
// a missing property, an f_rest count that is no SH degree.
//
// Numbers are checked at load (one policy for every reader of Gaussians): a
// Gaussian with a non-finite value, a zero rotation, or (activated values) a
// scale <= 0 or an opacity outside [0, 1] is invalid. With
// InvalidGaussians::reject (the default) any is an error naming the file,
// how many there are and the first one; with ::drop they are left out and
// counted in *dropped; ::keep reads the numbers as they are (tools that
// copy a file's bits).
enum class InvalidGaussians { reject, drop, keep };
GaussianSet read_ply(const std::string& path, PlyValues values = PlyValues::activated,
                     InvalidGaussians policy = InvalidGaussians::reject, size_t* dropped = nullptr);

// The index of the first invalid Gaussian of `gs` (rules above) and what is
// wrong with it, and how many there are; count 0 when all are valid.
struct InvalidReport {
  size_t count = 0;
  size_t first = 0;
  std::string what;  // "scale_1 = nan", "rotation (0, 0, 0, 0)", ...
};
InvalidReport find_invalid_gaussians(const GaussianSet& gs, PlyValues values = PlyValues::activated);

// Writes `gaussians` (validated first: std::invalid_argument when the array
// sizes disagree) as a binary little-endian PLY, applying the inverse
// activations logit(clamp(o, 1e-7, 1 - 1e-7)) and log(max(scale, 1e-30)).
// with_features = false leaves out feat_0..2 (a plain 3DGS file); with
// PlyValues::stored opacities and scales are written as they are. Atomic: the
// data goes to "<path>.tmp.<pid>", renamed over `path` only when complete;
// on failure the temporary file is removed, an existing `path` is left as it
// was, and std::runtime_error says why.
void write_ply(const std::string& path, const GaussianSet& gaussians, bool with_features = true,
               PlyValues values = PlyValues::activated);

}  // namespace ag2gs
