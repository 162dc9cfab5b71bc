#pragma once
/// @file map_internal.h
/// Internal to the map library: helpers shared by map.cpp, map_segments.cpp, map_covisibility.cpp
/// and map_read.cpp. Not part of the map's interface.

#include <cstdint>

#include "map/map.h"

namespace mer::map::map_detail {

inline constexpr std::uint32_t kLow32Mask = 0xFFFFFFFFu;
// A segment's fate (Map::fate_).
inline constexpr std::uint8_t kFateLive = 0;
inline constexpr std::uint8_t kFateMerged = 1;
inline constexpr std::uint8_t kFateDiscarded = 2;

inline std::uint64_t pack_edge(const CovisibleKeyframe& e) noexcept {
  return (static_cast<std::uint64_t>(e.id) << 32U) | e.weight;
}
inline CovisibleKeyframe unpack_edge(std::uint64_t w) noexcept {
  return {static_cast<KeyframeId>(w >> 32U), static_cast<std::uint32_t>(w & kLow32Mask)};
}
/// Edge order: weight descending, then id ascending (deterministic).
inline bool stronger(const CovisibleKeyframe& a, const CovisibleKeyframe& b) noexcept {
  return a.weight != b.weight ? a.weight > b.weight : a.id < b.id;
}

inline std::uint32_t as_u32(int v) noexcept {
  return static_cast<std::uint32_t>(v);
}

}  // namespace mer::map::map_detail
