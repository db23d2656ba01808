// Instance map of every anchor cluster in one pass (train/stage3/instance_map.h).
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
// GPU layout (NO_STAGING 0): the work-group stages each batch of BATCH
// records and their clusters through local memory, as blend_fwd does, so a
// record is read from global memory once per tile, not once per pixel. The
// CPU layout (NO_STAGING 1) reads them from cache. Same arithmetic per pixel
// either way, so the same bits.
//
// Defines: MIN_FRACTION (float literal), WITH_IMAGES (0 or 1), NO_STAGING,
// BATCH (with staging).

// One list entry at this work-item's pixels, as blend_fwd blends it, from
// its exponent sigma (the walks skip the entries out_of_reach, as
// blend_fwd does): the weight w (0 where the entry does not blend), with T
// and done advanced.
ALWAYS_INLINE vfloat instance_weight(vfloat sigma, float o, vfloat* T, vint* done, vint* okp) {
  const vfloat alpha = fmin(o * blend_falloff(sigma), ALPHA_MAX);
  vint ok = NOT(*done) & (sigma >= 0.f) & (alpha >= ALPHA_MIN);
  const vfloat Tn = *T * (1.f - alpha);
  const vint stop = ok & (Tn < T_MIN);
  *done = *done | stop;
  ok = ok & NOT(stop);
  const vfloat w = select((vfloat)0.f, alpha * *T, ok);
  *T = select(*T, Tn, ok);
  *okp = ok;
  return w;
}
// The CPU layout's sigma of record q at this work-item's pixels; the walk
// goes on to the next record where it is out of reach.
#define SIGMA_OR_NEXT(q)                                                                                         \
  const vfloat sigma = blend_sigma((q)[REC_CA], (q)[REC_CB], (q)[REC_CC], (q)[REC_U] - pr.px, (q)[REC_V] - pr.py); \
  if (out_of_reach(sigma, (q)[REC_THR])) continue;

// Walk 1's weighted majority vote. Against a different cluster the heavier
// side keeps the surplus; a tie leaves surplus 0, and the next vote wins.
typedef struct {
  vint cand;       // -1: none yet
  vfloat surplus;
  vint last_cand;  // last list entry that added to the final candidate
  vint contested;  // another cluster voted: walk 2 must sum the candidate
} Vote;

ALWAYS_INLINE void vote(Vote* s, int k, vfloat w, vint ok, int j) {
  if (k < 0) return;  // unclustered: occludes, does not vote
  const vint same = s->cand == k;
  const vint wins = NOT(same) & (w > s->surplus);
  const vfloat next = select(select(s->surplus - w, w - s->surplus, wins), s->surplus + w, same);
  s->contested = s->contested | (ok & NOT(same) & (s->cand >= 0));
  s->surplus = select(s->surplus, next, ok);
  s->cand = select(s->cand, (vint)k, ok & wins);
  s->last_cand = select(s->last_cand, (vint)j, ok & (same | wins));
}

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
#if !NO_STAGING
  __local float s_rec[BATCH * REC_SIZE];
  __local int s_k[BATCH];
  __local uint s_reach[BATCH];                     // tile_reached
  __local uint s_list[REACH_LISTS * LIST_WORDS];  // reach_lists
  __local int s_alive, s_end;
  const int lid = get_local_id(0);
  __local const uint *rows = ROW_LIST(pr), *cols = COL_LIST(pr);
  // Stage entries [b0, b0 + nb) of the tile's list; s_alive = 1 when a pixel
  // of the group still blends (alive: this work-item's).
#define STAGE_BATCH(b0, nb, alive)                                                                          \
  barrier(CLK_LOCAL_MEM_FENCE);                                                                            \
  if (lid == 0) s_alive = 0;                                                                               \
  for (int i = lid; i < (nb); i += WG_SIZE) {                                                              \
    const uint gid = isect_gid[isect_vals[range.x + (b0) + i]];                                            \
    stage_record(s_rec, i, records, gid);                                                                  \
    s_k[i] = anchor_cluster[gid / (uint)children];                                                         \
    s_reach[i] = tile_reached(s_rec + i * REC_SIZE, pr.tile, tiles_x);                                     \
  }                                                                                                        \
  barrier(CLK_LOCAL_MEM_FENCE);                                                                            \
  reach_lists(s_reach, nb, s_list, lid);                                                                   \
  if (alive) atomic_or(&s_alive, 1);                                                                       \
  barrier(CLK_LOCAL_MEM_FENCE);
#endif

  // Walk 1: the vote, and with WITH_IMAGES the feature planes as blend_fwd
  // sums them (same weights, same order).
  Vote s;
  s.cand = -1;
  s.surplus = 0.f;
  s.last_cand = -1;
  s.contested = 0;
#if WITH_IMAGES
  vfloat f0 = 0.f, f1 = 0.f, f2 = 0.f;
