#include "host/device/kernel_call.h"

#include <stdexcept>

namespace ag2gs {

void KernelCall::check_name(const char* name) const {
  if (i_ >= sig_->num_args)
    throw std::invalid_argument("kernel " + sig_->kernel + " takes " + std::to_string(sig_->num_args) +
                                " arguments; the host gave '" + name + "' as one more");
  if (i_ < sig_->params.size() && sig_->params[i_].name != name)
    throw std::invalid_argument("kernel " + sig_->kernel + ": argument " + std::to_string(i_) + " is '" +
                                sig_->params[i_].type + " " + sig_->params[i_].name + "'; the host gave '" + name +
                                "' there (arguments out of order?)");
}

void KernelCall::check_capacity(const char* name, const DeviceBuffer& b, size_t bytes) const {
  if (b.capacity() < bytes)
    throw std::logic_error("kernel " + sig_->kernel + ": buffer '" + name + "' holds " +
                           std::to_string(b.capacity()) + " bytes; the kernel reaches " + std::to_string(bytes));
}

}  // namespace ag2gs
