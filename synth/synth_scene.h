// A generator of synthetic scenes with exact ground truth: a small ray tracer
// of textured primitives standing on a textured ground plane, seen by cameras
// on a ring, all inside a textured backdrop (a cylindrical wall with a floor
// ring and a ceiling, so every camera ray meets textured geometry that the
// sparse points cover, as in a real capture; --no-backdrop gives the old
// untextured sky instead). It writes a complete scene directory in the formats of
// docs/formats.md, so every stage (training, clustering, queries, evaluation) can be
// measured against truth that is known exactly. Everything is deterministic
// from the seed (a counter-based hash, no global RNG state).
//
// Output layout of write_synth_scene(out_dir, options):
//   images/view_NNN.png                 RGB, 8 bit
//   sparse/0/{cameras,images,points3D}.bin   PINHOLE cameras; points sampled on
//                                       the visible surfaces with their colours
//   language_features/view_NNN_s.npy    float32 [4,H,W] SAM-like mask ids per
//                                       level (default, small, medium, large),
//                                       -1 = none, ids cumulative across levels
//   language_features/view_NNN_f.npy    float32 [num masks, 512] CLIP-like
//   masks/view_NNN.png                  16-bit ids of the level-3 masks + 1 (0 = none)
//   gt/view_NNN.png                     16-bit exact object ids (0 = ground,
//                                       backdrop or sky; no masks there either)
//   label/view_NNN.json                 LERF-style labelme polygons, test views
//   removal_gt/<category>/view_NNN.png  (--removal-gt) test views without the
//                                       objects of that category, exact
//   vocab.json                          {"phrase": [512 floats]} per category
//   clicks.json                         [{"frame","x","y","category"}] test views
//   synth.json                          the objects (id, category, primitive,
//                                       centre, size, colour), cameras, seed
#pragma once

#include <cstdint>
#include <string>

namespace ag2gs {

struct SynthOptions {
  uint64_t seed = 1;
  int width = 160;
  int height = 120;
  int views = 24;         // cameras on a ring around the scene; every 8th is a test view
  int objects = 5;        // number of objects (primitives) on the ground plane
  int feature_dim = 512;  // CLIP-like feature dimension
  int samples = 2;        // supersampling per pixel axis (2 = 4 rays per pixel)
  int points = 4000;      // SfM-like points written to points3D
  // The SAM-like masks (language_features/, masks/) at 1/mask_factor of the
  // image resolution, as the public LERF-OVS data often has them (docs/formats.md
  // section 3: masks may be smaller than the image); width and height must
  // be multiples of it. The exact GT (gt/, label/, clicks) is always full size.
  int mask_factor = 1;
  // The hard settings: two objects touching, two objects of
  // similar colour, one thin object, and occlusion between objects.
  bool hard = false;
  bool text_model = false;  // write the COLMAP model as .txt instead of .bin
  // A textured backdrop around the scene: a vertical cylindrical wall beyond
  // the camera ring, a floor ring from the ground disc to the wall and a
  // ceiling closing the wall, so no camera ray sees the (untextured, point-
  // less) sky. Off: rays that miss the objects and the ground see the sky.
  bool backdrop = true;
  // SfM-like points on the backdrop's wall. Off: the sparse points miss the
  // wall (each one hitting it is drawn again elsewhere), as the far walls of
  // real rooms often have none; what the trainer's far shell is for.
  bool wall_points = true;
  // SAM-like masks on the background too (floor quarters cut differently in
  // each view, the floor ring, wall halves, the ceiling), as SAM's automatic
  // mode gives them on real photos. Off: no masks on the background.
  bool background_masks = false;
  // Exact removal ground truth: each test view traced again without each
  // category's objects, as removal_gt/<category>/view_NNN.png.
  bool removal_gt = false;
};

// Writes the scene into `out_dir` (created if missing; existing files of the
// same names are replaced atomically). Throws std::invalid_argument for bad
// options, std::runtime_error naming the path when writing fails.
void write_synth_scene(const std::string& out_dir, const SynthOptions& options);

}  // namespace ag2gs
