// A kernel's arguments set by name, in the kernel's own order, for the
// kernels with many parameters (the renderer's): each arg() or buffer()
// names the parameter it fills, so the call site reads as the kernel's
// parameter list, and the call is checked against the kernel's declaration
// (kernel_signature, host/device/cl_runtime.h): the name at that position
// (where the device reports arg info), the kind and type as set_kernel_args
// checks them, a buffer's capacity against the bytes the kernel will reach,
// and at done() the count. Errors name the kernel and the parameter.
//
//   KernelCall(blend).arg("width", w).arg("height", h)
//       .buffer("records", records_, n * REC_SIZE * sizeof(float)) ... .done();
#pragma once

#include <memory>
#include <string>

#include "host/device/cl_runtime.h"

namespace ag2gs {

class KernelCall {
 public:
  explicit KernelCall(cl::Kernel& k) : k_(k), sig_(kernel_signature(k)) {}

  template <typename T>
  KernelCall& arg(const char* name, const T& v) {
    check_name(name);
    check_kernel_arg(*sig_, i_, host_arg_kind<T>());
    set_kernel_arg(k_, i_, v);
    ++i_;
    return *this;
  }
  // A buffer the kernel reaches `bytes` of (its capacity must hold them).
  KernelCall& buffer(const char* name, const DeviceBuffer& b, size_t bytes) {
    check_capacity(name, b, bytes);
    return arg(name, b);
  }
  // Every parameter was given.
  void done() const { check_kernel_arg_count(*sig_, i_); }

 private:
  void check_name(const char* name) const;
  void check_capacity(const char* name, const DeviceBuffer& b, size_t bytes) const;

  cl::Kernel& k_;
  std::shared_ptr<const KernelSignature> sig_;
  cl_uint i_ = 0;
};

}  // namespace ag2gs
