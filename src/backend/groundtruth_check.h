#pragma once
/// Ground-truth check of a finished map's observations (offline, `mer_slam --gt-check`).
///
/// The final BA returns the poses its observations favour. Where that differs from the truth,
/// the cause is either the estimate's history (initialization, tracking, loop closure: a
/// local minimum) or the observations themselves (keypoints, associations). The check tells
/// them apart, on a source with ground truth:
///  1. Every live keyframe is moved to its ground-truth pose, brought into the map frame by
///     the similarity (Umeyama, scale included) that best maps the ground-truth keyframe
///     centres onto the map's. Each point rides with its reference keyframe.
///  2. Each point is re-fitted to its observations with the keyframes held at the truth
///     (Gauss-Newton on the sigma-weighted reprojection error; a point with too little
///     parallax for that keeps the position it rode to). What is left of each
///     observation is its keypoint's error against the true geometry; its RMS per pyramid
///     level, in pixels of that level, is reported.
///  3. The full BA runs from there (`converged`): the poses the map's own observations
///     favour. Started at the truth, it cannot be caught by a bad start.
///  4. Every keypoint is then set to its ground-truth projection plus an error drawn, without
///     replacement, from the errors of step 2 at the same level (`shuffled`); the keyframes
///     and points go back to the truth and the full BA runs again. The errors keep their
///     sizes and their distribution but lose any pattern across observations (a detector
///     that is off the same way in similar views, a point matched to the wrong corner in
///     several keyframes). The gap between `converged` and `shuffled` is what such patterns
///     cost.
/// The map is changed for good (poses, points and keypoints): the check runs after every
/// output has been written, with no stage running.

#include <cstdint>
#include <span>
#include <string>
#include <vector>

#include "backend/local_ba.h"
#include "core/pose.h"
#include "geometry/camera_model.h"
#include "map/map.h"

namespace mer::backend {

/// Keypoint errors of one pyramid level against the ground truth (step 2).
struct GroundTruthLevelError {
  int observations = 0;       ///< observations at this level
  double rms_level_px = 0.0;  ///< RMS per image axis, pixels of this level
};

/// Result of check_against_groundtruth.
struct GroundTruthCheckReport {
  bool ran = false;
  std::string note;          ///< why it did not run
  int keyframes = 0;         ///< live keyframes (all have a ground-truth pose when ran)
  int points = 0;            ///< points with two or more observations (re-fitted)
  int observations = 0;      ///< their observations
  int unprojected = 0;       ///< observations behind their camera (keep their keypoint)
  double scale = 1.0;        ///< similarity scale, ground truth -> map
  double beyond_1_px = 0.0;  ///< fraction of observations off by more than 1 level px
  double beyond_2_px = 0.0;  ///< fraction off by more than 2 level px
  std::vector<GroundTruthLevelError> levels;  ///< per pyramid level
  int iterations_converged = 0;               ///< full-BA iterations of step 3
  int iterations_shuffled = 0;                ///< and of step 4
  std::vector<StampedPose> converged;         ///< keyframe poses after step 3, map frame
  std::vector<StampedPose> shuffled;          ///< keyframe poses after step 4, map frame
};

/// Runs the check (above) on `map` with `ba` (its options: robust kernel, outlier gate) for
/// at most `max_iterations` LM iterations per full BA. `groundtruth`: camera-to-world poses
/// sorted by time; a keyframe takes the pose nearest its time within `max_dt_ns`. Does not
/// run (note says why) when a live keyframe has no ground-truth pose, with fewer than three
/// keyframes, or when the ground-truth keyframe centres are degenerate (no motion).
/// `seed` fixes the shuffle. No other thread may use the map meanwhile.
GroundTruthCheckReport check_against_groundtruth(map::Map& map, LocalBundleAdjuster& ba,
                                                 const geometry::Pinhole& K,
                                                 std::span<const StampedPose> groundtruth,
                                                 std::int64_t max_dt_ns, int max_iterations,
                                                 std::uint64_t seed);

}  // namespace mer::backend
