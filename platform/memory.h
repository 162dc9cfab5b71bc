#pragma once

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

}  // namespace mer::platform
