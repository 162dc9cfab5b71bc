#include "platform/memory.h"

#include <sys/mman.h>
#if defined(__GLIBC__)
#include <malloc.h>
#endif

#include <cerrno>
#include <cstring>

namespace mer::platform {

namespace {
void set_error(std::string* error, const char* what, int err) {
  if (error != nullptr) {
    *error = std::string(what) + " failed: " + std::strerror(err) + " (errno " +
             std::to_string(err) + ")";
    if (err == EPERM || err == ENOMEM) {
      *error += "; needs CAP_IPC_LOCK or a larger RLIMIT_MEMLOCK (ulimit -l)";
    }
  }
}
}  // namespace

bool lock_memory(std::string* error) {
  if (::mlockall(MCL_CURRENT | MCL_FUTURE) != 0) {
    set_error(error, "mlockall(MCL_CURRENT|MCL_FUTURE)", errno);
    return false;
  }
  return true;
}

bool unlock_memory(std::string* error) {
  if (::munlockall() != 0) {
    set_error(error, "munlockall", errno);
    return false;
  }
  return true;
}

bool set_mmap_threshold(std::size_t bytes, std::string* error) {
  if (bytes == 0 || bytes > kMaxMmapThresholdBytes) {
    if (error != nullptr) {
      *error = "mmap threshold " + std::to_string(bytes) + " bytes: expected 1.." +
               std::to_string(kMaxMmapThresholdBytes);
    }
    return false;
  }
#if defined(__GLIBC__)
  if (::mallopt(M_MMAP_THRESHOLD, static_cast<int>(bytes)) != 1) {
    if (error != nullptr)
      *error = "mallopt(M_MMAP_THRESHOLD, " + std::to_string(bytes) + ") failed";
    return false;
  }
  return true;
#else
  if (error != nullptr) *error = "mmap threshold: not supported by this C library";
  return false;
#endif
}

}  // namespace mer::platform
