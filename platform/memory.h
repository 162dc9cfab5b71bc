#pragma once

#include <cstddef>
#include <string>

namespace mer::platform {

/// Locks all current and future pages of the process in RAM (mlockall(MCL_CURRENT |
/// MCL_FUTURE)) so the real-time threads never take a major page fault. Call once at
/// start-up, after the pools are allocated. Returns false when not permitted (no
/// CAP_IPC_LOCK / RLIMIT_MEMLOCK too small) and, if `error` is non-null, stores a message
/// with the errno text there; the caller decides whether that is fatal (normally: warn).
[[nodiscard]] bool lock_memory(std::string* error);

/// Undoes lock_memory() (munlockall). Returns false on failure, message in `error`.
bool unlock_memory(std::string* error);

/// Largest threshold set_mmap_threshold accepts (the allocator's own limit on 64-bit glibc).
inline constexpr std::size_t kMaxMmapThresholdBytes = std::size_t{32} << 20U;

/// Fixes the allocator's mmap threshold (glibc mallopt(M_MMAP_THRESHOLD)): a block of at
/// least `bytes` that no free chunk of a heap can serve gets a mapping of its own, unmapped
/// when freed. By default glibc raises the threshold each time such a block is freed, so that
/// later large, short-lived blocks (an optimizer's workspace) are carved from the heaps of the
/// threads that use them, and the holes they leave keep resident memory creeping up over a
/// long run. Setting it also stops glibc from raising its trim threshold, so free memory at
/// the top of a heap goes back to the system. Process-wide; call before the threads start.
/// Returns false (message in `error`) when `bytes` is 0 or above kMaxMmapThresholdBytes, or
/// the C library has no such setting.
[[nodiscard]] bool set_mmap_threshold(std::size_t bytes, std::string* error);

}  // namespace mer::platform
