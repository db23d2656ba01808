// Adam on the device (kernels/adam.cl), the update of torch.optim.Adam
// (weight decay 0, no amsgrad), one parameter group at a time: the trainer
// keeps each group (offsets, scales, rotations, opacity, SH dc, SH rest,
// semantic features) in its own device buffer with its own learning rate,
// which may change every iteration. Step t of a group:
//   m = beta1 m + (1 - beta1) g,   v = beta2 v + (1 - beta2) g^2
//   p = p - lr (m / (1 - beta1^t)) / (sqrt(v / (1 - beta2^t)) + eps)
// The step counter t belongs to the group, as torch keeps state["step"] per
// tensor. Also: a deterministic count of non-finite gradient values (so the
// trainer can skip a whole step), moment reset, and row gather/resize for
// when rows are added or removed (densification, pruning).
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "host/device/cl_runtime.h"

namespace ag2gs {

struct AdamSettings {
  double beta1 = 0.9;
  double beta2 = 0.999;
  double eps = 1e-15;  // 3DGS's value (torch's default is 1e-8)
};

// The learning rates of a Gaussian's appearance and shape groups, 3DGS's
// values, which the anchor trainer (TrainConfig) and the free-Gaussian
// baseline (FreeTrainConfig) both start from: SH DC, the higher SH bands,
// the opacity and scale logits, the rotation.
struct GaussianRates {
  double sh_dc_lr = 0.0025;
  double sh_rest_lr = 0.0025 / 20;
  double opacity_lr = 0.05;
  double scaling_lr = 0.005;
  double rotation_lr = 0.001;
};

// The optimiser state of one parameter group: first and second moments
// [rows, row_size] on the device (zero at creation) and the step count.
class AdamGroup {
 public:
  AdamGroup(Runtime& rt, std::string name, size_t rows, int row_size);

  const std::string& name() const { return name_; }
  size_t rows() const { return rows_; }
  int row_size() const { return row_size_; }
  size_t size() const { return rows_ * static_cast<size_t>(row_size_); }
  int64_t steps() const { return steps_; }
  void set_steps(int64_t steps);  // e.g. when restoring a checkpoint

  DeviceBuffer& exp_avg() { return *m_; }     // [rows, row_size]
  DeviceBuffer& exp_avg_sq() { return *v_; }  // [rows, row_size]

  // Zero both moments, keep the step count (3DGS's opacity reset does this).
  void zero_moments();
  // Keep the first min(old, new) rows, zero the moments of added rows.
  void resize(size_t rows);
  // New row r = old row index[r]; index -1 makes a new row with zero
  // moments. index: [new_rows] ints on the device, or a host vector that is
  // checked (every entry in [-1, rows)) before upload.
  void gather(const DeviceBuffer& index, size_t new_rows);
  void gather(const std::vector<int>& index);

  // Moves both moments into host memory and frees their device buffers;
  // unpark() brings them back, the same bits. Between the two the group
  // must not be stepped, gathered or read. For a simulator, whose every
  // launch costs in proportion to the device memory held (Runtime::
  // simulated), while a long run of launches needs no optimiser.
  void park();
  void unpark();
  bool parked() const { return parked_; }

 private:
  friend class Adam;  // advances steps_
  Runtime& rt_;
  std::string name_;
  size_t rows_;
  int row_size_;
  int64_t steps_ = 0;
  std::unique_ptr<DeviceBuffer> m_, v_;
  bool parked_ = false;
  std::vector<float> parked_m_, parked_v_;
};

class Adam {
 public:
  explicit Adam(Runtime& rt, AdamSettings settings = {});
  const AdamSettings& settings() const { return settings_; }

  // One step for a group: param and grad hold group.size() floats; lr is this
  // step's learning rate (schedules are the caller's). Increments steps().
  void step(AdamGroup& group, DeviceBuffer& param, const DeviceBuffer& grad, double lr);
  // The same, but only the first `cols` values of each row change (0 <= cols
  // <= row_size; cols == row_size is step above). For columns whose gradient
  // has always been zero, so that their moments are zero too, this gives
  // the bits of the full step: such a value does not move.
  void step_cols(AdamGroup& group, DeviceBuffer& param, const DeviceBuffer& grad, double lr, int cols);
  // Sparse step (3DGS's sparse Adam): only rows with visible[row] != 0 change,
  // parameters and moments of the other rows are left as they are; the step
  // count (bias correction) advances for the whole group, as in gsplat's
  // SelectiveAdam. visible: [rows] ints (the renderer's radii [N] qualify).
  void step_visible(AdamGroup& group, DeviceBuffer& param, const DeviceBuffer& grad, double lr,
                    const DeviceBuffer& visible);

  // Non-finite values (NaN, +-Inf) among the first n floats of a buffer.
  // Exact and deterministic; one host synchronisation.
  uint64_t count_nonfinite(const DeviceBuffer& buf, size_t n);
  // The same for several buffers with a single synchronisation: clear,
  // accumulate each gradient buffer, then read the total.
  void clear_nonfinite();
  void accumulate_nonfinite(const DeviceBuffer& buf, size_t n);
  // Only the first `cols` values of each of `rows` rows of row_size.
  void accumulate_nonfinite_cols(const DeviceBuffer& buf, size_t rows, int row_size, int cols);
  uint64_t read_nonfinite();

  int work_group() const { return wg_; }

 private:
  // Launches a kernel of adam.cl's 2-D column range over the first `cols`
  // columns of `rows` rows (adam_step_cols, count_nonfinite_cols).
  void launch_cols(cl::Kernel& k, size_t rows, int cols);

  Runtime& rt_;
  AdamSettings settings_;
  int wg_ = 64;
  DeviceBuffer counter_;
};

// dst row r = src row index[r] for r < out_rows, on [rows, row_size] float
// buffers (a separate dst: the gather is not in place). index -1 writes a row
// of zeros; an index outside [-1, src_rows) writes NaN. dst grows as needed.
void gather_rows(Runtime& rt, const DeviceBuffer& src, size_t src_rows, DeviceBuffer& dst, const DeviceBuffer& index,
                 size_t out_rows, int row_size);
// Host index list, checked before upload (throws naming the bad entry).
void gather_rows(Runtime& rt, const DeviceBuffer& src, size_t src_rows, DeviceBuffer& dst,
                 const std::vector<int>& index, int row_size);

}  // namespace ag2gs
