// Holes of an object removal (apps/removal/holes.h) on a constructed scene:
// a box standing on a textured floor that has no Gaussians under the box (no
// view saw that ground), seen from four sides. The hole of each view must be
// the box's footprint as the view's rays meet the floor plane, within a pixel;
// the rest of the box's silhouette shows floor the model knows. The fill
// (apps/removal/fill.h) must then find the footprint in 3D: on the floor
// plane, inside the box's base, and place anchors there only.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <functional>
#include <set>
#include <string>

#include "apps/removal/fill.h"
#include "apps/removal/holes.h"
#include "tests/test_util.h"

namespace ag2gs {
namespace {

constexpr double kHalf = 0.2;  // the box: [-0.2, 0.2]^2 x [0, 0.4]

void add(GaussianSet& g, double x, double y, double z, double sx, double sy, double sz, float r, float gr, float b) {
  const size_t i = g.size();
  g.resize(i + 1);
  g.means[3 * i] = static_cast<float>(x);
  g.means[3 * i + 1] = static_cast<float>(y);
  g.means[3 * i + 2] = static_cast<float>(z);
  g.scales[3 * i] = static_cast<float>(sx);
  g.scales[3 * i + 1] = static_cast<float>(sy);
  g.scales[3 * i + 2] = static_cast<float>(sz);
  g.quats[4 * i] = 1.f;
  g.opacities[i] = 0.95f;
  const float c0 = 0.28209479f;  // SH band 0: colour = 0.5 + c0 * sh
  g.sh[3 * i] = (r - 0.5f) / c0;
  g.sh[3 * i + 1] = (gr - 0.5f) / c0;
  g.sh[3 * i + 2] = (b - 0.5f) / c0;
}

GaussianSet floor_without_footprint() {
  GaussianSet g;
  g.sh_degree = 0;
  // Small Gaussians, so that the floor's edge around the footprint is sharp
  // to well within a pixel (0.04 world units here).
  const double step = 0.04;
  for (int i = -38; i <= 38; ++i)
    for (int j = -38; j <= 38; ++j) {
      const double x = i * step, y = j * step;
      if (std::abs(x) < kHalf && std::abs(y) < kHalf) continue;  // unseen under the box
      const float checker = (((i + 40) / 5 + (j + 40) / 5) & 1) ? 0.8f : 0.3f;
      add(g, x, y, 0.0, 0.02, 0.02, 0.002, checker, 0.5f, 1.f - checker);
    }
  return g;
}

GaussianSet box() {
  GaussianSet g;
  g.sh_degree = 0;
  const double step = 0.04, h = 2 * kHalf;
  for (int i = 0; i <= 10; ++i)
    for (int j = 0; j <= 10; ++j) {
      const double a = -kHalf + i * step, b = j * step, c = -kHalf + j * step;
      add(g, a, c, h, 0.025, 0.025, 0.002, 0.9f, 0.1f, 0.1f);       // top
      add(g, a, -kHalf, b, 0.025, 0.002, 0.025, 0.9f, 0.2f, 0.1f);  // four sides
      add(g, a, kHalf, b, 0.025, 0.002, 0.025, 0.9f, 0.2f, 0.1f);
      add(g, -kHalf, a, b, 0.002, 0.025, 0.025, 0.9f, 0.3f, 0.1f);
      add(g, kHalf, a, b, 0.002, 0.025, 0.025, 0.9f, 0.3f, 0.1f);
    }
  return g;
}

// A camera on a circle of radius 3 at 40 degrees elevation, looking at the origin.
Camera view_from(double azimuth) {
  const double el = 40.0 * M_PI / 180.0;
  const Eigen::Vector3d eye(3 * std::cos(el) * std::cos(azimuth), 3 * std::cos(el) * std::sin(azimuth),
                            3 * std::sin(el));
  return test::look_at(eye, Eigen::Vector3d::Zero(), 64, 48, 70);
}

// 1 where the pixel centre's ray meets the floor plane inside the footprint.
std::vector<uint8_t> expected_hole(const Camera& cam) {
  std::vector<uint8_t> m(static_cast<size_t>(cam.width) * cam.height, 0);
  const Eigen::Vector3d c = cam.center();
  for (int v = 0; v < cam.height; ++v)
    for (int u = 0; u < cam.width; ++u) {
      const Eigen::Vector3d dc((u + 0.5 - cam.cx) / cam.fx, (v + 0.5 - cam.cy) / cam.fy, 1.0);
      const Eigen::Vector3d d = cam.R.transpose() * dc;
      if (d.z() >= 0) continue;
      const Eigen::Vector3d p = c - c.z() / d.z() * d;
      m[static_cast<size_t>(v) * cam.width + u] = std::abs(p.x()) < kHalf && std::abs(p.y()) < kHalf;
    }
  return m;
}

// Pixels where a and b differ and no 8-neighbour of the pixel has b's other value.
size_t mismatches_beyond_a_pixel(const std::vector<uint8_t>& a, const std::vector<uint8_t>& b, int w, int h) {
  size_t bad = 0;
  for (int y = 0; y < h; ++y)
    for (int x = 0; x < w; ++x) {
      const size_t p = static_cast<size_t>(y) * w + x;
      if (a[p] == b[p]) continue;
      bool near_edge = false;
      for (int dy = -1; dy <= 1 && !near_edge; ++dy)
        for (int dx = -1; dx <= 1; ++dx) {
          const int xx = x + dx, yy = y + dy;
          if (xx < 0 || yy < 0 || xx >= w || yy >= h) continue;
          if (b[static_cast<size_t>(yy) * w + xx] != b[p]) near_edge = true;
        }
      bad += !near_edge;
    }
  return bad;
}

TEST(RemovalHoles, HoleIsTheFootprintSeenFromEachView) {
  const GaussianSet kept = floor_without_footprint(), removed = box();
  HoleFinder finder(kept, removed);
  EXPECT_NEAR(finder.diameter(), 2 * std::sqrt(3.0) * kHalf, 0.15);
  Renderer renderer(test::runtime());
  HoleSettings s;
  s.dilate = 0;
  for (double az : {0.3, 1.9, 3.4, 5.0}) {
    const Camera cam = view_from(az);
    const ViewHole h = finder.find(renderer, cam, s);
    const std::vector<uint8_t> want = expected_hole(cam);
    size_t want_pixels = 0;
    for (uint8_t b : want) want_pixels += b;
    std::printf("azimuth %.1f: object %zu px, hole %zu px, footprint %zu px\n", az, h.object_pixels, h.hole_pixels,
                want_pixels);
    ASSERT_GT(want_pixels, 30u) << "the footprint should be visible through the box";
    if (std::getenv("AG2GS_DEBUG_HOLES"))
      for (int y = 0; y < cam.height; ++y) {
        std::string row;
        for (int x = 0; x < cam.width; ++x) {
          const size_t p = static_cast<size_t>(y) * cam.width + x;
          row += h.hole[p] ? (want[p] ? '#' : '+') : want[p] ? '-' : h.object[p] ? 'o' : '.';
        }
        std::printf("%s\n", row.c_str());
      }
    EXPECT_GT(h.object_pixels, 2 * want_pixels) << "the box's silhouette is larger than its footprint";
    EXPECT_EQ(mismatches_beyond_a_pixel(h.hole, want, cam.width, cam.height), 0u) << "azimuth " << az;
  }
}

TEST(RemovalHoles, DilationGrowsTheHoleAndNothingRemovedMeansNoHole) {
  const GaussianSet kept = floor_without_footprint(), removed = box();
  Renderer renderer(test::runtime());
  const Camera cam = view_from(0.7);
  HoleSettings s;
  s.dilate = 0;
  HoleFinder finder(kept, removed);
  const ViewHole h0 = finder.find(renderer, cam, s);
  s.dilate = 2;
  const ViewHole h2 = finder.find(renderer, cam, s);
  EXPECT_EQ(h2.undilated_hole_pixels, h0.hole_pixels);
  EXPECT_GT(h2.hole_pixels, h0.hole_pixels);
  for (size_t p = 0; p < h0.hole.size(); ++p)
    if (h0.hole[p]) EXPECT_TRUE(h2.hole[p]);
  GaussianSet none;
  none.sh_degree = 0;
  const ViewHole hn = HoleFinder(kept, none).find(renderer, cam, s);
  EXPECT_EQ(hn.object_pixels, 0u);
  EXPECT_EQ(hn.hole_pixels, 0u);
  s.dilate = -1;
  EXPECT_THROW(finder.find(renderer, cam, s), std::invalid_argument);
  GaussianSet other_degree = removed;
  other_degree.sh_degree = 1;
  other_degree.sh.resize(other_degree.size() * 4 * 3, 0.f);
  EXPECT_THROW(HoleFinder(kept, other_degree), std::invalid_argument);
}

TEST(RemovalHoles, InpaintingFillsOnlyTheHole) {
  const int w = 40, h = 30;
  std::vector<float> rgb(static_cast<size_t>(w) * h * 3);
  std::vector<uint8_t> hole(static_cast<size_t>(w) * h, 0);
  for (int y = 0; y < h; ++y)
    for (int x = 0; x < w; ++x) {
      const size_t p = static_cast<size_t>(y) * w + x;
      const bool in = x >= 15 && x < 25 && y >= 10 && y < 20;
      hole[p] = in;
      for (int c = 0; c < 3; ++c) rgb[3 * p + c] = in ? 0.f : 0.2f + 0.3f * c;  // a flat colour around a black hole
    }
  for (const char* name : {"telea", "ns"}) {
    const std::vector<float> out = inpaint_hole(rgb, hole, w, h, parse_inpaint_method(name));
    for (size_t p = 0; p < hole.size(); ++p)
      for (int c = 0; c < 3; ++c) {
        if (!hole[p])
          EXPECT_EQ(out[3 * p + c], rgb[3 * p + c]);
        else
          EXPECT_NEAR(out[3 * p + c], 0.2f + 0.3f * c, 2.5f / 255.f) << name;
      }
  }
  EXPECT_EQ(inpaint_hole(rgb, hole, w, h, InpaintMethod::kNone), rgb);
  EXPECT_THROW(parse_inpaint_method("lama"), std::invalid_argument);
  EXPECT_THROW(inpaint_hole(rgb, hole, w + 1, h, InpaintMethod::kTelea), std::invalid_argument);
}

// The 3D footprint of the four views' holes lies on the floor plane inside
// the box's base and covers it; the fill puts anchors exactly into the empty
// voxels of the base (on the floor's layer), with the targets' colour, and
// marks the floor anchors around it trainable, the far ones not.
// Layer 1 of this grid: 0.08 cells, z = 0 the middle of cell 12.
VoxelGrid fill_grid() {
  VoxelGrid grid;
  grid.origin = Eigen::Vector3d(-1.0, -1.0, -1.0);
  grid.top_voxel = 0.32;
  grid.layer_ratio = 4;
  grid.layers = 2;
  return grid;
}

AnchorConfig fill_config() {
  AnchorConfig config;
  config.children = 2;
  config.layers = 2;
  return config;
}

// The footprint of the box's holes seen from four views around it, each
// view's target a flat colour in its hole: colour(v) for view v.
HoleFootprint box_footprint(const std::function<Eigen::Vector3f(int)>& colour) {
  const GaussianSet kept = floor_without_footprint(), removed = box();
  HoleFinder finder(kept, removed);
  Renderer renderer(test::runtime());
  HoleSettings s;
  s.dilate = 0;
  HoleFootprint footprint(fill_grid(), finder.diameter(), s.behind);
  int v = 0;
  for (double az : {0.3, 1.9, 3.4, 5.0}) {
    const Camera cam = view_from(az);
    const ViewHole h = finder.find(renderer, cam, s);
    std::vector<float> target(h.rgb_after);
    const Eigen::Vector3f c = colour(v++);
    for (size_t p = 0; p < h.hole.size(); ++p)
      if (h.hole[p])
        for (int k = 0; k < 3; ++k) target[3 * p + k] = c[k];
    footprint.add_view(cam, h, target);
  }
  return footprint;
}

// Floor anchors on layer 1 everywhere but under the box; `base` gets the
// 25 cells left empty.
AnchorModel floor_model(std::set<std::pair<int, int>>* base) {
  const VoxelGrid grid = fill_grid();
  AnchorModel model;
  model.reset(grid, fill_config());
  for (int i = 0; i < 26; ++i)
    for (int j = 0; j < 26; ++j) {
      const Eigen::Vector3i cell(i, j, 12);
      const Eigen::Vector3d c = grid.centre(1, cell);
      if (std::abs(c.x()) < kHalf && std::abs(c.y()) < kHalf) {
        if (base) base->insert({i, j});
        continue;
      }
      EXPECT_GE(model.add_anchor(1, cell, -1, 1), 0);
    }
  return model;
}

float sh_colour(const AnchorModel& model, size_t gaussian, int channel) {
  return 0.5f + 0.28209479f * model.sh()[gaussian * kAnchorShCoeffs * 3 + channel];
}

TEST(RemovalFill, FootprintIsTheBaseOnTheFloorAndTheFillGoesThere) {
  const VoxelGrid grid = fill_grid();
  const AnchorConfig config = fill_config();
  // A flat target colour in the hole: the fill's colour must be it.
  const HoleFootprint footprint = box_footprint([](int) { return Eigen::Vector3f(0.25f, 0.5f, 0.75f); });
  EXPECT_EQ(footprint.views_with_holes(), 4);
  ASSERT_GT(footprint.points(), 100u);
  // Voxels seen by two views or more (those the fill takes) lie on the
  // floor within 0.03 (1% of the camera distance); a voxel of one view's
  // rim pixels within 0.06.
  size_t off_plane = 0, outside = 0;
  for (const auto& [key, c] : footprint.cells()) {
    const double x = c.sum[0] / c.points, y = c.sum[1] / c.points, z = c.sum[2] / c.points;
    off_plane += std::abs(z) > (c.views() >= 2 ? 0.03 : 0.06);
    if (std::getenv("AG2GS_DEBUG_HOLES"))
      std::printf("cell %.3f %.3f %.3f (%zu points, %d views)\n", x, y, z, c.points, c.views());
    outside += std::abs(x) > kHalf + 0.04 || std::abs(y) > kHalf + 0.04;
  }
  EXPECT_EQ(off_plane, 0u) << "of " << footprint.cells().size() << " footprint voxels";
  EXPECT_EQ(outside, 0u) << "of " << footprint.cells().size() << " footprint voxels";

  std::set<std::pair<int, int>> base;
  AnchorModel model = floor_model(&base);
  const double edge = grid.voxel(1);
  ASSERT_EQ(base.size(), 25u);  // 5 x 5 cells of 0.08 tile the 0.4 base
  const size_t floor_anchors = model.size();
  FillSettings fs;
  const FillResult r = add_fill_anchors(model, footprint, fs, 100, 1);
  EXPECT_EQ(model.size(), floor_anchors + r.added.size());
  EXPECT_GE(r.added.size(), 20u) << "most of the base's 25 voxels";
  for (size_t k = 0; k < r.added.size(); ++k) {
    const int id = r.added[k];
    ASSERT_EQ(id, static_cast<int>(floor_anchors + k));
    EXPECT_EQ(model.layer()[id], 1);
    const int cx = model.cell()[3 * id], cy = model.cell()[3 * id + 1], cz = model.cell()[3 * id + 2];
    EXPECT_EQ(cz, 12);
    EXPECT_TRUE(base.count({cx, cy})) << cx << "," << cy;
    for (int i = 0; i < config.children; ++i) {
      const size_t g = static_cast<size_t>(id) * config.children + i;
      EXPECT_NEAR(sh_colour(model, g, 0), 0.25, 1e-3);
      EXPECT_NEAR(sh_colour(model, g, 2), 0.75, 1e-3);
      EXPECT_NEAR(1.0 / (1.0 + std::exp(-model.opacity_logit()[static_cast<size_t>(id) * config.children + i])),
                  fs.opacity, 1e-5);
    }
  }
  // Trainable: the fill and the floor ring within 1.5 voxels of the footprint.
  size_t ring = 0;
  for (size_t a = 0; a < floor_anchors; ++a) {
    const Eigen::Vector3d p(model.pos()[3 * a], model.pos()[3 * a + 1], model.pos()[3 * a + 2]);
    const double d = std::max(std::abs(p.x()), std::abs(p.y()));
    if (d > kHalf + 1.5 * edge + 0.04) EXPECT_EQ(r.trainable[a], 0) << "far floor anchor " << a;
    ring += r.trainable[a];
  }
  EXPECT_EQ(ring, r.trainable_kept);
  EXPECT_GE(ring, 12u) << "the floor cells around the base";
  for (int id : r.added) EXPECT_EQ(r.trainable[id], 1);
  // The cap keeps the best-supported voxels.
  AnchorModel capped;
  capped.reset(grid, config);
  ASSERT_GE(capped.add_anchor(1, Eigen::Vector3i(0, 0, 12), -1, 1), 0);
  FillSettings one = fs;
  one.max_anchors = 3;
  EXPECT_EQ(add_fill_anchors(capped, footprint, one, 100, 1).added.size(), 3u);
  FillSettings bad = fs;
  bad.opacity = 1.f;
  EXPECT_THROW(add_fill_anchors(capped, footprint, bad, 100, 1), std::invalid_argument);
  bad = fs;
  bad.colour_quantile = 1.5f;
  EXPECT_THROW(add_fill_anchors(capped, footprint, bad, 100, 1), std::invalid_argument);
}

// One of the four views sees the floor in shadow (its target dark); every
// fill voxel takes two views or more. The default upper quantile takes a lit
// view's colour everywhere; the lowest (0) takes the shadow's wherever that
// view reaches, and the lit colour elsewhere.
TEST(RemovalFill, TheFillTakesTheColourOfTheViewsThatSawItLit) {
  const Eigen::Vector3f lit(0.6f, 0.5f, 0.4f), shadow(0.15f, 0.12f, 0.1f);
  const HoleFootprint footprint = box_footprint([&](int v) { return v == 1 ? shadow : lit; });
  for (const float q : {0.75f, 0.5f, 0.f}) {
    AnchorModel model = floor_model(nullptr);
    const size_t floor_anchors = model.size();
    FillSettings fs;
    fs.colour_quantile = q;
    const FillResult r = add_fill_anchors(model, footprint, fs, 100, 1);
    ASSERT_GE(r.added.size(), 20u);
    size_t dark = 0;
    for (int id : r.added) {
      const size_t g = static_cast<size_t>(id) * model.children();
      const bool is_dark = std::abs(sh_colour(model, g, 0) - shadow[0]) < 1e-3f;
      dark += is_dark;
      for (int k = 0; k < 3; ++k)
        EXPECT_NEAR(sh_colour(model, g, k), is_dark ? shadow[k] : lit[k], 1e-3)
            << "quantile " << q << ", anchor " << id;
    }
    EXPECT_EQ(model.size(), floor_anchors + r.added.size());
    if (q > 0)
      EXPECT_EQ(dark, 0u) << "quantile " << q;  // 2-4 estimates, at most one dark: index floor(q n) is lit
    else
      EXPECT_GT(dark, 0u) << "the shadowed view reaches part of the base";
  }
}

// A kept child in a removed Gaussian's voxel with its colour is stray; one
// there with another colour, or elsewhere with the same colour, is not; nor
// is one whose colour is nearer to the kept Gaussians around it. With a
// reach of one voxel, children next to the object's voxel count too.
TEST(RemovalFill, StrayChildrenAreThoseAmongTheObjectsGaussiansWithItsColour) {
  AnchorConfig config;
  config.children = 2;
  config.layers = 1;
  VoxelGrid grid;
  grid.top_voxel = 1.0;
  grid.layers = 1;
  AnchorModel m;
  m.reset(grid, config);
  const int a = m.add_anchor(0, Eigen::Vector3i(0, 0, 0), -1, 1);  // removed
  const int b = m.add_anchor(0, Eigen::Vector3i(1, 0, 0), -1, 1);  // kept, child 0 reaches into a's voxel
  const int c = m.add_anchor(0, Eigen::Vector3i(0, 1, 0), -1, 1);  // kept, child 0 too, another colour
  const int d = m.add_anchor(0, Eigen::Vector3i(3, 0, 0), -1, 1);  // kept, far: 3 voxels from a
  ASSERT_TRUE(a == 0 && b == 1 && c == 2 && d == 3);
  auto set_child = [&](int anchor, int child, Eigen::Vector3f offset, float grey) {
    const size_t g = static_cast<size_t>(anchor) * 2 + child;
    for (int k = 0; k < 3; ++k) {
      m.offset()[3 * g + k] = offset[k];
      m.sh()[g * kAnchorShCoeffs * 3 + k] = (grey - 0.5f) / 0.28209479f;
    }
  };
  set_child(a, 0, {0.f, 0.f, 0.f}, 0.8f);
  set_child(a, 1, {0.2f, 0.f, 0.f}, 0.8f);
  set_child(b, 0, {-1.f, 0.f, 0.f}, 0.7f);  // in a's voxel, 0.1 off its colour: stray
  set_child(b, 1, {0.f, 0.f, 0.f}, 0.8f);   // a's colour in the next voxel: stray from reach 1
  set_child(c, 0, {0.f, -1.f, 0.f}, 0.2f);  // in a's voxel, another colour: kept
  set_child(c, 1, {0.f, 0.f, 0.f}, 0.2f);   // next to a's voxel, c's colour: kept
  set_child(d, 0, {0.f, 0.f, 0.f}, 0.8f);   // a's colour, 3 voxels away: kept up to reach 2
  set_child(d, 1, {0.f, 0.f, 0.f}, 0.8f);
  const std::vector<uint8_t> selected = {1, 0, 0, 0};
  EXPECT_EQ(stray_children(m, selected, 0.2f, 0), std::vector<size_t>({2}));
  EXPECT_TRUE(stray_children(m, selected, 0.05f, 0).empty());
  // Within 0.7, c's child 0 (0.2) is 0.6 from the object's 0.8 but 0.5 from
  // the kept 0.7 beside it: it stays.
  EXPECT_EQ(stray_children(m, selected, 0.7f, 0), std::vector<size_t>({2}));
  // Reach 1: b's child 1 (0.8) is 0 from the object and 0.3 from the others
  // near it (0.7, 0.2, 0.2: mean 0.37); c's children stay (0.2 is nearer to
  // the others' mean). d's children, 3 voxels off, come in at reach 3.
  EXPECT_EQ(stray_children(m, selected, 0.2f, 1), std::vector<size_t>({2, 3}));
  EXPECT_EQ(stray_children(m, selected, 0.2f, 3), std::vector<size_t>({2, 3, 6, 7}));
  // Transparent children neither count nor are cleared.
  AnchorModel faded = m;
  for (int k = 0; k < 2; ++k) faded.opacity_logit()[2 + k] = -10.f;  // b's children
  EXPECT_TRUE(stray_children(faded, selected, 0.2f, 0).empty());
  EXPECT_TRUE(stray_children(m, {0, 0, 0, 0}).empty());
  EXPECT_THROW(stray_children(m, {1, 0}), std::invalid_argument);
  EXPECT_THROW(stray_children(m, selected, 0.2f, -1), std::invalid_argument);
}

// seen_weight against the alpha images: a Gaussian F in front of another, B,
// seen by one camera. Alone, F's weight per pixel is its alpha; behind it,
// B's is what it adds to the pair's alpha, alpha_FB - alpha_F. With F as the
// object only the pixels where F's alpha is 0.5 or less count.
TEST(RemovalHidden, SeenWeightIsWhatTheAlphaImagesShow) {
  GaussianSet front, back;
  front.sh_degree = back.sh_degree = 0;
  add(front, 0.0, 0.0, 0.3, 0.12, 0.12, 0.12, 0.5f, 0.5f, 0.5f);
  add(back, 0.05, 0.0, 0.0, 0.15, 0.15, 0.15, 0.5f, 0.5f, 0.5f);
  GaussianSet both = front;
  both.resize(2);
  for (int k = 0; k < 3; ++k) {
    both.means[3 + k] = back.means[k];
    both.scales[3 + k] = back.scales[k];
    both.sh[3 + k] = back.sh[k];
  }
  both.quats[4] = 1.f;
  both.opacities[1] = back.opacities[0];
  const Camera cam = test::look_at(Eigen::Vector3d(0.2, 0.1, 3.0), Eigen::Vector3d::Zero(), 64, 48, 70);
  Renderer renderer(test::runtime());
  const std::vector<float> a_front = renderer.render(front, cam).alpha, a_both = renderer.render(both, cam).alpha;
  double w_front = 0, w_back = 0, w_front_outside = 0, w_back_outside = 0;
  for (size_t p = 0; p < a_both.size(); ++p) {
    w_front += a_front[p];
    w_back += a_both[p] - a_front[p];
    if (a_front[p] <= 0.5f) {
      w_front_outside += a_front[p];
      w_back_outside += a_both[p] - a_front[p];
    }
  }
  ASSERT_GT(w_back_outside, 1.0);
  ASSERT_LT(w_back_outside, 0.9 * w_back) << "the front Gaussian must hide part of the back one";
  const std::vector<double> seen = seen_weight(renderer, both, {cam, cam}, RenderSettings{});
  EXPECT_NEAR(seen[0], 2 * w_front, 1e-4 * w_front);
  EXPECT_NEAR(seen[1], 2 * w_back, 1e-4 * w_back);
  const std::vector<uint8_t> object = {1, 0};
  const std::vector<double> outside = seen_weight(renderer, both, {cam}, RenderSettings{}, &object);
  EXPECT_NEAR(outside[1], w_back_outside, 1e-3 * w_back_outside);
  EXPECT_NEAR(outside[0], w_front_outside, 1e-3 * w_front_outside);
  const std::vector<uint8_t> short_flags = {1};
  EXPECT_THROW(seen_weight(renderer, both, {cam}, RenderSettings{}, &short_flags), std::invalid_argument);
}

// A block of opaque object anchors with a cavity holding a kept anchor:
// no view sees into it, so that anchor is hidden and goes with the object.
// A kept anchor beside the block is seen; so is one with a child inside the
// block and a child outside (a surface the photos show).
TEST(RemovalHidden, AnAnchorInsideTheObjectIsHiddenAndOnesBesideItAreNot) {
  AnchorModel m;
  m.reset(fill_grid(), fill_config());
  std::vector<uint8_t> selected;
  auto anchor = [&](int i, int j, int k, bool object) {
    const int a = m.add_anchor(1, Eigen::Vector3i(i, j, k), -1, 1);
    EXPECT_GE(a, 0);
    selected.push_back(object);
    for (int c = 0; c < 2; ++c) {
      const size_t g = static_cast<size_t>(a) * 2 + c;
      for (int d = 0; d < 3; ++d) {
        m.offset()[3 * g + d] = 0.f;
        m.scale_logit()[3 * g + d] = 0.4f;  // sigmoid: 0.6 of the 0.08 voxel
      }
      m.opacity_logit()[g] = 5.f;  // 0.993
    }
    return a;
  };
  for (int i = 10; i <= 15; ++i)
    for (int j = 10; j <= 15; ++j)
      for (int k = 12; k <= 16; ++k)
        if (!(i == 12 && j == 12 && k == 14)) anchor(i, j, k, true);
  const int inside = anchor(12, 12, 14, false);
  const int beside = anchor(18, 12, 13, false);
  const int straddling = anchor(16, 13, 14, false);
  m.offset()[3 * (static_cast<size_t>(straddling) * 2)] = -1.f;  // child 0 in the block's voxel (15, 13, 14)
  std::vector<Camera> cams;
  for (double az : {0.3, 1.9, 3.4, 5.0}) cams.push_back(view_from(az));
  Renderer renderer(test::runtime());
  EXPECT_EQ(hidden_anchors(renderer, m, 0, selected, cams, RenderSettings{}), std::vector<int>({inside}));
  // The cavity's own voxel holds none of the object's Gaussians: reach 0
  // does not look beyond it.
  EXPECT_TRUE(hidden_anchors(renderer, m, 0, selected, cams, RenderSettings{}, 0).empty());
  EXPECT_TRUE(hidden_anchors(renderer, m, 0, selected, cams, RenderSettings{}, 3, 0.0).empty());
  // Without the object nothing hides it; nothing selected, nothing near.
  std::vector<uint8_t> none(selected.size(), 0);
  EXPECT_TRUE(hidden_anchors(renderer, m, 0, none, cams, RenderSettings{}).empty());
  (void)beside;
  EXPECT_THROW(hidden_anchors(renderer, m, 0, {1, 0}, cams, RenderSettings{}), std::invalid_argument);
  EXPECT_THROW(hidden_anchors(renderer, m, 0, selected, cams, RenderSettings{}, 17), std::invalid_argument);
}

}  // namespace
}  // namespace ag2gs
