#include "platform/pi_mutex.h"

#include <pthread.h>

#include <cerrno>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <new>

namespace mer::platform {

static_assert(sizeof(pthread_mutex_t) <= PiMutex::kStorageBytes,
              "PiMutex: storage too small for pthread_mutex_t on this platform");
static_assert(alignof(pthread_mutex_t) <= 8, "PiMutex: storage under-aligned");

namespace {

pthread_mutex_t* as_mutex(void* p) noexcept {
  return std::launder(static_cast<pthread_mutex_t*>(p));
}

[[noreturn]] void fail(const char* what, int err) noexcept {
  std::fprintf(stderr, "PiMutex: %s failed: %s (errno %d)\n", what, std::strerror(err), err);
  std::abort();
}

}  // namespace

PiMutex::PiMutex() noexcept {
  pthread_mutexattr_t attr;
  if (const int e = ::pthread_mutexattr_init(&attr); e != 0) fail("pthread_mutexattr_init", e);
  pi_ = ::pthread_mutexattr_setprotocol(&attr, PTHREAD_PRIO_INHERIT) == 0;
  auto* m = new (storage_) pthread_mutex_t;
  int e = ::pthread_mutex_init(m, &attr);
  if (e != 0 && pi_) {  // PI refused at init (e.g. ENOTSUP): a plain mutex instead
    pi_ = false;
    e = ::pthread_mutex_init(m, nullptr);
  }
  ::pthread_mutexattr_destroy(&attr);
  if (e != 0) fail("pthread_mutex_init", e);
}

PiMutex::~PiMutex() {
  (void)::pthread_mutex_destroy(as_mutex(native()));
}

void PiMutex::lock() noexcept {
  if (const int e = ::pthread_mutex_lock(as_mutex(native())); e != 0) fail("pthread_mutex_lock", e);
}

bool PiMutex::try_lock() noexcept {
  const int e = ::pthread_mutex_trylock(as_mutex(native()));
  if (e == 0) return true;
  if (e != EBUSY) fail("pthread_mutex_trylock", e);
  return false;
}

void PiMutex::unlock() noexcept {
  if (const int e = ::pthread_mutex_unlock(as_mutex(native())); e != 0) {
    fail("pthread_mutex_unlock", e);
  }
}

}  // namespace mer::platform
