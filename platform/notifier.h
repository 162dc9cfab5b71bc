#pragma once

#include <linux/futex.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <atomic>
#include <cstdint>
#include <ctime>
#include <limits>

#include "platform/cache_line.h"

namespace mer::platform {

/// Wakes a sleeping consumer without locks: an epoch counter the consumer sleeps on with a
/// Linux futex (timed or not); notify() makes no system call when nobody is waiting.
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

  /// Bumps the epoch and wakes one waiter. Call after publishing the work. Makes a system
  /// call only when a thread is actually sleeping in wait()/wait_for().
  void notify() noexcept { bump_and_wake(1); }

  /// Bumps the epoch and wakes all waiters (e.g. on shutdown).
  void notify_all() noexcept { bump_and_wake(std::numeric_limits<int>::max()); }

  /// Blocks until the epoch differs from `seen_epoch` (returns at once if it already does).
  void wait(std::uint32_t seen_epoch) const noexcept {
    while (!wait_for(seen_epoch, kForeverNs)) {
    }
  }

  /// Like wait() but gives up after `timeout_ns`. Returns true when the epoch changed,
  /// false on timeout. Sleeps in the kernel (futex) until notified or timed out: an idle
  /// consumer costs no CPU, and a notify wakes it at once.
  bool wait_for(std::uint32_t seen_epoch, std::int64_t timeout_ns) const noexcept {
    for (int i = 0; i < kSpins; ++i) {
      if (epoch() != seen_epoch) return true;
    }
    const std::int64_t t0 = now_ns();
    for (;;) {
      if (epoch() != seen_epoch) return true;
      const std::int64_t left = timeout_ns - (now_ns() - t0);
      if (left <= 0) return false;
      // Dekker-style with notify(): either we see the new epoch (the kernel compares it
      // atomically and returns EAGAIN) or the notifier sees waiters_ > 0 and wakes us.
      waiters_.fetch_add(1, std::memory_order_seq_cst);
      const timespec rel{static_cast<time_t>(left / kNsPerS), static_cast<long>(left % kNsPerS)};
      ::syscall(SYS_futex, futex_word(), FUTEX_WAIT_PRIVATE, seen_epoch, &rel, nullptr, 0);
      waiters_.fetch_sub(1, std::memory_order_seq_cst);
    }
  }

 private:
  static constexpr int kSpins = 64;
  static constexpr std::int64_t kNsPerS = 1'000'000'000;
  static constexpr std::int64_t kForeverNs = std::numeric_limits<std::int64_t>::max() / 2;

  static std::int64_t now_ns() noexcept {
    timespec t{};
    ::clock_gettime(CLOCK_MONOTONIC, &t);
    return static_cast<std::int64_t>(t.tv_sec) * kNsPerS + t.tv_nsec;
  }

  // std::atomic<std::uint32_t> has the size and alignment of std::uint32_t (checked below),
  // so the kernel can wait on it directly.
  std::uint32_t* futex_word() const noexcept {
    return reinterpret_cast<std::uint32_t*>(const_cast<std::atomic<std::uint32_t>*>(&epoch_));
  }

  void bump_and_wake(int how_many) noexcept {
    epoch_.fetch_add(1, std::memory_order_seq_cst);
    if (waiters_.load(std::memory_order_seq_cst) > 0) {
      ::syscall(SYS_futex, futex_word(), FUTEX_WAKE_PRIVATE, how_many, nullptr, nullptr, 0);
    }
  }

  alignas(kCacheLine) std::atomic<std::uint32_t> epoch_{0};
  mutable std::atomic<std::int32_t> waiters_{0};
  static_assert(sizeof(std::atomic<std::uint32_t>) == sizeof(std::uint32_t) &&
                    alignof(std::atomic<std::uint32_t>) == alignof(std::uint32_t),
                "futex needs a plain 32-bit word");
};

}  // namespace mer::platform
