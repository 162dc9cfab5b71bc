#pragma once
/// @file tracking_result.h
/// What the tracking stage hands to the output stage for every processed frame.
/// Trivially copyable-ish plain data: it travels through an SpscRing by value.

#include <array>
#include <cstdint>

#include "core/pose.h"

namespace mer::frontend {

/// Localization outcome of one frame.
enum class TrackState : std::uint8_t {
  kTracked = 0,         ///< pose estimated
  kLost = 1,            ///< localization failed (frame omitted from trajectory.txt)
  kNotInitialized = 2,  ///< no map yet
};

/// Printable name of a TrackState.
constexpr const char* to_string(TrackState s) {
  switch (s) {
    case TrackState::kTracked:
      return "tracked";
    case TrackState::kLost:
      return "lost";
    case TrackState::kNotInitialized:
      return "not_initialized";
  }
  return "?";
}

/// Stages whose per-frame latency is carried with the result (columns of latency.csv).
enum class StageId : std::uint8_t { kCapture = 0, kTracking = 1, kQueue = 2, kCount = 3 };

/// Per-frame output of the tracking stage.
struct TrackingResult {
  std::uint64_t seq = 0;  ///< frame sequence number from the source
  std::int64_t t_ns = 0;  ///< frame timestamp, ns
  TrackState state = TrackState::kNotInitialized;
  bool is_keyframe = false;        ///< this frame became a keyframe
  SE3d T_w_c = SE3d::Identity();   ///< camera-to-world pose (valid when tracked)
  std::int32_t num_features = 0;   ///< features detected
  std::uint64_t feature_hash = 0;  ///< FNV-1a over feature positions (determinism checks)
  std::int64_t t_ready_ns = 0;     ///< monotonic time the frame was ready in the pool
  std::array<std::int64_t, static_cast<std::size_t>(StageId::kCount)> stage_ns{};  ///< latencies
};

}  // namespace mer::frontend
