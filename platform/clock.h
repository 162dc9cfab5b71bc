#pragma once

#include <atomic>
#include <cstdint>
#include <limits>

namespace mer::platform {

/// Current CLOCK_MONOTONIC time in nanoseconds (never jumps with wall-clock changes).
/// vDSO call, no syscall, no allocation: safe on real-time threads.
std::int64_t monotonic_now_ns() noexcept;

/// CPU time consumed so far by the whole process (every thread), ns (CLOCK_PROCESS_CPUTIME_ID;
/// a system call on most kernels, no allocation). 0 when the clock is unavailable.
std::int64_t process_cpu_ns() noexcept;

/// CPU time consumed so far by the calling thread, ns (CLOCK_THREAD_CPUTIME_ID). 0 when the
/// clock is unavailable.
std::int64_t thread_cpu_ns() noexcept;

/// Milliseconds of the monotonic clock since `t0_ns` (a monotonic_now_ns() reading).
inline double elapsed_ms(std::int64_t t0_ns) noexcept {
  constexpr double kNsToMs = 1e-6;
  return static_cast<double>(monotonic_now_ns() - t0_ns) * kNsToMs;
}

/// `t_ns + dt_ns` clamped to the int64 range (deadlines from caller-supplied timeouts).
constexpr std::int64_t saturating_add_ns(std::int64_t t_ns, std::int64_t dt_ns) noexcept {
  constexpr std::int64_t kMax = std::numeric_limits<std::int64_t>::max();
  constexpr std::int64_t kMin = std::numeric_limits<std::int64_t>::min();
  if (dt_ns > 0 && t_ns > kMax - dt_ns) return kMax;
  if (dt_ns < 0 && t_ns < kMin - dt_ns) return kMin;
  return t_ns + dt_ns;
}

/// Time source injected into stages, so that live runs use the monotonic clock and
/// deterministic replay uses a clock driven by the frame timestamps.
class Clock {
 public:
  /// Virtual destructor for the interface.
  virtual ~Clock();
  /// Current time in nanoseconds on this clock's time base.
  virtual std::int64_t now_ns() const = 0;
};

/// Clock reading CLOCK_MONOTONIC (monotonic_now_ns()).
class MonotonicClock final : public Clock {
 public:
  /// monotonic_now_ns().
  std::int64_t now_ns() const override;
};

/// Manually driven clock for lockstep replay: the replay driver sets it to each frame's
/// timestamp, so every stage sees the same time on every run. The value is atomic, so
/// other threads (e.g. a monitor) may read it while the driver sets it.
class LockstepClock final : public Clock {
 public:
  /// Starts at `start_ns` (default 0).
  explicit LockstepClock(std::int64_t start_ns = 0) noexcept : t_ns_(start_ns) {}
  /// The last value set.
  std::int64_t now_ns() const override;
  /// Sets the current time (may go backwards; replay decides).
  void set_ns(std::int64_t t_ns) noexcept;
  /// Adds `dt_ns` to the current time.
  void advance_ns(std::int64_t dt_ns) noexcept;

 private:
  std::atomic<std::int64_t> t_ns_;
};

}  // namespace mer::platform
