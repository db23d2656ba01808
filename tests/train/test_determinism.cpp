// Determinism: the same inputs give bit-identical forward and backward
// results, run to run and whatever the number of PoCL threads (the blend
// backward writes per-intersection slots and reduces them in a fixed order;
// no floating-point atomics anywhere).
#include <unistd.h>

#include <cstdio>
#include <cstdlib>
#include <fstream>

#include "tests/test_util.h"

namespace ag2gs {
namespace {

uint64_t render_hash() {
  test::SceneSpec spec;
  spec.n = 3000;
  spec.sh_degree = 2;
  GaussianSet g = test::random_scene(spec, 99);
  Camera cam = test::look_at_origin(203, 151);
  Renderer r(test::runtime());
  RenderOutput out = r.render(g, cam, {});
  std::mt19937 rng(5);
  std::uniform_real_distribution<float> u(-1, 1);
  OutputGrads og;
  for (auto* v : {&og.rgb, &og.feature}) {
    v->resize(out.rgb.size());
    for (auto& x : *v) x = u(rng);
  }
  for (auto* v : {&og.depth, &og.alpha, &og.distortion}) {
    v->resize(out.alpha.size());
    for (auto& x : *v) x = u(rng);
  }
  GaussianGrads gr = r.render_backward(og);
  uint64_t h = test::hash_vec(out.rgb);
  for (auto* v : {&out.feature, &out.depth, &out.alpha, &out.distortion}) h = test::hash_vec(*v, h);
  for (auto* v : {&gr.means, &gr.scales, &gr.quats, &gr.opacities, &gr.sh, &gr.features, &gr.means2d})
    h = test::hash_vec(*v, h);
  return h;
}

TEST(Determinism, SameBitsTwice) {
  uint64_t a = render_hash(), b = render_hash();
  EXPECT_EQ(a, b);
}

// Run by the test below in a child process with a given thread count.
TEST(DeterminismWorker, WriteHash) {
  const char* out = std::getenv("AG2GS_HASH_OUT");
  if (!out) GTEST_SKIP() << "only run as a child of SameBitsAcrossThreadCounts";
  std::ofstream(out) << render_hash() << "\n";
}

TEST(Determinism, SameBitsAcrossThreadCounts) {
  const auto hashes = test::lines_by_thread_count("DeterminismWorker.WriteHash");
  EXPECT_EQ(hashes[0], hashes[1]) << "1 thread vs 2 threads";
  EXPECT_EQ(hashes[0], std::to_string(render_hash())) << "child vs this process";
}

}  // namespace
}  // namespace ag2gs
