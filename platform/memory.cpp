#include "platform/memory.h"

#include <sys/mman.h>

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

}  // namespace mer::platform
