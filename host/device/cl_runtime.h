// OpenCL device runtime: device discovery and selection, one context + queue,
// program assembly (defines + common.cl + kernel file) with an in-memory and
// an on-disk cache, a checked-call macro, growable buffers and kernel timing.
#pragma once

#include <CL/opencl.hpp>
#include <cstdint>
#include <cstdio>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <stdexcept>
#include <string>
#include <type_traits>
#include <utility>
#include <vector>

namespace ag2gs {

// An OpenCL call failed: names the call, the error and file:line.
class ClError : public std::runtime_error {
 public:
  ClError(cl_int code, const std::string& call, const char* file, int line);
  cl_int code() const { return code_; }

 private:
  cl_int code_;
};

const char* cl_error_name(cl_int code);

#define AG2GS_CL_CHECK(call)                                                                     \
  do {                                                                                           \
    cl_int ag2gs_err_ = (call);                                                                  \
    if (ag2gs_err_ != CL_SUCCESS) throw ::ag2gs::ClError(ag2gs_err_, #call, __FILE__, __LINE__); \
  } while (0)

// A kernel program failed to build: program name, options and full log.
class BuildError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

struct DeviceInfo {
  int index = 0;  // global index across platforms (what --device takes)
  std::string platform, name, vendor, version, driver;
  bool is_gpu = false, is_cpu = false;
  unsigned compute_units = 0;
  uint64_t global_mem = 0, local_mem = 0, max_alloc = 0;
  size_t max_work_group = 0;
  bool fp64 = false;
  bool correct_div = false;  // CL_FP_CORRECTLY_ROUNDED_DIVIDE_SQRT: kernels build with it (same bits in every kernel)
  unsigned native_float_width = 0;  // CL_DEVICE_NATIVE_VECTOR_WIDTH_FLOAT (PoCL: 8 with AVX2, 16 with AVX-512)
  cl::Device device;
};

std::vector<DeviceInfo> list_devices();
// Resolves -1 to $AG2GS_DEVICE, then to the default. Throws when out of range.
int resolve_device_index(int requested, const std::vector<DeviceInfo>& devices);

class Runtime {
 public:
  // device_index -1: $AG2GS_DEVICE or the default device.
  explicit Runtime(int device_index = -1);
  ~Runtime();
  Runtime(const Runtime&) = delete;
  Runtime& operator=(const Runtime&) = delete;

  const DeviceInfo& info() const { return info_; }
  cl::Context& context() { return context_; }
  cl::CommandQueue& queue() { return queue_; }
  // Pixels per work-item in the blending kernels: 16 on CPUs (explicit SIMD
  // vectors), 1 on GPUs. $AG2GS_VECTOR_WIDTH overrides (1, 4, 8 or 16).
  int vector_width() const { return vector_width_; }

  // Builds (or fetches from cache) kernels/<file> assembled as
  // "#define"s of `defines` + common.cl + the file.
  cl::Program program(const std::string& file, const std::map<std::string, std::string>& defines);
  cl::Kernel kernel(const std::string& file, const std::string& name,
                    const std::map<std::string, std::string>& defines);

  // Enqueue with optional timing; global size rounded up to the local size.
  // With $AG2GS_LAUNCH_LOG set, every launch appends "<kernel> vw=<width>" to
  // that file (the oclgrind tests check from it that every kernel ran).
  void launch(const std::string& label, cl::Kernel& k, const cl::NDRange& global,
              const cl::NDRange& local = cl::NullRange);

  // Per-label times in ms, summed since the last reset (profiling events).
  // With by_kernel, every kernel's own time is also kept, as "kernel:<name>".
  void set_profiling(bool on, bool by_kernel = false) {
    profiling_ = on;
    by_kernel_ = on && by_kernel;
  }
  std::map<std::string, double> take_timings();

  // Bytes currently allocated through DeviceBuffer, and the peak.
  uint64_t allocated_bytes() const { return allocated_; }
  uint64_t peak_bytes() const { return peak_; }
  void reset_peak() { peak_ = allocated_; }
  void on_alloc(int64_t delta);
  // Buffers grow to what is asked, without headroom: on a simulator, whose
  // every launch costs time in proportion to all allocated bytes (Oclgrind's
  // race detector clears a record of each one), spare capacity is not free.
  bool exact_allocations() const { return exact_allocations_; }
  // Whether the device is a simulator (Oclgrind): work that only pays for
  // itself there (holding less memory between launches, wider walks) asks.
  bool simulated() const { return exact_allocations_; }

  static std::string cache_dir();

 private:
  DeviceInfo info_;
  cl::Context context_;
  cl::CommandQueue queue_;
  int vector_width_ = 1;
  bool exact_allocations_ = false;
  bool profiling_ = false, by_kernel_ = false;
  std::map<std::string, cl::Program> programs_;
  std::map<std::string, cl::Kernel> kernels_;  // by file|name|defines
  struct PendingEvent {
    std::string label, kernel;  // kernel: set with by_kernel_
    cl::Event event;
  };
  std::vector<PendingEvent> pending_events_;
  std::map<std::string, double> timings_;
  uint64_t allocated_ = 0, peak_ = 0;
  std::mutex mutex_;
  std::FILE* launch_log_ = nullptr;  // $AG2GS_LAUNCH_LOG, opened for appending
};

// A device buffer that grows on demand (never shrinks unless released);
// contents are not preserved across growth. In test builds
// (AG2GS_FILL_SENTINEL=1 in the environment) fresh memory is filled with a
// NaN sentinel.
class DeviceBuffer {
 public:
  DeviceBuffer() = default;
  explicit DeviceBuffer(Runtime* rt) : rt_(rt) {}
  ~DeviceBuffer();
  DeviceBuffer(const DeviceBuffer&) = delete;
  DeviceBuffer& operator=(const DeviceBuffer&) = delete;

  void bind(Runtime* rt) { rt_ = rt; }
  // Ensures capacity for `bytes`; returns true when reallocated.
  bool reserve(size_t bytes);
  cl::Buffer& get() { return buffer_; }
  size_t capacity() const { return capacity_; }
  // Frees the memory (capacity 0); the next reserve() allocates afresh.
  void release();

  template <typename T>
  void upload(const std::vector<T>& data) {
    reserve(std::max<size_t>(data.size() * sizeof(T), 4));
    if (!data.empty())
      AG2GS_CL_CHECK(rt_->queue().enqueueWriteBuffer(buffer_, CL_TRUE, 0, data.size() * sizeof(T), data.data()));
  }
  template <typename T>
  void download(std::vector<T>& out, size_t count) const {
    out.resize(count);
    if (count) AG2GS_CL_CHECK(rt_->queue().enqueueReadBuffer(buffer_, CL_TRUE, 0, count * sizeof(T), out.data()));
  }
  void fill_zero(size_t bytes);

 private:
  Runtime* rt_ = nullptr;
  cl::Buffer buffer_;
  size_t capacity_ = 0;
};

// A kernel's parameters as its program declares them, read once per kernel
// object: the count (CL_KERNEL_NUM_ARGS) always, and each parameter's name,
// type name and address space where the device reports them (programs build
// with -cl-kernel-arg-info; a device may still answer
// CL_KERNEL_ARG_INFO_NOT_AVAILABLE, and then only the count is checked).
struct KernelParam {
  std::string name, type;  // "ranges", "int2*"; "width", "int"
  cl_kernel_arg_address_qualifier space = CL_KERNEL_ARG_ADDRESS_PRIVATE;
};
struct KernelSignature {
  std::string kernel;
  size_t num_args = 0;
  std::vector<KernelParam> params;  // empty without arg info
};
std::shared_ptr<const KernelSignature> kernel_signature(const cl::Kernel& k);

// What a host argument is, for the check against the kernel's parameter:
// a buffer (a __global or __constant pointer), local memory, or a scalar of
// the OpenCL type `type` ("" when the host type has no checked name: only
// its being a scalar is checked).
struct HostArgKind {
  enum { kBuffer, kLocal, kScalar } kind;
  const char* type;
};
template <typename T>
constexpr HostArgKind host_arg_kind() {
  using U = std::decay_t<T>;
  if constexpr (std::is_same_v<U, DeviceBuffer> || std::is_same_v<U, cl::Buffer>)
    return {HostArgKind::kBuffer, ""};
  else if constexpr (std::is_same_v<U, cl::LocalSpaceArg>)
    return {HostArgKind::kLocal, ""};
  else if constexpr (std::is_same_v<U, float>)
    return {HostArgKind::kScalar, "float"};
  else if constexpr (std::is_same_v<U, double>)
    return {HostArgKind::kScalar, "double"};
  else if constexpr (std::is_integral_v<U> && std::is_signed_v<U> && sizeof(U) == 4)
    return {HostArgKind::kScalar, "int"};
  else if constexpr (std::is_integral_v<U> && std::is_unsigned_v<U> && sizeof(U) == 4)
    return {HostArgKind::kScalar, "uint"};
  else if constexpr (std::is_integral_v<U> && std::is_signed_v<U> && sizeof(U) == 8)
    return {HostArgKind::kScalar, "long"};
  else if constexpr (std::is_integral_v<U> && std::is_unsigned_v<U> && sizeof(U) == 8)
    return {HostArgKind::kScalar, "ulong"};
  else
    return {HostArgKind::kScalar, ""};
}
// Throws std::invalid_argument naming the kernel, the parameter (position,
// name, declared type) and what the host passed, when the host argument
// cannot be the parameter: a buffer for a scalar or the other way round, an
// int for a float, a count that is not the kernel's.
void check_kernel_arg(const KernelSignature& sig, cl_uint index, HostArgKind given);
void check_kernel_arg_count(const KernelSignature& sig, size_t given);

// Sets every argument of `k` in order; buffers pass as DeviceBuffer, scalars
// as themselves. Each is first checked against the kernel's own declaration
// (kernel_signature): a call that passes arguments in another order, or one
// too few, fails with the parameter's name instead of computing garbage.
// Errors of OpenCL itself name the call and the file:line (AG2GS_CL_CHECK).
template <typename T>
void set_kernel_arg(cl::Kernel& k, cl_uint i, const T& v) {
  AG2GS_CL_CHECK(k.setArg(i, v));
}
inline void set_kernel_arg(cl::Kernel& k, cl_uint i, const DeviceBuffer& b) {
  AG2GS_CL_CHECK(k.setArg(i, const_cast<DeviceBuffer&>(b).get()));
}
inline void set_kernel_arg(cl::Kernel& k, cl_uint i, DeviceBuffer& b) {
  AG2GS_CL_CHECK(k.setArg(i, b.get()));
}
template <typename... Args>
void set_kernel_args(cl::Kernel& k, Args&&... args) {
  const std::shared_ptr<const KernelSignature> sig = kernel_signature(k);
  check_kernel_arg_count(*sig, sizeof...(Args));
  cl_uint i = 0;
  ((check_kernel_arg(*sig, i, host_arg_kind<Args>()), set_kernel_arg(k, i, std::forward<Args>(args)), ++i), ...);
}

// Work-group size and pixels per work-item for a family of kernels that share
// both as build defines. `work_group` 0 = the largest power of two up to 256
// the device allows, halved until every kernel accepts it (a kernel's own
// limit can be lower than the device's); `lanes` 0 = the runtime's vector
// width. `kernel_limit(wg, lanes)` returns the smallest
// CL_KERNEL_WORK_GROUP_SIZE over the family built with those defines.
// Throws std::invalid_argument for bad requests and std::runtime_error when
// no size fits; messages start with `who`.
struct LaunchShape {
  int work_group = 1;
  int lanes = 1;
};
LaunchShape choose_launch_shape(Runtime& rt, const std::string& who, int work_group, int lanes,
                                const std::function<size_t(int, int)>& kernel_limit);

}  // namespace ag2gs
