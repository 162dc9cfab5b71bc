#pragma once
/// @file final_trajectory.h
/// Every tracked frame re-anchored to the final map (trajectory_final.txt).
///
/// trajectory.txt is causal: each pose is what tracking knew at that frame. The back end
/// keeps improving the keyframes afterwards (local BA, loop closure, --final-ba); those
/// gains reach the per-frame trajectory through a re-anchoring after the run, as in
/// ORB-SLAM's saved trajectories: each frame's pose relative to the keyframe it was tracked
/// with (frame_anchors.txt, written by the output stage) is composed with that keyframe's
/// final pose, T_w_c' = T_w_kf(final) T_kf_c. The back end moves the next keyframe relative
/// to that one too (D: from the next keyframe's offset as tracked to its final pose, in the
/// keyframe's frame); a frame a fraction alpha of the way in time to the next keyframe gets
/// D^alpha: T_w_c' = T_w_kf(final) D^alpha T_kf_c, which runs on into the next keyframe.
///
/// Keyframes removed by culling are followed through their lineage: their pose relative to
/// the live keyframe that shared most points with them when they were removed
/// (backend::CulledKeyframe), composed up to a keyframe still in the map. That offset is in
/// the units of its segment then; a segment that later merged into the main one moved by a
/// similarity, so its offsets are scaled by the merges' scale.
///
/// A frame whose keyframe cannot be resolved (tracked before any keyframe existed, or its
/// lineage record forgotten: culling.lineage_capacity) is moved by the correction of the
/// last re-anchored frame before it (kept as tracked when there is none), and counted.
///
/// Limit: the relative pose keeps the scale of the moment it was measured; a Sim(3) loop
/// correction rescales the map around the keyframe but not that offset (as in ORB-SLAM).
/// The offset spans at most the keyframe spacing, so the error is that fraction of it.

#include <cstdint>
#include <span>
#include <vector>

#include "backend/map_culling.h"
#include "core/pose.h"

namespace mer::pipeline {

/// A keyframe's pose in the final map.
struct FinalKeyframePose {
  std::int64_t t_ns = 0;
  SE3d T_w_c = SE3d::Identity();
  bool from_lineage = false;  ///< removed by culling; pose through its lineage
};

/// One tracked frame as tracking wrote it (trajectory.txt + frame_anchors.txt).
struct AnchoredFrame {
  std::int64_t t_ns = 0;
  SE3d T_w_c = SE3d::Identity();   ///< pose as tracked
  bool has_anchor = false;         ///< tracked with a keyframe in the map
  std::int64_t anchor_t_ns = 0;    ///< that keyframe's timestamp
  SE3d T_kf_c = SE3d::Identity();  ///< pose relative to it
};

/// What the re-anchoring did (summary.json `final_trajectory`).
struct FinalTrajectoryStats {
  std::uint64_t frames = 0;        ///< frames written
  std::uint64_t reanchored = 0;    ///< moved with their own keyframe
  std::uint64_t via_lineage = 0;   ///< of these, through removed keyframes' lineage
  std::uint64_t interpolated = 0;  ///< of these, with a share of the next keyframe's correction
  std::uint64_t unresolved = 0;    ///< moved with the previous frame's correction (or kept)
};

/// Final poses of the live keyframes (`live`, any order) and of the removed keyframes that
/// `lineage` connects to them, sorted by time. A timestamp appears once (live wins).
/// `segment_scale[s]` takes segment s's units into those of `live` (segment_scales_into; 0: s
/// did not join it, its records are not followed); empty: every record is in those units.
std::vector<FinalKeyframePose> resolve_keyframe_poses(
    std::span<const StampedPose> live, std::span<const backend::CulledKeyframe> lineage,
    std::span<const double> segment_scale = {});

/// Re-anchors `frames` (in time order) to `keyframes` (sorted by time, as returned by
/// resolve_keyframe_poses); one output pose per frame.
std::vector<StampedPose> reanchor_frames(std::span<const AnchoredFrame> frames,
                                         std::span<const FinalKeyframePose> keyframes,
                                         FinalTrajectoryStats& stats);

}  // namespace mer::pipeline
