#include "host/optim/adam.h"

#include <algorithm>
#include <cmath>
#include <initializer_list>
#include <limits>
#include <map>
#include <stdexcept>

#include "host/device/kernel_call.h"

namespace ag2gs {

namespace {

const std::map<std::string, std::string> kNoDefines;

// The largest power of two no larger than 256, the device's limit and the
// limit of each of the named kernels of adam.cl.
int pick_work_group(Runtime& rt, std::initializer_list<const char*> kernels) {
  size_t limit = std::min<size_t>(256, rt.info().max_work_group);
  for (const char* name : kernels) {
    cl::Kernel k = rt.kernel("adam.cl", name, kNoDefines);
    limit = std::min(limit, k.getWorkGroupInfo<CL_KERNEL_WORK_GROUP_SIZE>(rt.info().device));
  }
  int wg = 1;
  while (static_cast<size_t>(wg) * 2 <= limit) wg *= 2;
  return wg;
}

void check_floats(const DeviceBuffer& b, size_t n, const char* what, const std::string& group) {
  if (b.capacity() < n * sizeof(float))
    throw std::invalid_argument("adam: " + std::string(what) + " buffer of group '" + group + "' holds " +
                                std::to_string(b.capacity() / sizeof(float)) + " floats, the group has " +
                                std::to_string(n));
}

void check_index(const std::vector<int>& index, size_t src_rows) {
  for (size_t r = 0; r < index.size(); ++r)
    if (index[r] < -1 || (index[r] >= 0 && static_cast<size_t>(index[r]) >= src_rows))
      throw std::invalid_argument("gather_rows: index[" + std::to_string(r) + "] = " + std::to_string(index[r]) +
                                  " is outside [-1, " + std::to_string(src_rows) + ")");
}

std::unique_ptr<DeviceBuffer> zero_buffer(Runtime& rt, size_t floats) {
  auto b = std::make_unique<DeviceBuffer>(&rt);
  b->fill_zero(floats * sizeof(float));
  return b;
}

}  // namespace

// ---------------------------------------------------------------- gather

void gather_rows(Runtime& rt, const DeviceBuffer& src, size_t src_rows, DeviceBuffer& dst, const DeviceBuffer& index,
                 size_t out_rows, int row_size) {
  if (row_size <= 0) throw std::invalid_argument("gather_rows: row size must be positive");
  if (&src == &dst) throw std::invalid_argument("gather_rows: source and destination must be different buffers");
  const size_t n = out_rows * row_size;
  if (src.capacity() < src_rows * row_size * sizeof(float))
    throw std::invalid_argument("gather_rows: the source holds fewer than " + std::to_string(src_rows) + " rows");
  if (index.capacity() < out_rows * sizeof(int))
    throw std::invalid_argument("gather_rows: the index buffer holds fewer than " + std::to_string(out_rows) +
                                " entries");
  dst.reserve(std::max<size_t>(n * sizeof(float), 4));
  if (n == 0) return;
  cl::Kernel k = rt.kernel("adam.cl", "gather_rows", kNoDefines);
  KernelCall(k)
      .arg("n_out", static_cast<cl_ulong>(n))
      .arg("row_size", row_size)
      .arg("src_rows", static_cast<cl_ulong>(src_rows))
      .buffer("index", index, out_rows * sizeof(int))
      .buffer("src", src, src_rows * row_size * sizeof(float))
      .buffer("dst", dst, n * sizeof(float))
      .done();
  rt.launch("adam", k, cl::NDRange(n), cl::NDRange(pick_work_group(rt, {"gather_rows"})));
}

void gather_rows(Runtime& rt, const DeviceBuffer& src, size_t src_rows, DeviceBuffer& dst,
                 const std::vector<int>& index, int row_size) {
  check_index(index, src_rows);
  DeviceBuffer idx(&rt);
  idx.upload(index);
  gather_rows(rt, src, src_rows, dst, idx, index.size(), row_size);
  // Releasing idx now is safe: OpenCL frees it after the queued gather ran.
}

// ---------------------------------------------------------------- group

AdamGroup::AdamGroup(Runtime& rt, std::string name, size_t rows, int row_size)
    : rt_(rt), name_(std::move(name)), rows_(rows), row_size_(row_size) {
  if (row_size <= 0) throw std::invalid_argument("adam group '" + name_ + "': row size must be positive");
  m_ = zero_buffer(rt_, size());
  v_ = zero_buffer(rt_, size());
}

void AdamGroup::set_steps(int64_t steps) {
  if (steps < 0) throw std::invalid_argument("adam group '" + name_ + "': negative step count");
  steps_ = steps;
}

void AdamGroup::zero_moments() {
  m_->fill_zero(size() * sizeof(float));
  v_->fill_zero(size() * sizeof(float));
}

void AdamGroup::resize(size_t rows) {
  const size_t old_n = size(), new_n = rows * static_cast<size_t>(row_size_);
  for (auto* b : {&m_, &v_}) {
    if ((*b)->capacity() >= new_n * sizeof(float)) {
      if (new_n > old_n) {
        cl_uint zero = 0;
        AG2GS_CL_CHECK(
            rt_.queue().enqueueFillBuffer((*b)->get(), zero, old_n * sizeof(float), (new_n - old_n) * sizeof(float)));
      }
      continue;
    }
    auto fresh = zero_buffer(rt_, new_n);  // grows: new rows are zero
    if (old_n > 0)
      AG2GS_CL_CHECK(rt_.queue().enqueueCopyBuffer((*b)->get(), fresh->get(), 0, 0, old_n * sizeof(float)));
    *b = std::move(fresh);  // OpenCL frees the old buffer after the copy ran
  }
  rows_ = rows;
}

void AdamGroup::gather(const DeviceBuffer& index, size_t new_rows) {
  for (auto* b : {&m_, &v_}) {
    auto fresh = std::make_unique<DeviceBuffer>(&rt_);
    gather_rows(rt_, **b, rows_, *fresh, index, new_rows, row_size_);
    *b = std::move(fresh);
  }
  rows_ = new_rows;
}

void AdamGroup::gather(const std::vector<int>& index) {
  check_index(index, rows_);
  DeviceBuffer idx(&rt_);
  idx.upload(index);
  gather(idx, index.size());
}

void AdamGroup::park() {
  if (parked_) return;
  m_->download(parked_m_, size());
  v_->download(parked_v_, size());
  m_->release();
  v_->release();
  parked_ = true;
}

void AdamGroup::unpark() {
  if (!parked_) return;
  m_->upload(parked_m_);
  v_->upload(parked_v_);
  parked_m_ = {};
  parked_v_ = {};
  parked_ = false;
}

// ---------------------------------------------------------------- optimiser

Adam::Adam(Runtime& rt, AdamSettings settings) : rt_(rt), settings_(settings), counter_(&rt) {
  const AdamSettings& s = settings_;
  if (!(s.beta1 >= 0 && s.beta1 < 1) || !(s.beta2 >= 0 && s.beta2 < 1) || !(s.eps > 0))
    throw std::invalid_argument("adam: need 0 <= beta1, beta2 < 1 and eps > 0");
  wg_ = pick_work_group(
      rt_, {"adam_step", "adam_step_visible", "adam_step_cols", "count_nonfinite", "count_nonfinite_cols"});
  counter_.fill_zero(sizeof(cl_uint));
}

namespace {

struct StepCoeffs {
  float one_minus_beta1, beta2, one_minus_beta2, eps, step_size, bc2_sqrt;
};

// torch's bias corrections, in double: step_size = lr / (1 - beta1^t),
// bc2_sqrt = sqrt(1 - beta2^t).
StepCoeffs step_coeffs(const AdamSettings& s, int64_t t, double lr) {
  const double bc1 = 1.0 - std::pow(s.beta1, static_cast<double>(t));
  const double bc2 = 1.0 - std::pow(s.beta2, static_cast<double>(t));
  return {static_cast<float>(1.0 - s.beta1), static_cast<float>(s.beta2),  static_cast<float>(1.0 - s.beta2),
          static_cast<float>(s.eps),         static_cast<float>(lr / bc1), static_cast<float>(std::sqrt(bc2))};
}

void check_step(const AdamGroup& g, const DeviceBuffer& param, const DeviceBuffer& grad, double lr) {
  if (!(lr >= 0) || !std::isfinite(lr))
    throw std::invalid_argument("adam: learning rate of group '" + g.name() + "' must be finite and >= 0, got " +
                                std::to_string(lr));
  if (&param == &grad) throw std::invalid_argument("adam: group '" + g.name() + "': param and grad are one buffer");
  check_floats(param, g.size(), "parameter", g.name());
  check_floats(grad, g.size(), "gradient", g.name());
}

// The arguments every step kernel ends with: the group's parameter, gradient
// and moments ([rows, row_size] each) and the step's coefficients.
void step_args(KernelCall& call, DeviceBuffer& param, const DeviceBuffer& grad, AdamGroup& group, const StepCoeffs& c) {
  const size_t bytes = group.size() * sizeof(float);
  call.buffer("param", param, bytes)
      .buffer("grad", grad, bytes)
      .buffer("exp_avg", group.exp_avg(), bytes)
      .buffer("exp_avg_sq", group.exp_avg_sq(), bytes)
      .arg("one_minus_beta1", c.one_minus_beta1)
      .arg("beta2", c.beta2)
      .arg("one_minus_beta2", c.one_minus_beta2)
      .arg("eps", c.eps)
      .arg("step_size", c.step_size)
      .arg("bc2_sqrt", c.bc2_sqrt)
      .done();
}

}  // namespace

void Adam::step(AdamGroup& group, DeviceBuffer& param, const DeviceBuffer& grad, double lr) {
  check_step(group, param, grad, lr);
  const StepCoeffs c = step_coeffs(settings_, group.steps_ + 1, lr);
  ++group.steps_;
  const size_t n = group.size();
  if (n == 0) return;
  cl::Kernel k = rt_.kernel("adam.cl", "adam_step", kNoDefines);
  step_args(KernelCall(k).arg("n", static_cast<cl_ulong>(n)), param, grad, group, c);
  rt_.launch("adam", k, cl::NDRange(n), cl::NDRange(wg_));
}

void Adam::step_cols(AdamGroup& group, DeviceBuffer& param, const DeviceBuffer& grad, double lr, int cols) {
  if (cols < 0 || cols > group.row_size())
    throw std::invalid_argument("adam: group '" + group.name() + "': " + std::to_string(cols) +
                                " columns of a row of " + std::to_string(group.row_size()));
  if (cols == group.row_size()) return step(group, param, grad, lr);
  check_step(group, param, grad, lr);
  const StepCoeffs c = step_coeffs(settings_, group.steps_ + 1, lr);
  ++group.steps_;  // the bias correction counts every step, stepped columns or not
  const size_t n = group.rows() * static_cast<size_t>(cols);
  if (n == 0) return;
  cl::Kernel k = rt_.kernel("adam.cl", "adam_step_cols", kNoDefines);
  step_args(KernelCall(k)
                .arg("rows", static_cast<cl_ulong>(group.rows()))
                .arg("row_size", group.row_size())
                .arg("cols", cols),
            param, grad, group, c);
  launch_cols(k, group.rows(), cols);
}

void Adam::launch_cols(cl::Kernel& k, size_t rows, int cols) {
  // Work-groups of 16 columns (or fewer) by as many rows as make wg_; the
  // runtime rounds the range up to whole work-groups.
  const size_t lx = std::min<size_t>(16, wg_), ly = wg_ / lx;
  rt_.launch("adam", k, cl::NDRange(static_cast<size_t>(cols), rows), cl::NDRange(lx, ly));
}

void Adam::step_visible(AdamGroup& group, DeviceBuffer& param, const DeviceBuffer& grad, double lr,
                        const DeviceBuffer& visible) {
  check_step(group, param, grad, lr);
  if (visible.capacity() < group.rows() * sizeof(int))
    throw std::invalid_argument("adam: the visibility buffer of group '" + group.name() + "' holds fewer than " +
                                std::to_string(group.rows()) + " ints");
  if (group.size() > std::numeric_limits<cl_uint>::max())
    throw std::invalid_argument("adam: group '" + group.name() + "' has 2^32 or more values; split it");
  const StepCoeffs c = step_coeffs(settings_, group.steps_ + 1, lr);
  ++group.steps_;
  const size_t n = group.size();
  if (n == 0) return;
  cl::Kernel k = rt_.kernel("adam.cl", "adam_step_visible", kNoDefines);
  step_args(KernelCall(k)
                .arg("n", static_cast<cl_ulong>(n))
                .arg("row_size", group.row_size())
                .buffer("visible", visible, group.rows() * sizeof(int)),
            param, grad, group, c);
  rt_.launch("adam", k, cl::NDRange(n), cl::NDRange(wg_));
}

void Adam::clear_nonfinite() {
  counter_.fill_zero(sizeof(cl_uint));
}

void Adam::accumulate_nonfinite(const DeviceBuffer& buf, size_t n) {
  if (n == 0) return;
  if (buf.capacity() < n * sizeof(float))
    throw std::invalid_argument("count_nonfinite: the buffer holds fewer than " + std::to_string(n) + " floats");
  if (n > std::numeric_limits<cl_uint>::max())
    throw std::invalid_argument("count_nonfinite: more than 2^32 values in one buffer");
  constexpr size_t kChunk = 16;  // NONFINITE_CHUNK in adam.cl
  const size_t groups = (n + kChunk * wg_ - 1) / (kChunk * wg_);
  cl::Kernel k = rt_.kernel("adam.cl", "count_nonfinite", kNoDefines);
  set_kernel_args(k, static_cast<cl_ulong>(n), buf, counter_);
  rt_.launch("adam", k, cl::NDRange(groups * wg_), cl::NDRange(wg_));
}

void Adam::accumulate_nonfinite_cols(const DeviceBuffer& buf, size_t rows, int row_size, int cols) {
  if (cols < 0 || cols > row_size)
    throw std::invalid_argument("count_nonfinite: " + std::to_string(cols) + " columns of a row of " +
                                std::to_string(row_size));
  if (cols == row_size) return accumulate_nonfinite(buf, rows * static_cast<size_t>(row_size));
  const size_t n = rows * static_cast<size_t>(cols);
  if (n == 0) return;
  if (buf.capacity() < rows * static_cast<size_t>(row_size) * sizeof(float))
    throw std::invalid_argument("count_nonfinite: the buffer holds fewer than " + std::to_string(rows) + " rows");
  if (rows * static_cast<size_t>(row_size) > std::numeric_limits<cl_uint>::max())
    throw std::invalid_argument("count_nonfinite: more than 2^32 values in one buffer");
  cl::Kernel k = rt_.kernel("adam.cl", "count_nonfinite_cols", kNoDefines);
  KernelCall(k)
      .arg("rows", static_cast<cl_ulong>(rows))
      .arg("row_size", row_size)
      .arg("cols", cols)
      .buffer("v", buf, rows * static_cast<size_t>(row_size) * sizeof(float))
      .buffer("count", counter_, sizeof(cl_uint))
      .done();
  launch_cols(k, rows, cols);
}

uint64_t Adam::read_nonfinite() {
  std::vector<cl_uint> c;
  counter_.download(c, 1);
  return c[0];
}

uint64_t Adam::count_nonfinite(const DeviceBuffer& buf, size_t n) {
  clear_nonfinite();
  accumulate_nonfinite(buf, n);
  return read_nonfinite();
}

}  // namespace ag2gs
