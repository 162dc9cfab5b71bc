#pragma once
/// @file synthetic_internal.h
/// Internal to the synthetic camera (synthetic_camera.cpp, synthetic_paths.cpp,
/// synthetic_scene.cpp): the constants and helpers more than one of them uses. Not part of
/// the HAL's interface.

#include <numbers>
#include <random>

namespace mer::hal::synthetic_detail {

inline constexpr double kTwoPi = 2.0 * std::numbers::pi;
inline constexpr double kLoopSemiAxisX = 1.5;  // room_loop: ellipse semi-axis along x, m
inline constexpr double kLoopSemiAxisY = 1.0;  // room_loop: ellipse semi-axis along y, m
inline constexpr int kMinMipSize = 8;          // coarsest texture level, texels per side

/// Uniform deviate in [lo, hi) from one draw of `rng` (portable across standard libraries).
inline double uniform(std::mt19937& rng, double lo, double hi) {
  return lo + (hi - lo) * (static_cast<double>(rng()) / 4294967296.0);
}

}  // namespace mer::hal::synthetic_detail
