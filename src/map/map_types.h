#pragma once
/// @file map_types.h
/// Identifiers of map entities. Ids are slot indices into the map's preallocated storage,
/// assigned in increasing order and never reused (a bad point keeps its slot), so an id
/// read by a lock-free reader can never come to name a different entity (no ABA).

#include <cstdint>

namespace mer::map {

using KeyframeId = std::uint32_t;  ///< keyframe slot index
using PointId = std::uint32_t;     ///< map-point slot index

/// "No keyframe / no point" (an unassociated keypoint, an empty slot).
inline constexpr std::uint32_t kNoId = 0xFFFFFFFFu;

}  // namespace mer::map
