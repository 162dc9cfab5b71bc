#include "platform/clock.h"

#include <ctime>

namespace mer::platform {

std::int64_t monotonic_now_ns() noexcept {
  timespec ts{};
  ::clock_gettime(CLOCK_MONOTONIC, &ts);
  return static_cast<std::int64_t>(ts.tv_sec) * 1'000'000'000LL + ts.tv_nsec;
}

namespace {

std::int64_t read_ns(clockid_t id) noexcept {
  timespec ts{};
  if (::clock_gettime(id, &ts) != 0) return 0;
  return static_cast<std::int64_t>(ts.tv_sec) * 1'000'000'000LL + ts.tv_nsec;
}

}  // namespace

std::int64_t process_cpu_ns() noexcept {
  return read_ns(CLOCK_PROCESS_CPUTIME_ID);
}

std::int64_t thread_cpu_ns() noexcept {
  return read_ns(CLOCK_THREAD_CPUTIME_ID);
}

Clock::~Clock() = default;

std::int64_t MonotonicClock::now_ns() const {
  return monotonic_now_ns();
}

std::int64_t LockstepClock::now_ns() const {
  return t_ns_.load(std::memory_order_acquire);
}

void LockstepClock::set_ns(std::int64_t t_ns) noexcept {
  t_ns_.store(t_ns, std::memory_order_release);
}

void LockstepClock::advance_ns(std::int64_t dt_ns) noexcept {
  t_ns_.fetch_add(dt_ns, std::memory_order_acq_rel);
}

}  // namespace mer::platform
