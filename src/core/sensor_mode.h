#pragma once
/// @file sensor_mode.h
/// The sensor mode of a run (`pipeline.mode`): monocular, or RGB-D (a depth image with every
/// frame, in metres). Tracking, keyframe creation and evaluation branch on it.

#include <array>
#include <cstdint>
#include <string_view>

#include "core/options.h"

namespace mer {

/// Sensor mode of a run.
enum class SensorMode : std::uint8_t {
  kMono,  ///< images only: depth from triangulation, map up to scale
  kRgbd,  ///< images with sensor depth: metric map
};

/// Names of SensorMode in config and output files (`pipeline.mode`), by value.
inline constexpr std::array<std::string_view, 2> kSensorModeNames{"mono", "rgbd"};

/// "mono" or "rgbd".
inline std::string_view to_string(SensorMode m) {
  return options::name_of(m, kSensorModeNames);
}

}  // namespace mer
