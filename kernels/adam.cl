// Adam as torch.optim.Adam computes it (no weight decay, no amsgrad), one
// parameter group per launch, and the buffer housekeeping around it: a
// non-finite check of gradients and a row gather for adding/removing rows.
//
// Step t (the host passes step_size = lr / (1 - beta1^t) and
// bc2_sqrt = sqrt(1 - beta2^t), computed in double):
//   m = m + (1 - beta1) (g - m)              (torch: exp_avg.lerp_(grad, 1 - beta1))
//   v = beta2 v + (1 - beta2) g^2
//   p = p - step_size m / (sqrt(v) / bc2_sqrt + eps)
// which is p - lr mhat / (sqrt(vhat) + eps) with mhat = m / (1 - beta1^t),
// vhat = v / (1 - beta2^t).
// The float coefficients 1 - beta1 and 1 - beta2 are rounded from double, as
// torch rounds its Python scalars.

inline void adam_update(size_t i, __global float* param, __global const float* grad, __global float* exp_avg,
                        __global float* exp_avg_sq, float one_minus_beta1, float beta2, float one_minus_beta2,
                        float eps, float step_size, float bc2_sqrt) {
  const float g = grad[i];
  float m = exp_avg[i];
  m = m + one_minus_beta1 * (g - m);
  const float v = beta2 * exp_avg_sq[i] + one_minus_beta2 * (g * g);
  exp_avg[i] = m;
  exp_avg_sq[i] = v;
  const float denom = sqrt(v) / bc2_sqrt + eps;
  param[i] = param[i] - step_size * (m / denom);
}

__kernel void adam_step(ulong n,
                        __global float* param,       // [n]
                        __global const float* grad,  // [n]
                        __global float* exp_avg,     // [n] first moment
                        __global float* exp_avg_sq,  // [n] second moment
                        float one_minus_beta1, float beta2, float one_minus_beta2, float eps, float step_size,
                        float bc2_sqrt) {
  const size_t i = get_global_id(0);
  if (i >= n) return;
  adam_update(i, param, grad, exp_avg, exp_avg_sq, one_minus_beta1, beta2, one_minus_beta2, eps, step_size,
              bc2_sqrt);
}

// Sparse variant (3DGS's sparse Adam): rows whose visible flag is 0 keep their
// parameters and moments.
__kernel void adam_step_visible(ulong n, int row_size,
                                __global const int* visible,  // [n / row_size] nonzero: update the row
                                __global float* param,        // [n]
                                __global const float* grad,   // [n]
                                __global float* exp_avg,      // [n]
                                __global float* exp_avg_sq,   // [n]
                                float one_minus_beta1, float beta2, float one_minus_beta2, float eps,
                                float step_size, float bc2_sqrt) {
  const size_t i = get_global_id(0);
  // n < 2^32 (checked by the host): a 32-bit division.
  if (i >= n || visible[(uint)i / (uint)row_size] == 0) return;
  adam_update(i, param, grad, exp_avg, exp_avg_sq, one_minus_beta1, beta2, one_minus_beta2, eps, step_size,
              bc2_sqrt);
}

// Prefix variant: each row of row_size values steps only its first `cols`.
// The trainer steps the SH coefficients of the degrees switched on so far;
// the others have had only zero gradients, so their moments are zero and a
// full step would leave them as they are. A 2-D range: column
// get_global_id(0) (< cols) of row get_global_id(1) (< rows), both ranges
// rounded up to the work-group's shape; the work-items of a work-group row
// read consecutive values (vector loads on CPUs, coalesced on GPUs) with no
// division to find their row.
__kernel void adam_step_cols(ulong rows, int row_size, int cols,
                             __global float* param,       // [rows, row_size]
                             __global const float* grad,  // [rows, row_size]
                             __global float* exp_avg,     // [rows, row_size]
                             __global float* exp_avg_sq,  // [rows, row_size]
                             float one_minus_beta1, float beta2, float one_minus_beta2, float eps, float step_size,
                             float bc2_sqrt) {
  const size_t c = get_global_id(0), r = get_global_id(1);
  if (c >= (size_t)cols || r >= rows) return;
  adam_update(r * (size_t)row_size + c, param, grad, exp_avg, exp_avg_sq, one_minus_beta1, beta2, one_minus_beta2,
              eps, step_size, bc2_sqrt);
}

// Whether a float is NaN or Inf by its exponent bits, which do not depend
// on the compiler's isfinite under relaxed-math options.
inline int nonfinite(float x) { return (as_uint(x) & 0x7f800000u) == 0x7f800000u; }

#define NONFINITE_CHUNK 16
// Adds the number of NaN/Inf values of v to *count. Each work-item checks
// NONFINITE_CHUNK values, strided by the group size (coalesced on GPUs);
// integer atomics make the count exact whatever the order.
__kernel void count_nonfinite(ulong n,
                              __global const float* v,  // [n]
                              __global uint* count) {   // [1] accumulated
  const size_t lsize = get_local_size(0);
  const size_t base = get_group_id(0) * lsize * NONFINITE_CHUNK + get_local_id(0);
  uint c = 0;
  for (int k = 0; k < NONFINITE_CHUNK; ++k) {
    const size_t i = base + k * lsize;
    if (i >= n) break;
    if (nonfinite(v[i])) ++c;
  }
  if (c != 0) atomic_add(count, c);
}

// The same over the first `cols` values of each row of row_size, in
// adam_step_cols' 2-D range: one value per work-item.
__kernel void count_nonfinite_cols(ulong rows, int row_size, int cols,
                                   __global const float* v,  // [rows, row_size]
                                   __global uint* count) {   // [1] accumulated
  const size_t c = get_global_id(0), r = get_global_id(1);
  if (c >= (size_t)cols || r >= rows) return;
  if (nonfinite(v[r * (size_t)row_size + c])) atomic_inc(count);
}

// dst row r = src row index[r]; index -1 gives a row of zeros (a new row),
// an index outside [-1, src_rows) a row of NaN (a bug made visible).
__kernel void gather_rows(ulong n_out,  // rows of dst * row_size
                          int row_size, ulong src_rows,
                          __global const int* index,  // [n_out / row_size]
                          __global const float* src,  // [src_rows, row_size]
                          __global float* dst) {      // [n_out / row_size, row_size]
  const size_t i = get_global_id(0);
  if (i >= n_out) return;
  const size_t r = i / (size_t)row_size, c = i % (size_t)row_size;
  const int s = index[r];
  float v;
  if (s == -1)
    v = 0.f;
  else if (s >= 0 && (ulong)s < src_rows)
    v = src[(size_t)s * row_size + c];
  else
    v = NAN;
  dst[i] = v;
}
