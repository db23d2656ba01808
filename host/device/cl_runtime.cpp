#include "host/device/cl_runtime.h"

#include <spdlog/spdlog.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <limits>
#include <sstream>

#include "host/device/device_policy.h"
#include "host/device/kernel_source.h"

namespace fs = std::filesystem;

namespace ag2gs {

const char* cl_error_name(cl_int code) {
  switch (code) {
#define E(x) \
  case x:    \
    return #x;
    E(CL_DEVICE_NOT_FOUND)
    E(CL_DEVICE_NOT_AVAILABLE)
    E(CL_COMPILER_NOT_AVAILABLE) E(CL_MEM_OBJECT_ALLOCATION_FAILURE) E(CL_OUT_OF_RESOURCES) E(CL_OUT_OF_HOST_MEMORY)
        E(CL_PROFILING_INFO_NOT_AVAILABLE) E(CL_BUILD_PROGRAM_FAILURE) E(CL_INVALID_VALUE) E(CL_INVALID_DEVICE)
            E(CL_INVALID_CONTEXT) E(CL_INVALID_COMMAND_QUEUE) E(CL_INVALID_MEM_OBJECT) E(CL_INVALID_BINARY)
                E(CL_INVALID_BUILD_OPTIONS) E(CL_INVALID_PROGRAM) E(CL_INVALID_PROGRAM_EXECUTABLE)
                    E(CL_INVALID_KERNEL_NAME) E(CL_INVALID_KERNEL) E(CL_INVALID_ARG_INDEX) E(CL_INVALID_ARG_VALUE)
                        E(CL_INVALID_ARG_SIZE) E(CL_INVALID_KERNEL_ARGS) E(CL_INVALID_WORK_DIMENSION)
                            E(CL_INVALID_WORK_GROUP_SIZE) E(CL_INVALID_WORK_ITEM_SIZE) E(CL_INVALID_GLOBAL_OFFSET)
                                E(CL_INVALID_EVENT_WAIT_LIST) E(CL_INVALID_EVENT) E(CL_INVALID_OPERATION)
                                    E(CL_INVALID_BUFFER_SIZE) E(CL_INVALID_GLOBAL_WORK_SIZE)
                                        E(CL_PLATFORM_NOT_FOUND_KHR)
#undef E
                                            default : return "unknown OpenCL error";
  }
}

ClError::ClError(cl_int code, const std::string& call, const char* file, int line)
    : std::runtime_error(
          call + " failed: " + cl_error_name(code) + " (" + std::to_string(code) + ") at " + file + ":" +
          std::to_string(line) +
          (code == CL_MEM_OBJECT_ALLOCATION_FAILURE || code == CL_OUT_OF_RESOURCES
               ? ". The device ran out of memory: render at a lower resolution (-r) or pick another device (--device)."
               : "")),
      code_(code) {}

// ---------------------------------------------------------------- devices

std::vector<DeviceInfo> list_devices() {
  std::vector<cl::Platform> platforms;
  cl_int err = cl::Platform::get(&platforms);
  if (err == CL_PLATFORM_NOT_FOUND_KHR || platforms.empty()) return {};
  AG2GS_CL_CHECK(err);
  std::vector<DeviceInfo> out;
  for (auto& p : platforms) {
    std::vector<cl::Device> devs;
    if (p.getDevices(CL_DEVICE_TYPE_ALL, &devs) != CL_SUCCESS) continue;
    for (auto& d : devs) {
      DeviceInfo i;
      i.index = static_cast<int>(out.size());
      i.platform = p.getInfo<CL_PLATFORM_NAME>();
      i.name = d.getInfo<CL_DEVICE_NAME>();
      i.vendor = d.getInfo<CL_DEVICE_VENDOR>();
      i.version = d.getInfo<CL_DEVICE_VERSION>();
      i.driver = d.getInfo<CL_DRIVER_VERSION>();
      cl_device_type type = d.getInfo<CL_DEVICE_TYPE>();
      i.is_gpu = (type & CL_DEVICE_TYPE_GPU) != 0;
      i.is_cpu = (type & CL_DEVICE_TYPE_CPU) != 0;
      i.compute_units = d.getInfo<CL_DEVICE_MAX_COMPUTE_UNITS>();
      i.global_mem = d.getInfo<CL_DEVICE_GLOBAL_MEM_SIZE>();
      i.local_mem = d.getInfo<CL_DEVICE_LOCAL_MEM_SIZE>();
      i.max_alloc = d.getInfo<CL_DEVICE_MAX_MEM_ALLOC_SIZE>();
      i.max_work_group = d.getInfo<CL_DEVICE_MAX_WORK_GROUP_SIZE>();
      i.fp64 = d.getInfo<CL_DEVICE_DOUBLE_FP_CONFIG>() != 0;
      i.correct_div = (d.getInfo<CL_DEVICE_SINGLE_FP_CONFIG>() & CL_FP_CORRECTLY_ROUNDED_DIVIDE_SQRT) != 0;
      i.native_float_width = d.getInfo<CL_DEVICE_NATIVE_VECTOR_WIDTH_FLOAT>();
      i.device = d;
      out.push_back(std::move(i));
    }
  }
  return out;
}

// PoCL (the CPU driver) hides its device when it cannot create its kernel
// cache: $POCL_CACHE_DIR, else $XDG_CACHE_HOME/pocl, else $HOME/.cache/pocl.
// The folder that would hold that cache when it cannot be written ("" when
// it can, or when none is known).
std::string unwritable_cache_root() {
  std::string dir;
  if (const char* p = std::getenv("POCL_CACHE_DIR"); p && *p)
    dir = p;
  else if (const char* x = std::getenv("XDG_CACHE_HOME"); x && *x)
    dir = x;
  else if (const char* h = std::getenv("HOME"); h && *h)
    dir = std::string(h) + "/.cache";
  else
    return "";
  // The deepest existing folder on the way decides.
  std::filesystem::path p(dir);
  std::error_code ec;
  while (!p.empty() && !std::filesystem::exists(p, ec)) p = p.parent_path();
  if (p.empty()) return "";
  // A real probe: access(2) says yes to root where mkdir fails (/proc).
  std::string probe = (p / ".ag2gs_probe_XXXXXX").string();
  if (::mkdtemp(probe.data()) == nullptr) return p.string();
  ::rmdir(probe.c_str());
  return "";
}

int resolve_device_index(int requested, const std::vector<DeviceInfo>& devices) {
  if (devices.empty()) {
    const std::string cache = unwritable_cache_root();
    if (!cache.empty())
      throw std::runtime_error(
          "no OpenCL device found, and " + cache +
          " is not writable: the CPU driver (PoCL) needs a writable kernel cache and hides its device without "
          "one. Set XDG_CACHE_HOME (or POCL_CACHE_DIR) to a writable folder, e.g. `XDG_CACHE_HOME=/tmp/cache`, or "
          "make HOME writable.");
    throw std::runtime_error(
        "no OpenCL device found. Install an OpenCL driver: on Debian `apt-get install pocl-opencl-icd` "
        "for the CPU, or your GPU vendor's OpenCL ICD; `clinfo -l` lists what the loader sees.");
  }
  int index = requested;
  if (index < 0) {
    if (const char* env = std::getenv("AG2GS_DEVICE"); env && *env) {
      char* end = nullptr;
      long v = std::strtol(env, &end, 10);
      if (*end != '\0' || v < 0)
        throw std::runtime_error(std::string("AG2GS_DEVICE='") + env +
                                 "' is not a device index; run `ag2gs devices` to list them");
      index = static_cast<int>(v);
    } else {
      index = default_device_index(devices);
    }
  }
  if (index >= static_cast<int>(devices.size()))
    throw std::runtime_error("device " + std::to_string(index) + " does not exist (there are " +
                             std::to_string(devices.size()) + "); run `ag2gs devices` to list them");
  return index;
}

// ---------------------------------------------------------------- runtime

Runtime::Runtime(int device_index) {
  auto devices = list_devices();
  info_ = devices[resolve_device_index(device_index, devices)];
  cl_int err = CL_SUCCESS;
  context_ = cl::Context(info_.device, nullptr, nullptr, nullptr, &err);
  AG2GS_CL_CHECK(err);
  queue_ = cl::CommandQueue(context_, info_.device, CL_QUEUE_PROFILING_ENABLE, &err);
  AG2GS_CL_CHECK(err);
  vector_width_ = vector_width_for(info_);
  exact_allocations_ = simulated_device(info_);
  if (const char* log = std::getenv("AG2GS_LAUNCH_LOG"); log && *log) {
    launch_log_ = std::fopen(log, "a");
    if (!launch_log_) throw std::runtime_error(std::string("AG2GS_LAUNCH_LOG='") + log + "' cannot be opened for appending");
  }
  spdlog::debug("OpenCL device {}: {} ({}), vector width {}", info_.index, info_.name, info_.platform, vector_width_);
}

Runtime::~Runtime() {
  if (launch_log_) std::fclose(launch_log_);
}

std::string Runtime::cache_dir() {
  if (const char* env = std::getenv("AG2GS_CACHE_DIR"); env && *env) return env;
  if (const char* xdg = std::getenv("XDG_CACHE_HOME"); xdg && *xdg) return std::string(xdg) + "/ag2gs/kernels";
  if (const char* home = std::getenv("HOME"); home && *home) return std::string(home) + "/.cache/ag2gs/kernels";
  return (fs::temp_directory_path() / "ag2gs-kernels").string();
}

namespace {

// FNV-1a, 64 bit: enough to key a cache whose entries are also verified.
uint64_t fnv1a(const std::string& s, uint64_t h = 1469598103934665603ull) {
  for (unsigned char c : s) {
    h ^= c;
    h *= 1099511628211ull;
  }
  return h;
}

std::string hex(uint64_t v) {
  std::ostringstream o;
  o << std::hex << v;
  return o.str();
}

// Cache file: magic, key length + key, binary length + binary, checksum.
constexpr char kCacheMagic[8] = {'A', 'G', '2', 'G', 'S', 'K', 'C', '1'};

bool load_cached_binary(const std::string& path, const std::string& key, std::vector<unsigned char>& bin) {
  std::ifstream f(path, std::ios::binary);
  if (!f) return false;
  char magic[8];
  uint64_t klen = 0, blen = 0, sum = 0;
  if (!f.read(magic, 8) || std::memcmp(magic, kCacheMagic, 8) != 0) return false;
  if (!f.read(reinterpret_cast<char*>(&klen), 8) || klen > (1u << 24)) return false;
  std::string k(klen, '\0');
  if (!f.read(k.data(), klen) || k != key) return false;
  if (!f.read(reinterpret_cast<char*>(&blen), 8) || blen == 0 || blen > (1ull << 31)) return false;
  bin.resize(blen);
  if (!f.read(reinterpret_cast<char*>(bin.data()), blen)) return false;
  if (!f.read(reinterpret_cast<char*>(&sum), 8)) return false;
  return sum == fnv1a(std::string(bin.begin(), bin.end()));
}

void store_cached_binary(const std::string& path, const std::string& key, const std::vector<unsigned char>& bin) {
  std::error_code ec;
  fs::create_directories(fs::path(path).parent_path(), ec);
  std::string tmp = path + ".tmp." + std::to_string(::getpid());
  {
    std::ofstream f(tmp, std::ios::binary);
    if (!f) return;  // a cache is optional
    uint64_t klen = key.size(), blen = bin.size(), sum = fnv1a(std::string(bin.begin(), bin.end()));
    f.write(kCacheMagic, 8);
    f.write(reinterpret_cast<const char*>(&klen), 8);
    f.write(key.data(), klen);
    f.write(reinterpret_cast<const char*>(&blen), 8);
    f.write(reinterpret_cast<const char*>(bin.data()), blen);
    f.write(reinterpret_cast<const char*>(&sum), 8);
    if (!f) {
      f.close();
      fs::remove(tmp, ec);
      return;
    }
  }
  fs::rename(tmp, path, ec);
  if (ec) fs::remove(tmp, ec);
}

}  // namespace

cl::Program Runtime::program(const std::string& file, const std::map<std::string, std::string>& defines) {
  std::string header = "// generated defines\n";
  for (auto& [k, v] : defines) header += "#define " + k + " " + v + "\n";
  // A kernel may ask for its own vector width (the blend backward's plan).
  if (!defines.count("VW")) header += "#define VW " + std::to_string(vector_width_) + "\n";
  std::string source = header + kernel_source("layout.h") + kernel_source("common.cl") + "\n#line 1\n" + kernel_source(file);
  // Arg info: each launch checks its arguments against the kernel's own
  // declaration (kernel_signature).
  std::string options = "-cl-std=CL1.2 -cl-kernel-arg-info";
  // OpenCL lets x / y and sqrt be off by a few ulp, and a GPU compiler may
  // then divide differently in two kernels that share a helper (NVIDIA's
  // does: the mask loss's G = F / alpha came out with other bits in its
  // gradient kernel than in its mean). Correct rounding, where the device
  // offers it, gives every kernel and every such device the same quotient.
  if (info_.correct_div) options += " -cl-fp32-correctly-rounded-divide-sqrt";
  // PoCL on a CPU without AVX-512 warns that every 16-wide vector argument
  // "changes the ABI" and prints "N warnings generated." into the user's
  // log, once per program: nothing a user can act on. AG2GS_KERNEL_WARNINGS=1
  // keeps the compiler's warnings (in the build log, `ag2gs -v`).
  if (const char* w = std::getenv("AG2GS_KERNEL_WARNINGS"); !w || std::string(w) != "1") options += " -w";
  if (const char* env = std::getenv("AG2GS_CL_OPTIONS"); env) options += std::string(" ") + env;

  std::string key = file + "\n" + options + "\n" + info_.platform + "\n" + info_.name + "\n" + info_.driver + "\n" +
                    info_.version + "\n" + hex(fnv1a(source));
  std::lock_guard<std::mutex> lock(mutex_);
  if (auto it = programs_.find(key); it != programs_.end()) return it->second;

  cl_int err = CL_SUCCESS;
  std::string cache_path = cache_dir() + "/" + hex(fnv1a(key)) + ".bin";
  bool use_disk = std::getenv("AG2GS_NO_KERNEL_CACHE") == nullptr;
  std::vector<unsigned char> binary;
  if (use_disk && load_cached_binary(cache_path, key, binary)) {
    cl::Program::Binaries bins{binary};
    std::vector<cl_int> status;
    cl::Program p(context_, {info_.device}, bins, &status, &err);
    if (err == CL_SUCCESS && p.build({info_.device}, options.c_str()) == CL_SUCCESS) {
      programs_[key] = p;
      return p;
    }
    spdlog::warn("kernel cache entry {} is unusable; rebuilding {}", cache_path, file);
  }

  cl::Program p(context_, source, false, &err);
  AG2GS_CL_CHECK(err);
  err = p.build({info_.device}, options.c_str());
  if (err != CL_SUCCESS) {
    std::string log = p.getBuildInfo<CL_PROGRAM_BUILD_LOG>(info_.device);
    throw BuildError("building OpenCL program " + file + " failed (" + cl_error_name(err) + ") on " + info_.name +
                     "\noptions: " + options + "\ndefines:\n" + header + "build log:\n" + log);
  }
  if (std::string log = p.getBuildInfo<CL_PROGRAM_BUILD_LOG>(info_.device);
      log.find_first_not_of(" \n\r\t") != std::string::npos)
    spdlog::debug("build log of {}:\n{}", file, log);
  if (use_disk) {
    auto bins = p.getInfo<CL_PROGRAM_BINARIES>();
    if (!bins.empty() && !bins[0].empty()) store_cached_binary(cache_path, key, bins[0]);
  }
  programs_[key] = p;
  return p;
}

cl::Kernel Runtime::kernel(const std::string& file, const std::string& name,
                           const std::map<std::string, std::string>& defines) {
  // Kernels are fetched every frame: look them up by a cheap key first, so the
  // source is assembled and hashed only once per (file, name, defines).
  std::string key = file + "|" + name;
  for (auto& [k, v] : defines) key += "|" + k + "=" + v;
  if (auto it = kernels_.find(key); it != kernels_.end()) return it->second;
  cl::Program p = program(file, defines);
  cl_int err = CL_SUCCESS;
  cl::Kernel k(p, name.c_str(), &err);
  if (err != CL_SUCCESS) throw ClError(err, "clCreateKernel(" + file + ":" + name + ")", __FILE__, __LINE__);
  kernels_[key] = k;
  return k;
}

void Runtime::launch(const std::string& label, cl::Kernel& k, const cl::NDRange& global, const cl::NDRange& local) {
  cl::NDRange g = global;
  if (local.dimensions() > 0) {
    size_t dims[3] = {1, 1, 1};
    for (cl_uint i = 0; i < global.dimensions(); ++i) {
      size_t l = local.get()[i];
      dims[i] = (global.get()[i] + l - 1) / l * l;
    }
    g = global.dimensions() == 1   ? cl::NDRange(dims[0])
        : global.dimensions() == 2 ? cl::NDRange(dims[0], dims[1])
                                   : cl::NDRange(dims[0], dims[1], dims[2]);
  }
  for (cl_uint i = 0; i < g.dimensions(); ++i)
    if (g.get()[i] == 0) return;  // nothing to do
  cl::Event ev;
  cl_int err = queue_.enqueueNDRangeKernel(k, cl::NullRange, g, local, nullptr, profiling_ ? &ev : nullptr);
  if (err != CL_SUCCESS) throw ClError(err, "enqueueNDRangeKernel(" + label + ")", __FILE__, __LINE__);
  if (profiling_)
    pending_events_.push_back({label, by_kernel_ ? k.getInfo<CL_KERNEL_FUNCTION_NAME>() : std::string(), ev});
  if (launch_log_) {
    // The kernel, then its work-item count: a simulator's time is about
    // proportional to the latter (tests/oclgrind/run_oclgrind.sh reads $1).
    size_t items = 1;
    for (cl_uint i = 0; i < g.dimensions(); ++i) items *= g.get()[i];
    // The log waits for each launch, so that its wall time (s=) is the
    // kernel's own: slower, but the bits are the same.
    const auto t0 = std::chrono::steady_clock::now();
    queue_.finish();
    const auto t1 = std::chrono::steady_clock::now();
    std::fprintf(launch_log_, "%s vw=%d items=%zu label=%s mem=%llu s=%.4f\n",
                 k.getInfo<CL_KERNEL_FUNCTION_NAME>().c_str(), vector_width_, items, label.c_str(),
                 static_cast<unsigned long long>(allocated_), std::chrono::duration<double>(t1 - t0).count());
    std::fflush(launch_log_);
  }
}

std::map<std::string, double> Runtime::take_timings() {
  queue_.finish();
  for (auto& [label, kernel, ev] : pending_events_) {
    cl_ulong a = 0, b = 0;
    if (ev.getProfilingInfo(CL_PROFILING_COMMAND_START, &a) == CL_SUCCESS &&
        ev.getProfilingInfo(CL_PROFILING_COMMAND_END, &b) == CL_SUCCESS) {
      timings_[label] += (b - a) * 1e-6;
      if (!kernel.empty()) timings_["kernel:" + kernel] += (b - a) * 1e-6;
    }
  }
  pending_events_.clear();
  auto out = std::move(timings_);
  timings_.clear();
  return out;
}

void Runtime::on_alloc(int64_t delta) {
  allocated_ = static_cast<uint64_t>(static_cast<int64_t>(allocated_) + delta);
  peak_ = std::max(peak_, allocated_);
}

// ---------------------------------------------------------------- buffers

DeviceBuffer::~DeviceBuffer() {
  if (rt_ && capacity_) rt_->on_alloc(-static_cast<int64_t>(capacity_));
}

bool DeviceBuffer::reserve(size_t bytes) {
  if (bytes <= capacity_ && capacity_ > 0) return false;
  // Grow geometrically so a slowly rising demand does not reallocate each
  // frame (on a simulator, to the size asked: Runtime::exact_allocations).
  size_t want = std::max<size_t>({bytes, rt_->exact_allocations() ? 0 : capacity_ + capacity_ / 2, 256});
  if (want > rt_->info().max_alloc && bytes <= rt_->info().max_alloc) want = rt_->info().max_alloc;
  if (want > rt_->info().max_alloc)
    throw std::runtime_error("a device buffer of " + std::to_string(bytes >> 20) + " MiB exceeds the device's " +
                             "largest allocation (" + std::to_string(rt_->info().max_alloc >> 20) +
                             " MiB): render at a lower resolution (-r) or use fewer Gaussians");
  cl_int err = CL_SUCCESS;
  cl::Buffer b(rt_->context(), CL_MEM_READ_WRITE, want, nullptr, &err);
  AG2GS_CL_CHECK(err);
  if (capacity_) rt_->on_alloc(-static_cast<int64_t>(capacity_));
  buffer_ = b;
  capacity_ = want;
  rt_->on_alloc(static_cast<int64_t>(want));
  if (const char* s = std::getenv("AG2GS_FILL_SENTINEL"); s && *s == '1') {
    // Quiet NaN: code that assumes zeroed memory shows up as NaN outputs.
    cl_uint pattern = 0x7fc00000u;
    AG2GS_CL_CHECK(rt_->queue().enqueueFillBuffer(buffer_, pattern, 0, want / 4 * 4));
  }
  return true;
}

void DeviceBuffer::release() {
  if (!capacity_) return;
  rt_->on_alloc(-static_cast<int64_t>(capacity_));
  buffer_ = cl::Buffer();
  capacity_ = 0;
}

void DeviceBuffer::fill_zero(size_t bytes) {
  reserve(std::max<size_t>(bytes, 4));
  if (bytes == 0) return;
  cl_uint zero = 0;
  AG2GS_CL_CHECK(rt_->queue().enqueueFillBuffer(buffer_, zero, 0, (bytes + 3) / 4 * 4));
}

LaunchShape choose_launch_shape(Runtime& rt, const std::string& who, int work_group, int lanes,
                                const std::function<size_t(int, int)>& kernel_limit) {
  auto power_of_two = [](long v) { return v > 0 && (v & (v - 1)) == 0; };
  const size_t device_max = rt.info().max_work_group;
  LaunchShape shape;
  if (work_group != 0) {
    if (!power_of_two(work_group) || static_cast<size_t>(work_group) > device_max)
      throw std::invalid_argument(who + ": work-group size " + std::to_string(work_group) +
                                  " must be a power of two no larger than the device's " + std::to_string(device_max));
    shape.work_group = work_group;
  } else {
    while (static_cast<size_t>(shape.work_group) * 2 <= std::min<size_t>(256, device_max)) shape.work_group *= 2;
  }
  shape.lanes = lanes != 0 ? lanes : rt.vector_width();
  if (!power_of_two(shape.lanes) || shape.lanes > 16)
    throw std::invalid_argument(who + ": lanes must be 1, 2, 4, 8 or 16, got " + std::to_string(shape.lanes));
  for (;;) {
    const size_t limit = std::min(device_max, kernel_limit(shape.work_group, shape.lanes));
    if (static_cast<size_t>(shape.work_group) <= limit) return shape;
    if (work_group != 0 || shape.work_group == 1)
      throw std::runtime_error(who + ": the device runs these kernels with at most " + std::to_string(limit) +
                               " work-items per group, fewer than " + std::to_string(shape.work_group));
    shape.work_group /= 2;
  }
}

// ------------------------------------------------------------------ kernel arguments
std::shared_ptr<const KernelSignature> kernel_signature(const cl::Kernel& k) {
  static std::mutex mutex;
  static std::map<cl_kernel, std::shared_ptr<const KernelSignature>> signatures;
  std::lock_guard<std::mutex> lock(mutex);
  // Keyed by the handle, which OpenCL may give to another kernel once this
  // one is released: an entry counts only while its name and count match.
  const std::string name = k.getInfo<CL_KERNEL_FUNCTION_NAME>();
  const size_t num_args = k.getInfo<CL_KERNEL_NUM_ARGS>();
  std::shared_ptr<const KernelSignature>& entry = signatures[k()];
  if (entry && entry->kernel == name && entry->num_args == num_args) return entry;
  auto fresh = std::make_shared<KernelSignature>();
  KernelSignature& sig = *fresh;
  sig.kernel = name;
  sig.num_args = num_args;
  for (cl_uint i = 0; i < sig.num_args; ++i) {
    KernelParam p;
    cl_int e1 = CL_SUCCESS, e2 = CL_SUCCESS, e3 = CL_SUCCESS;
    p.name = k.getArgInfo<CL_KERNEL_ARG_NAME>(i, &e1);
    p.type = k.getArgInfo<CL_KERNEL_ARG_TYPE_NAME>(i, &e2);
    p.space = k.getArgInfo<CL_KERNEL_ARG_ADDRESS_QUALIFIER>(i, &e3);
    // Some drivers end the names with NULs.
    for (std::string* s : {&p.name, &p.type})
      while (!s->empty() && s->back() == '\0') s->pop_back();
    // PoCL's headers rename the builtin functions by macro (#define step
    // _cl_step), which renames a parameter of that name too (growth_accumulate's
    // step): the kernel declares it without the prefix.
    if (p.name.rfind("_cl_", 0) == 0) p.name.erase(0, 4);
    // Not reported (an error, or empty names): the count alone is checked.
    if (e1 != CL_SUCCESS || e2 != CL_SUCCESS || e3 != CL_SUCCESS || p.name.empty() || p.type.empty()) {
      sig.params.clear();
      break;
    }
    sig.params.push_back(p);
  }
  entry = fresh;
  return entry;
}

void check_kernel_arg_count(const KernelSignature& sig, size_t given) {
  if (given != sig.num_args)
    throw std::invalid_argument("kernel " + sig.kernel + " takes " + std::to_string(sig.num_args) +
                                " arguments; the host passed " + std::to_string(given));
}

namespace {

// A scalar type name as the spec spells it ("uint" for "unsigned int", which
// a driver might report), and whether it is one the check compares (a
// typedef or a vector type is checked for its kind alone).
std::string scalar_name(std::string t) {
  static const std::pair<const char*, const char*> spelled[] = {
      {"unsigned int", "uint"}, {"unsigned long", "ulong"}, {"unsigned short", "ushort"}, {"unsigned char", "uchar"}};
  for (const auto& [longer, shorter] : spelled)
    if (t == longer) t = shorter;
  return t;
}
bool is_checked_scalar(const std::string& t) {
  const std::string n = scalar_name(t);
  for (const char* k : {"int", "uint", "long", "ulong", "float", "double"})
    if (n == k) return true;
  return false;
}

}  // namespace

void check_kernel_arg(const KernelSignature& sig, cl_uint index, HostArgKind given) {
  if (index >= sig.params.size()) return;
  const KernelParam& p = sig.params[index];
  const bool pointer = !p.type.empty() && p.type.back() == '*';
  const bool buffer = pointer && (p.space == CL_KERNEL_ARG_ADDRESS_GLOBAL || p.space == CL_KERNEL_ARG_ADDRESS_CONSTANT);
  const bool local = p.space == CL_KERNEL_ARG_ADDRESS_LOCAL;
  std::string wrong;
  switch (given.kind) {
    case HostArgKind::kBuffer:
      if (!buffer) wrong = "a buffer";
      break;
    case HostArgKind::kLocal:
      if (!local) wrong = "local memory";
      break;
    case HostArgKind::kScalar:
      if (pointer || local || (*given.type && is_checked_scalar(p.type) && scalar_name(p.type) != given.type))
        wrong = std::string("a scalar ") + given.type;
      break;
  }
  if (!wrong.empty())
    throw std::invalid_argument("kernel " + sig.kernel + ": argument " + std::to_string(index) + " is '" + p.type +
                                " " + p.name + "'; the host passed " + wrong + " there (arguments out of order?)");
}

}  // namespace ag2gs
