#pragma once

#include <cstddef>

namespace mer::platform {

/// A mutex with priority inheritance (POSIX PTHREAD_PRIO_INHERIT, a Linux PI futex): while a
/// thread of higher real-time priority waits for it, the owner runs at the waiter's priority.
/// Without it, a low-priority owner preempted by medium-priority work would hold up the
/// high-priority waiter for as long as that work runs (unbounded priority inversion). Use it
/// for a lock shared by threads of different priorities (the map's writer lock: the
/// low-priority depth thread and the high-priority back-end thread).
///
/// - Satisfies Lockable (lock / try_lock / unlock): use std::lock_guard / std::unique_lock.
/// - Not recursive; unlock only from the owning thread.
/// - No allocation: the pthread mutex lives inline (this header includes no pthread header:
///   only platform/ may; its size is checked in pi_mutex.cpp).
/// - Uncontended lock / unlock are one atomic operation each (glibc PI mutexes only enter
///   the kernel on contention).
/// - When the system refuses the PI protocol, the constructor falls back to a plain mutex
///   and priority_inheritance() returns false (the caller may warn).
class PiMutex {
 public:
  /// Initializes the mutex with PTHREAD_PRIO_INHERIT (plain mutex if that is refused).
  PiMutex() noexcept;
  /// The mutex must not be locked.
  ~PiMutex();
  PiMutex(const PiMutex&) = delete;
  PiMutex& operator=(const PiMutex&) = delete;
  PiMutex(PiMutex&&) = delete;
  PiMutex& operator=(PiMutex&&) = delete;

  /// Blocks until the calling thread owns the mutex. Aborts with a message on a broken
  /// invariant the OS reports (e.g. EDEADLK: the caller already owns it).
  void lock() noexcept;
  /// Takes the mutex if it is free; false (at once) when another thread owns it.
  [[nodiscard]] bool try_lock() noexcept;
  /// Releases the mutex (owner only).
  void unlock() noexcept;

  /// True when the mutex was created with the priority-inheritance protocol.
  bool priority_inheritance() const noexcept { return pi_; }

  /// Bytes reserved for the pthread mutex (glibc x86-64: 40, AArch64: 48).
  static constexpr std::size_t kStorageBytes = 64;

 private:
  void* native() noexcept { return storage_; }

  alignas(8) std::byte storage_[kStorageBytes] = {};
  bool pi_ = false;
};

}  // namespace mer::platform
