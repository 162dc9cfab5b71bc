#pragma once

#include <cstdint>
#include <cstdlib>

namespace mer::platform::stress {

/// True in a -fsanitize=thread build (GCC defines __SANITIZE_THREAD__).
#if defined(__SANITIZE_THREAD__)
inline constexpr bool kUnderTsan = true;
#else
inline constexpr bool kUnderTsan = false;
#endif

/// Number of items for a ring stress test: MER_STRESS_ITEMS if set (> 0), otherwise
/// `normal` (or `tsan` under ThreadSanitizer, which is ~10x slower).
inline std::uint64_t ring_items(std::uint64_t normal, std::uint64_t tsan) {
  if (const char* env = std::getenv("MER_STRESS_ITEMS")) {
    const unsigned long long v = std::strtoull(env, nullptr, 10);
    if (v > 0) {
      return v;
    }
  }
  return kUnderTsan ? tsan : normal;
}

/// Iteration count for the non-ring stress tests: `normal`, divided by `tsan_divisor`
/// under TSan.
inline std::uint64_t iterations(std::uint64_t normal, std::uint64_t tsan_divisor) {
  return kUnderTsan ? normal / tsan_divisor : normal;
}

/// Spin-wait hint.
inline void cpu_relax() {
#if defined(__x86_64__) || defined(__i386__)
  __builtin_ia32_pause();
#elif defined(__aarch64__)
  asm volatile("yield" ::: "memory");
#endif
}

}  // namespace mer::platform::stress
