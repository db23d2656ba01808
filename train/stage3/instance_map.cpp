#include "train/stage3/instance_map.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <stdexcept>
#include <string>

#include "host/device/device_policy.h"
#include "host/device/kernel_call.h"
#include "kernels/layout.h"

namespace ag2gs {

InstanceMapper::InstanceMapper(Runtime& rt)
    : rt_(rt), anchor_cluster_(&rt), ids_(&rt), weights_(&rt), feat_(&rt), alpha_(&rt) {}

void InstanceMapper::set_clusters(const std::vector<int32_t>& anchor_cluster, int children, float min_fraction) {
  if (children < 1) throw std::invalid_argument("instance map: children per anchor must be >= 1");
  if (!(min_fraction >= 0.5f && min_fraction < 1.f))
    throw std::invalid_argument("instance map: min_fraction must lie in [0.5, 1) (at most one cluster may pass it)");
  for (size_t a = 0; a < anchor_cluster.size(); ++a)
    if (anchor_cluster[a] < -1)
      throw std::invalid_argument("instance map: anchor " + std::to_string(a) + " has cluster id " +
                                  std::to_string(anchor_cluster[a]) + " (ids are >= 0, or -1 for none)");
  anchors_ = anchor_cluster.size();
  children_ = children;
  min_fraction_ = min_fraction;
  anchor_cluster_.upload(anchor_cluster);
  have_clusters_ = true;
}

void InstanceMapper::compute(const Renderer& renderer) {
  run(renderer, false);
}

void InstanceMapper::compute_with_images(const Renderer& renderer) {
  run(renderer, true);
}

void InstanceMapper::run(const Renderer& renderer, bool with_images) {
  if (!have_clusters_) throw std::logic_error("InstanceMapper::compute() before set_clusters()");
  const Renderer::DeviceFrame f = renderer.device_frame();
  if (f.n_gaussians != anchors_ * static_cast<size_t>(children_))
    throw std::invalid_argument("instance map: the frame has " + std::to_string(f.n_gaussians) +
                                " Gaussians but the clusters cover " + std::to_string(anchors_) + " anchors x " +
                                std::to_string(children_) +
                                " children; render the expanded model the clusters "
                                "were made for");
  width_ = f.width;
  height_ = f.height;
  const size_t npix = static_cast<size_t>(f.width) * f.height;
  ids_.reserve(npix * 4);
  weights_.reserve(npix * 4);
  char frac[32];
  std::snprintf(frac, sizeof frac, "((float)(%.9g))", static_cast<double>(min_fraction_));
  // Without images the kernel writes neither plane: small placeholders.
  feat_.reserve(with_images ? npix * 12 : 4);
  alpha_.reserve(with_images ? npix * 4 : 4);
  // The renderer's layout: records staged through local memory on GPUs,
  // there with the walk's own pixels per work-item (the same bits at any).
  const int vw = renderer.staged() ? instance_walk_vector_width(rt_.info(), rt_.vector_width()) : rt_.vector_width();
  const int wg = 256 / vw;
  cl::Kernel k = rt_.kernel("instance_map.cl", "instance_map",
                            {{"MIN_FRACTION", frac},
                             {"WITH_IMAGES", with_images ? "1" : "0"},
                             {"NO_STAGING", renderer.staged() ? "0" : "1"},
                             {"VW", std::to_string(vw)},
                             {"BATCH", std::to_string(std::max(64, wg))}});
  const int ntiles = f.tiles_x * f.tiles_y;
  const size_t M = renderer.stats().n_intersections, f4 = sizeof(float);
  KernelCall(k)
      .arg("width", f.width)
      .arg("height", f.height)
      .arg("tiles_x", f.tiles_x)
      .arg("children", children_)
      .buffer("ranges", *f.ranges, static_cast<size_t>(ntiles) * 8)
      .buffer("isect_vals", *f.isect_vals, M * 4)
      .buffer("isect_gid", *f.isect_gid, M * 4)
      .buffer("records", *f.records, f.n_gaussians * REC_SIZE * f4)
      .buffer("anchor_cluster", anchor_cluster_, anchors_ * 4)
      .buffer("out_id", ids_, npix * 4)
      .buffer("out_weight", weights_, npix * f4)
      .buffer("out_feat", feat_, with_images ? npix * 3 * f4 : 0)
      .buffer("out_alpha", alpha_, with_images ? npix * f4 : 0)
      .done();
  rt_.launch("instance_map", k, cl::NDRange(static_cast<size_t>(ntiles) * wg), cl::NDRange(wg));
}

InstanceMap InstanceMapper::download() const {
  InstanceMap m;
  m.width = width_;
  m.height = height_;
  const size_t npix = static_cast<size_t>(width_) * height_;
  ids_.download(m.ids, npix);
  weights_.download(m.weight, npix);
  return m;
}

}  // namespace ag2gs
