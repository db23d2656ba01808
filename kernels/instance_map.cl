// Instance map of every anchor cluster in one pass (stages/instance_map.h).
// Reads the renderer's frame (Renderer::device_frame(): the same tile ranges,
// depth-sorted intersections and projected records blend_fwd.cl walks) and
// repeats blend_fwd's per-Gaussian decisions operation for operation, so the
// blending weights w_i = alpha_i T_i here are bit-identical to the rendered
// ones (same VW, same helpers, FP_CONTRACT OFF in common.cl).
//
// Pixel p belongs to cluster c when W_c(p) = sum of w_i over c's Gaussians
// exceeds MIN_FRACTION (>= 0.5). The w_i of a ray sum to 1 - T <= 1, so at
// most one cluster can pass 0.5 and it then holds more than half of the ray's
// total weight: a weighted Boyer-Moore majority vote over the ray (state: one
// candidate and its surplus) ends on that cluster whenever it exists. Walk 1
// votes, walk 2 sums the candidate's weight exactly, front to back in the
// blending order. Unclustered Gaussians (id -1) occlude but do not vote.
// Float rounding of the surplus only matters when W_c is within a few ulps
// times the ray length of 0.5, where the float sum itself is ambiguous.
//
// With WITH_IMAGES 1, walk 1 also sums the feature planes and the alpha as
// blend_fwd does (same weights, same order, so the same bits): a view needs
// Renderer::bin() alone instead of a whole forward pass before this kernel.
//
// Defines: MIN_FRACTION (float literal), WITH_IMAGES (0 or 1).

// Gaussian id of list entry j of this tile and its cluster (children inherit
// their anchor's cluster: anchor = gid / children).
#define INSTANCE_STEP                                                                  \
  uint gid = isect_gid[isect_vals[range.x + j]];                                       \
  __global const float* q = records + (size_t)gid * REC_SIZE;                          \
  const int k = anchor_cluster[gid / (uint)children];                                  \
  vfloat dx = q[REC_U] - pr.px;                                                        \
  float dy = q[REC_V] - pr.py;                                                         \
  vfloat sigma = blend_sigma(q[REC_CA], q[REC_CB], q[REC_CC], dx, dy);                 \
  vfloat alpha = fmin(q[REC_OPACITY] * blend_falloff(sigma), ALPHA_MAX);               \
  vint ok = NOT(done) & (sigma >= 0.f) & (alpha >= ALPHA_MIN);                         \
  vfloat Tn = T * (1.f - alpha);                                                       \
  vint stop = ok & (Tn < T_MIN);                                                       \
  done = done | stop;                                                                  \
  ok = ok & NOT(stop);                                                                 \
  vfloat w = select((vfloat)0.f, alpha * T, ok);                                       \
  T = select(T, Tn, ok);

__kernel __attribute__((reqd_work_group_size(WG_SIZE, 1, 1)))
void instance_map(int width, int height, int tiles_x, int children,
                  __global const int2* ranges,          // [tiles] [start, end) into isect_vals
                  __global const uint* isect_vals,      // [M] sorted: intersection slot
                  __global const uint* isect_gid,       // [M] by slot: Gaussian id
                  __global const float* records,        // [N,REC_SIZE]
                  __global const int* anchor_cluster,   // [N / children] cluster id, -1 = none
                  __global int* out_id,                 // [H,W] cluster id, -1 = none
                  __global float* out_weight,           // [H,W] weight of the vote's candidate
                  __global float* out_feat,             // [3,H,W] with WITH_IMAGES: blend_fwd's feature
                  __global float* out_alpha) {          // [H,W] with WITH_IMAGES: blend_fwd's alpha
  PixelRow pr = pixel_row(tiles_x, width, height);
  const int2 range = ranges[pr.tile];
  const int n = range.y - range.x;

  // Walk 1: weighted majority vote. Against a different cluster the heavier
  // side keeps the surplus; a tie leaves surplus 0, and the next vote wins.
  vint cand = -1;
  vfloat surplus = 0.f;
  vint last_cand = -1;  // last list entry that added to the final candidate
  vint contested = 0;   // another cluster voted: walk 2 must sum the candidate
#if WITH_IMAGES
  vfloat f0 = 0.f, f1 = 0.f, f2 = 0.f;
#endif
  vfloat T = 1.f;
  {
    vint done = NOT(pr.inside);
    for (int j = 0; j < n; ++j) {
      INSTANCE_STEP
#if WITH_IMAGES
      f0 += w * q[REC_FEAT]; f1 += w * q[REC_FEAT + 1]; f2 += w * q[REC_FEAT + 2];
#endif
      if (k >= 0) {
        vint same = cand == k;
        vint wins = NOT(same) & (w > surplus);
        vfloat next = select(select(surplus - w, w - surplus, wins), surplus + w, same);
        surplus = select(surplus, next, ok);
        contested = contested | (ok & NOT(same) & (cand >= 0));
        cand = select(cand, (vint)k, ok & wins);
        last_cand = select(last_cand, (vint)j, ok & (same | wins));
      }
      if (!ANY(NOT(done))) break;
    }
  }
  // Walk 2: the candidate's total weight, summed in blending order. After
  // the final candidate took over, each of its contributions moved
  // last_cand, so nothing of it lies beyond: the walk ends there. A pixel
  // where no other cluster ever voted needs no walk 2: its surplus is
  // 0 + w_1 + w_2 + ... over the candidate's Gaussians in blending order
  // (the first vote gives w_1 - 0), the very sum walk 2 would make, bit for
  // bit; only contested pixels walk again (at an object's edge, say).
  const vint again = contested & (cand >= 0) & pr.inside;
  int end = 0;
#if VW == 1
  end = again ? last_cand + 1 : 0;
#else
  {
    int lc[VW];
    VSTORE(select((vint)-1, last_cand, again), lc);
    for (int l = 0; l < VW; ++l) end = max(end, lc[l] + 1);
  }
#endif
  vfloat weight = select((vfloat)0.f, surplus, (cand >= 0) & NOT(again));
  {
    vfloat T = 1.f;  // walk 2's own (walk 1's T gives the alpha below)
    vint done = NOT(again);
    for (int j = 0; j < end; ++j) {
      INSTANCE_STEP
      weight += select((vfloat)0.f, w, ok & (cand == k));
      if (!ANY(NOT(done))) break;
    }
  }
  vint id = select((vint)-1, cand, (cand >= 0) & (weight > MIN_FRACTION));
  store_row_int(id, out_id, pr, width);
  store_row(weight, out_weight, pr, width);
#if WITH_IMAGES
  const size_t npix = (size_t)width * height;
  store_row(f0, out_feat, pr, width);
  store_row(f1, out_feat + npix, pr, width);
  store_row(f2, out_feat + 2 * npix, pr, width);
  store_row(1.f - T, out_alpha, pr, width);
#endif
}
