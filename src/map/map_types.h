#pragma once
/// @file map_types.h
/// Identifiers of map entities. Ids are slot indices into the map's preallocated storage.
/// A slot freed by culling is reused for a new entity once every registered reader has
/// passed a quiescent point (map.h), so an id names one entity only together with the
/// slot's generation, which changes every time the slot is freed. An id a reader obtained
/// in its current read section keeps naming the same entity until its next quiescent point;
/// an id kept longer is validated by comparing generations.

#include <cstdint>

namespace mer::map {

using KeyframeId = std::uint32_t;  ///< keyframe slot index
using PointId = std::uint32_t;     ///< map-point slot index
using Generation = std::uint32_t;  ///< occupant of a slot: incremented when the slot is freed

/// "No keyframe / no point" (an unassociated keypoint, an empty slot).
inline constexpr std::uint32_t kNoId = 0xFFFFFFFFu;
/// Generation reported for a free or unknown slot (never a live occupant's).
inline constexpr Generation kNoGeneration = 0xFFFFFFFFu;
/// Map segment reported for an unknown keyframe (never a live keyframe's).
inline constexpr std::uint16_t kNoSegment = 0xFFFFu;
/// Map segments one map holds (segment ids 0 .. kMaxSegments - 1).
inline constexpr std::uint16_t kMaxSegments = 256;

}  // namespace mer::map
