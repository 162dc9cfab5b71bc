#pragma once
/// @file keypoint.h
/// Keypoints and binary descriptors shared by the extractor, the map and the front end.

#include <algorithm>
#include <array>
#include <bit>
#include <cstdint>
#include <span>

namespace mer::features {

/// A 256-bit binary descriptor (ORB / rBRIEF), 32 bytes as four 64-bit words.
using Descriptor = std::array<std::uint64_t, 4>;

/// Hamming distance between two descriptors (0..256).
inline int hamming(const Descriptor& a, const Descriptor& b) {
  return std::popcount(a[0] ^ b[0]) + std::popcount(a[1] ^ b[1]) + std::popcount(a[2] ^ b[2]) +
         std::popcount(a[3] ^ b[3]);
}

/// Squared keypoint sigma at pyramid level `level` from a per-level table (level clamped to
/// the table; 1 when the table is empty).
inline float level_sigma2(std::span<const float> table, int level) {
  if (table.empty()) return 1.0F;
  return table[static_cast<std::size_t>(std::clamp(level, 0, static_cast<int>(table.size()) - 1))];
}

/// A keypoint in level-0 pixel coordinates.
struct Keypoint {
  float x = 0.0F;          ///< column, level-0 px (sub-pixel allowed)
  float y = 0.0F;          ///< row, level-0 px
  float angle_rad = 0.0F;  ///< orientation (intensity centroid), radians
  float response = 0.0F;   ///< detector score (higher is stronger)
  std::int8_t level = 0;   ///< pyramid level it was detected at
  /// 1: a map keypoint that measures its point's anchor (the anchor's own detection, or
  /// aligned to it: depth.align_keypoints), so it agrees with the point's other anchored
  /// keypoints more closely than independent detections do; 0 otherwise.
  std::uint8_t anchored = 0;
  float scale = 1.0F;  ///< scale factor of that level (scale_factor^level)
};

}  // namespace mer::features
