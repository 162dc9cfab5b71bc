#pragma once

#include <atomic>
#include <cstdint>
#include <ctime>

#include "platform/cache_line.h"

namespace mer::platform {

/// Wakes a sleeping consumer without locks: an epoch counter plus C++20 atomic wait/notify
/// (a futex on Linux; with libstdc++ notify() makes no syscall when nobody is waiting).
///
/// Usage pattern that cannot lose a wake-up:
/// ```
///   // consumer                               // producer
///   for (;;) {                                ring.try_push(x);
///     const auto seen = n.epoch();            n.notify();
///     while (ring.try_pop(x)) handle(x);
///     n.wait(seen);   // returns at once if notify() ran after epoch() was read
///   }
/// ```
/// The epoch is read *before* checking the ring. If the producer pushes after that check,
/// its notify() bumps the epoch past `seen`, so wait(seen) returns immediately; if it pushed
/// before the epoch read, the acquire/release pair makes the item visible to the check.
class Notifier {
 public:
  /// Starts at epoch 0.
  Notifier() noexcept = default;
  Notifier(const Notifier&) = delete;
  Notifier& operator=(const Notifier&) = delete;

  /// Current epoch; read it before checking for work, pass it to wait().
  std::uint32_t epoch() const noexcept { return epoch_.load(std::memory_order_acquire); }

  /// Bumps the epoch and wakes one waiter. Call after publishing the work.
  void notify() noexcept {
    epoch_.fetch_add(1, std::memory_order_acq_rel);
    epoch_.notify_one();
  }

  /// Bumps the epoch and wakes all waiters (e.g. on shutdown).
  void notify_all() noexcept {
    epoch_.fetch_add(1, std::memory_order_acq_rel);
    epoch_.notify_all();
  }

  /// Blocks until the epoch differs from `seen_epoch` (returns at once if it already does).
  void wait(std::uint32_t seen_epoch) const noexcept {
    epoch_.wait(seen_epoch, std::memory_order_acquire);
  }

  /// Like wait() but gives up after `timeout_ns`. Returns true when the epoch changed,
  /// false on timeout. Polls (spins briefly, then sleeps 50 us at a time), so it is meant
  /// for watchdog-style loops, not for the lowest-latency hand-off.
  bool wait_for(std::uint32_t seen_epoch, std::int64_t timeout_ns) const noexcept {
    for (int i = 0; i < 64; ++i) {
      if (epoch() != seen_epoch) {
        return true;
      }
    }
    timespec start{};
    ::clock_gettime(CLOCK_MONOTONIC, &start);
    const std::int64_t t0 =
        static_cast<std::int64_t>(start.tv_sec) * 1'000'000'000LL + start.tv_nsec;
    for (;;) {
      if (epoch() != seen_epoch) {
        return true;
      }
      timespec now{};
      ::clock_gettime(CLOCK_MONOTONIC, &now);
      const std::int64_t elapsed =
          static_cast<std::int64_t>(now.tv_sec) * 1'000'000'000LL + now.tv_nsec - t0;
      if (elapsed >= timeout_ns) {
        return epoch() != seen_epoch;
      }
      const std::int64_t left = timeout_ns - elapsed;
      const timespec nap{0, static_cast<long>(left < kPollNs ? left : kPollNs)};
      ::nanosleep(&nap, nullptr);
    }
  }

 private:
  static constexpr std::int64_t kPollNs = 50'000;
  alignas(kCacheLine) std::atomic<std::uint32_t> epoch_{0};
};

}  // namespace mer::platform
