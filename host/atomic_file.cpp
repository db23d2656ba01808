#include "host/atomic_file.h"

#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <stdexcept>

namespace ag2gs {

AtomicFile::AtomicFile(std::string path) : path_(std::move(path)) {
  temp_ = path_ + ".tmp." + std::to_string(static_cast<long>(::getpid()));
  file_ = std::fopen(temp_.c_str(), "wb");
  if (!file_) {
    throw std::runtime_error(path_ + ": cannot create the temporary file '" + temp_ + "': " + std::strerror(errno) +
                             "; check that the directory exists and is writable");
  }
  created_ = true;
}

AtomicFile::~AtomicFile() {
  if (file_) std::fclose(file_);
  if (created_ && !committed_) std::remove(temp_.c_str());
}

void AtomicFile::fail(const std::string& what) {
  throw std::runtime_error(path_ + ": " + what + ": " + std::strerror(errno) +
                           "; the previous file, if any, is unchanged");
}

void AtomicFile::write(const void* data, size_t bytes) {
  if (!file_) throw std::logic_error("AtomicFile::write after commit");
  if (bytes > 0 && std::fwrite(data, 1, bytes, file_) != bytes) fail("writing '" + temp_ + "' failed (disk full?)");
}

void AtomicFile::commit() {
  if (!file_) throw std::logic_error("AtomicFile::commit twice");
  if (std::fflush(file_) != 0) fail("writing '" + temp_ + "' failed (disk full?)");
  ::fsync(::fileno(file_));  // the data must be on disk before the rename publishes it
  const int rc = std::fclose(file_);
  file_ = nullptr;
  if (rc != 0) fail("closing '" + temp_ + "' failed");
  if (std::rename(temp_.c_str(), path_.c_str()) != 0) fail("cannot move '" + temp_ + "' into place");
  committed_ = true;
}

}  // namespace ag2gs