#endif
  vfloat T = 1.f;
  {
    vint done = NOT(pr.inside), ok;
#if NO_STAGING
    for (int j = 0; j < n; ++j) {
      const uint gid = isect_gid[isect_vals[range.x + j]];
      __global const float* q = records + (size_t)gid * REC_SIZE;
      const int k = anchor_cluster[gid / (uint)children];
      SIGMA_OR_NEXT(q)
      {
#else
    for (int b0 = 0; b0 < n; b0 += BATCH) {
      const int nb = min(BATCH, n - b0);
      STAGE_BATCH(b0, nb, ANY(NOT(done)))
      if (!s_alive) break;
      // The records that may reach this work-item's pixels, in list order.
      for (int wd = 0, jj; wd < LIST_WORDS && ANY(NOT(done)); ++wd)
      for (uint m = rows[wd] & cols[wd];;) {
        vfloat sigma;
        jj = next_in_reach(&m, wd, s_rec, pr, &sigma);
        if (jj < 0) break;
        const int j = b0 + jj;
        __local const float* q = s_rec + jj * REC_SIZE;
        const int k = s_k[jj];
#endif
        const vfloat w = instance_weight(sigma, q[REC_OPACITY], &T, &done, &ok);
        // Where no lane blended, the sums would add zeros and the vote
        // change nothing.
        if (ANY(ok)) {
#if WITH_IMAGES
          f0 += w * q[REC_FEAT]; f1 += w * q[REC_FEAT + 1]; f2 += w * q[REC_FEAT + 2];
#endif
          vote(&s, k, w, ok, j);
        }
        if (!ANY(NOT(done))) break;
      }
    }
  }
  // Walk 2: the candidate's total weight, summed in blending order. After
  // the final candidate took over, each of its contributions moved
  // last_cand, so nothing of it lies beyond: the walk ends there. A pixel
  // where no other cluster ever voted needs no walk 2: its surplus is
  // 0 + w_1 + w_2 + ... over the candidate's Gaussians in blending order
  // (the first vote gives w_1 - 0), the very sum walk 2 would make, bit for
  // bit; only contested pixels walk again (at an object's edge, say).
  // Walk 1 also bounds the candidate: its weight not in the surplus was
  // cancelled by as much weight of other clusters, so W_cand <= (total +
  // surplus) / 2 with total = 1 - T. Where that bound, widened by the float
  // rounding of n steps (8 ulps of 1 per step, more than the surplus's, the
  // product's and walk 2's sum's errors together), stays below MIN_FRACTION,
  // no cluster passes and walk 2 is skipped: a cluttered ray with no majority.
  const vfloat bound = 0.5f * ((1.f - T) + s.surplus);
  const vint no_majority = (bound + (float)(n + 4) * 0x1p-21f) < MIN_FRACTION;
  const vint again = s.contested & (s.cand >= 0) & pr.inside & NOT(no_majority);
  int end = 0;
#if VW == 1
  end = again ? s.last_cand + 1 : 0;
#else
  {
    int lc[VW];
    VSTORE(select((vint)-1, s.last_cand, again), lc);
    for (int l = 0; l < VW; ++l) end = max(end, lc[l] + 1);
  }
#endif
  vfloat weight = select((vfloat)0.f, select(bound, s.surplus, NOT(s.contested)), (s.cand >= 0) & NOT(again));
  {
    vfloat T2 = 1.f;  // walk 2's own (walk 1's T gives the alpha below)
    vint done = NOT(again), ok;
#if NO_STAGING
    for (int j = 0; j < end; ++j) {
      const uint gid = isect_gid[isect_vals[range.x + j]];
      __global const float* q = records + (size_t)gid * REC_SIZE;
      const int k = anchor_cluster[gid / (uint)children];
      SIGMA_OR_NEXT(q)
      {
#else
    barrier(CLK_LOCAL_MEM_FENCE);
    if (lid == 0) s_end = 0;
    barrier(CLK_LOCAL_MEM_FENCE);
    atomic_max(&s_end, end);
    barrier(CLK_LOCAL_MEM_FENCE);
    const int group_end = s_end;
    for (int b0 = 0; b0 < group_end; b0 += BATCH) {
      const int nb = min(BATCH, group_end - b0);
      STAGE_BATCH(b0, nb, b0 < end && ANY(NOT(done)))
      if (!s_alive) break;
      if (b0 >= end) continue;
      // The same records before end.
      const int stop = min(nb, end - b0);
      for (int wd = 0, jj = 0; wd < LIST_WORDS && jj < stop && ANY(NOT(done)); ++wd)
      for (uint m = rows[wd] & cols[wd];;) {
        vfloat sigma;
        jj = next_in_reach(&m, wd, s_rec, pr, &sigma);
        if (jj < 0 || jj >= stop) break;  // (jj -1: on to the next word)
        __local const float* q = s_rec + jj * REC_SIZE;
        const int k = s_k[jj];
#endif
        const vfloat w = instance_weight(sigma, q[REC_OPACITY], &T2, &done, &ok);
        weight += select((vfloat)0.f, w, ok & (s.cand == k));
        if (!ANY(NOT(done))) break;
      }
    }
  }
  vint id = select((vint)-1, s.cand, (s.cand >= 0) & (weight > MIN_FRACTION));
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
