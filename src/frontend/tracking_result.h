#pragma once
/// @file tracking_result.h
/// What the tracking stage hands to the output stage for every processed frame.
/// Trivially copyable-ish plain data: it travels through an SpscRing by value.

#include <array>
#include <cstddef>
#include <cstdint>

#include <Eigen/Geometry>

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

/// The tracker's state machine (frames.csv `tracker_state`), after the frame:
/// - initializing: no map yet (two-view or RGB-D initialization is being tried);
/// - tracking: the frame was localized against the map;
/// - lost: localization failed; the next frames still search from the last pose with a wide
///   radius (`tracking.relocalize_after_lost_frames` of them before relocalization is asked);
/// - relocalizing: localization has failed for that many frames; each frame is also offered to
///   the relocalizer (retrieval of keyframes by the frame's descriptors, PnP-RANSAC), and a pose
///   it finds is the prediction of the next frame's search;
/// - new_segment: tracking was lost for `tracking.new_segment_after_s` without relocalizing: a
///   new map segment, with a world frame of its own, is being initialized (as at the start),
///   while each frame is still offered to the relocalizer. A relocalization returns to the
///   segment of the keyframe found; an initialization continues in the new segment.
/// - initializing_rotation: initializing the first map, and the frame was found to be a pure
///   rotation of the initializer's reference: its orientation is known (TrackingResult
///   `has_orientation`), its position and the map are not.
enum class TrackerState : std::uint8_t {
  kInitializing = 0,
  kTracking = 1,
  kLost = 2,
  kRelocalizing = 3,
  kNewSegment = 4,
  kInitializingRotation = 5,
};
/// Number of TrackerState values (counters indexed by it).
inline constexpr std::size_t kTrackerStateCount =
    static_cast<std::size_t>(TrackerState::kInitializingRotation) + 1;

/// Printable name of a TrackerState.
constexpr const char* to_string(TrackerState s) {
  switch (s) {
    case TrackerState::kInitializing:
      return "initializing";
    case TrackerState::kTracking:
      return "tracking";
    case TrackerState::kLost:
      return "lost";
    case TrackerState::kRelocalizing:
      return "relocalizing";
    case TrackerState::kNewSegment:
      return "new_segment";
    case TrackerState::kInitializingRotation:
      return "initializing_rotation";
  }
  return "?";
}

/// Stages whose per-frame latency is carried with the result (columns of latency.csv).
enum class StageId : std::uint8_t { kCapture = 0, kTracking = 1, kQueue = 2, kCount = 3 };

/// Steps of tracking whose time is carried with each result (the latency breakdown).
enum class TrackStep : std::uint8_t { kExtract = 0, kQuery, kMatch, kPose, kDecide, kCount };

/// Printable name of a TrackStep.
constexpr const char* to_string(TrackStep s) {
  switch (s) {
    case TrackStep::kExtract:
      return "extract";
    case TrackStep::kQuery:
      return "query";
    case TrackStep::kMatch:
      return "match";
    case TrackStep::kPose:
      return "pose";
    case TrackStep::kDecide:
      return "decide";
    case TrackStep::kCount:
      break;
  }
  return "?";
}

/// Per-frame output of the tracking stage.
struct TrackingResult {
  std::uint64_t seq = 0;  ///< frame sequence number from the source
  std::int64_t t_ns = 0;  ///< frame timestamp, ns
  TrackState state = TrackState::kNotInitialized;
  TrackerState tracker_state = TrackerState::kInitializing;  ///< state machine after the frame
  /// The frame should be offered to the relocalizer (state relocalizing): the caller fills a
  /// RelocalizationRequest with Tracker::fill_relocalization_request while the frame's
  /// features are still the tracker's (before its next spin_once).
  bool relocalization_request = false;
  bool relocalized = false;  ///< tracked from a relocalizer's pose (after a lost spell)
  /// When relocalized: the keyframe the relocalizer matched (its timestamp, ns; 0 when it was
  /// culled meanwhile) and the frame's pose relative to it as the map held it then
  /// (T_rkf_c = T_w_kf^-1 T_w_c), for ground-truth audits of relocalizations.
  std::int64_t reloc_keyframe_t_ns = 0;
  SE3d T_rkf_c = SE3d::Identity();
  bool reloc_confirmed = false;    ///< confirmed on following frames (not trusted at once)
  float reloc_found_ratio = 0.0F;  ///< found share / usual share: the lowest while
                                   ///< confirming, or the frame's when trusted at once
  std::uint16_t segment = 0;       ///< map segment whose world frame T_w_c is in (0: the first)
  /// This frame found the segment `discarded_segment` a failed start (tracking.init.
  /// discard_failed_starts): the frames tracked in it count as lost from now on.
  bool discarded_start = false;
  std::uint16_t discarded_segment = 0;  ///< valid when discarded_start
  bool is_keyframe = false;             ///< this frame became a keyframe
  bool keyframe_job = false;            ///< the keyframe still has to be created (queue a job)
  SE3d T_w_c = SE3d::Identity();        ///< camera-to-world pose (valid when tracked)
  /// Not tracked (no map yet), monocular: the frame is a pure rotation of the initializer's
  /// reference, and its orientation is known in the world of the chain of references it belongs
  /// to (the chain's first reference camera; frontend/initializer.h). Its position is not.
  bool has_orientation = false;
  std::uint32_t orientation_chain = 0;  ///< that chain (a new number: a new world)
  Eigen::Quaterniond q_chain_c = Eigen::Quaterniond::Identity();  ///< camera-to-chain rotation
  /// Tracked with a keyframe in the map: the pose relative to the newest keyframe as the map
  /// held it then (T_kf_c = T_w_kf^-1 T_w_c), to re-anchor the frame to the final map.
  bool has_anchor = false;
  std::int64_t anchor_t_ns = 0;      ///< that keyframe's timestamp, ns (its identity)
  SE3d T_kf_c = SE3d::Identity();    ///< pose relative to that keyframe
  std::int32_t num_features = 0;     ///< features detected
  std::int32_t num_matches = 0;      ///< map-point matches given to PnP
  std::int32_t num_inliers = 0;      ///< matches consistent with the pose
  std::int32_t query_temporal = 0;   ///< |Q_T|: points of the recently tracked keyframes
  std::int32_t query_spatial = 0;    ///< |Q_S|: points in the cells visible from the prediction
  std::int32_t query_total = 0;      ///< |Q_T u Q_S|
  std::uint8_t keyframe_reason = 0;  ///< KeyframeReason that fired (0: none)
  bool steady = false;               ///< tracked against an existing map (not initializing)
  float kl = 0.0F;                   ///< KL divergence of the tracked-point histogram
  double focal = 0.0;                ///< focal length used, px
  std::array<std::int32_t, static_cast<std::size_t>(TrackStep::kCount)> step_ns{};  ///< breakdown
  std::uint64_t feature_hash = 0;    ///< FNV-1a over feature positions (determinism checks)
  bool has_ground_truth = false;     ///< the source knew the true pose of this frame
  SE3d T_w_c_gt = SE3d::Identity();  ///< true camera-to-world pose (when has_ground_truth)
  std::int64_t t_ready_ns = 0;       ///< monotonic time the frame was ready in the pool
  std::array<std::int64_t, static_cast<std::size_t>(StageId::kCount)> stage_ns{};  ///< latencies
};

}  // namespace mer::frontend
