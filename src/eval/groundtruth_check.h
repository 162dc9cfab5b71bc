#pragma once
/// Ground-truth check of a finished map's observations (offline, `mer_slam --gt-check`), run
/// by the application after the pipeline has stopped.
///
/// The final BA returns the poses its observations favour. Where that differs from the truth,
/// the cause is either the estimate's history (initialization, tracking, loop closure: a
/// local minimum) or the observations themselves (keypoints, associations). The check tells
/// them apart, on a source with ground truth:
///  1. Every live keyframe is moved to its ground-truth pose, brought into the map frame by
///     the transform (Umeyama; with scale for monocular maps, without for metric ones) that
///     best maps the ground-truth keyframe centres onto the map's. Each point rides with its
///     reference keyframe.
///  2. Each point with two or more observations is re-fitted to them with the keyframes held
///     at the truth (Gauss-Newton on the sigma-weighted reprojection error). A point whose
///     observation rays meet at less than kMinRefitParallaxDeg, or whose re-fit fails, keeps
///     the position it rode to and is left out of the check (`refit_rejected`). What is left
///     of each observation of a re-fitted point is its keypoint's error against the true
///     geometry; its RMS per pyramid level, in pixels of that level, is reported.
///  3. The full BA runs from there without culling points (`converged`): the poses the map's
///     own observations lead to from the truth, not from the run's history. It is a local
///     optimum like any other: no bound on what the run could have reached.
///  4. Every point and keyframe goes back to where step 3 started, and the keypoint of every
///     checked observation is set to its ground-truth projection plus an error drawn, without
///     replacement, from the errors of step 2 at the same level (an error may land where it
///     was); the full BA runs again on the same points (`shuffled`). The errors keep their
///     sizes and their distribution but lose any pattern across observations (a detector
///     that is off the same way in similar views, a point matched to the wrong corner in
///     several keyframes). The gap between `converged` and `shuffled` is what such patterns
///     cost. Only keypoints are shuffled: 3D-3D depth edges (RGB-D) keep their depths, and
///     with `backend.depth_edges: scaled` the depth scales step 3 folds in stay for step 4
///     (and those of steps 3 and 4 for step 5).
///  5. When some checked keypoints are anchored (depth.align_keypoints) and some are not,
///     step 4 again with only the keypoints that are not anchored trading errors, among
///     themselves; anchored keypoints keep their own (`shuffled_detected`). Close to
///     `shuffled`: the pattern lives in the detected keypoints; close to `converged`: in
///     the anchored ones.
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

namespace mer::eval {

/// Observation rays of a point meeting at less than this leave its re-fit ill-posed, degrees.
inline constexpr double kMinRefitParallaxDeg = 1.0;

/// Keypoint errors of one pyramid level against the ground truth (step 2).
struct GroundTruthLevelError {
  int observations = 0;       ///< checked observations at this level
  double rms_level_px = 0.0;  ///< RMS per image axis of those within 5 level px, level px
};

/// Result of check_against_groundtruth.
struct GroundTruthCheckReport {
  bool ran = false;                ///< the check ran (else `note` says why)
  std::string note;                ///< why it did not run
  int keyframes = 0;               ///< live keyframes (all have a ground-truth pose when ran)
  int points = 0;                  ///< points re-fitted and checked
  int refit_rejected = 0;          ///< points left out: too little parallax, or no re-fit
  int observations = 0;            ///< checked observations (of the checked points)
  int unprojected = 0;             ///< observations behind their camera (keep their keypoint)
  double scale = 1.0;              ///< alignment scale, ground truth -> map (1: metric map)
  double beyond_1_level_px = 0.0;  ///< fraction of observations off by more than 1 level px
  double beyond_2_level_px = 0.0;  ///< fraction off by more than 2 level px
  std::vector<GroundTruthLevelError> levels;  ///< per pyramid level
  int anchored_observations = 0;              ///< checked observations whose keypoint is anchored
  double anchored_rms_level_px = 0.0;    ///< RMS per axis (within 5 level px) of those, level px
  double detected_rms_level_px = 0.0;    ///< and of the other checked observations, level px
  int iterations_converged = 0;          ///< full-BA iterations of step 3
  int iterations_shuffled = 0;           ///< and of step 4
  std::vector<StampedPose> converged;    ///< keyframe poses after step 3, map frame
  std::vector<StampedPose> shuffled;     ///< keyframe poses after step 4, map frame
  int iterations_shuffled_detected = 0;  ///< full-BA iterations of step 5 (0: not run)
  std::vector<StampedPose> shuffled_detected;  ///< keyframe poses after step 5 (empty: not run)
};

/// Runs the check (above) on `map` with `ba` (its options: robust kernel, outlier gate) for
/// at most `max_iterations` LM iterations per full BA. `groundtruth`: camera-to-world poses
/// sorted by time; a keyframe takes the pose nearest its time within `max_dt_ns`.
/// `with_scale`: align with a similarity (monocular maps) or a rigid motion (metric maps).
/// Does not run (note says why) when a live keyframe has no ground-truth pose, with fewer
/// than three keyframes, or when the ground-truth keyframe centres do not move. `seed` fixes
/// the shuffle. No other thread may use the map meanwhile.
GroundTruthCheckReport check_against_groundtruth(map::Map& map, backend::LocalBundleAdjuster& ba,
                                                 const geometry::Pinhole& K,
                                                 std::span<const StampedPose> groundtruth,
                                                 std::int64_t max_dt_ns, bool with_scale,
                                                 int max_iterations, std::uint64_t seed);

}  // namespace mer::eval
