#pragma once

#include <cstddef>

namespace mer::platform {

/// Size in bytes of one cache line, used to keep data written by different threads on
/// different lines (no false sharing). 64 on x86-64, Cortex-A72 (RPi 4) and Cortex-A78AE
/// (Jetson Orin). Deliberately not std::hardware_destructive_interference_size: GCC warns
/// that its value may differ between translation units compiled with different -mtune.
inline constexpr std::size_t kCacheLine = 64;

}  // namespace mer::platform
