#pragma once
/// @file accuracy.h
/// Trajectory accuracy of a finished run, for summary.json: when the source knew the true
/// poses (synthetic camera, datasets with ground truth), the estimate (trajectory.txt) is
/// scored against them (groundtruth.txt) with the project's evaluator — ATE after Sim(3)
/// alignment for monocular runs (scale is unobservable), SE(3) for RGB-D.

#include <cstddef>
#include <cstdint>
#include <span>
#include <string>
#include <vector>

#include "core/sensor_mode.h"
#include "eval/groundtruth_check.h"
#include "pipeline/pipeline.h"

namespace mer::app {

/// ATE of one run.
struct AccuracyReport {
  bool available = false;     ///< ground truth and at least 3 tracked frames
  std::string note;           ///< why not, when not available
  std::string alignment;      ///< sim3 | se3
  std::size_t pairs = 0;      ///< associated poses
  std::size_t gt_frames = 0;  ///< frames with ground truth
  double scale = 1.0;         ///< Sim(3) scale of the alignment
  double ate_rmse_m = 0.0;
  double ate_mean_m = 0.0;
  double ate_median_m = 0.0;
  double ate_max_m = 0.0;
  double path_length_m = 0.0;           ///< ground-truth path length over the associated frames
  double ate_pct_of_path = 0.0;         ///< 100 * ATE RMSE / path length
  double tracked_after_init_pct = 0.0;  ///< tracked frames / frames from initialization on
  /// The first kStartWindowS of the scored frames (from the start of the trajectory's segment),
  /// aligned on their own: a fast start must not be a bad one (pairs 0: fewer than 3).
  std::size_t start_pairs = 0;
  double start_ate_rmse_m = 0.0;
  double start_path_length_m = 0.0;
  double start_ate_pct_of_path = 0.0;
};

/// Span after the first scored frame of AccuracyReport's start figures, s.
inline constexpr double kStartWindowS = 5.0;

/// Scores `dir`/`trajectory` (trajectory.txt by default) against `dir`/groundtruth.txt.
/// With `only_segment` >= 0, only the frames frames.csv says were tracked in that map
/// segment are scored (aligned on their own): a merged segment's own accuracy, read from
/// the file it was joined into.
AccuracyReport evaluate_run(const std::string& dir, SensorMode sensor_mode,
                            const pipeline::PipelineStats& stats,
                            const std::string& trajectory = "trajectory.txt",
                            int only_segment = -1);

/// A relocalization or loop closure further from the truth than this is counted as wrong, m.
inline constexpr double kWrongRelocalizationM = 0.10;
inline constexpr double kWrongLoopM = 0.50;

/// One accepted relocalization or closed loop, checked against the ground truth: the
/// estimated relative pose between its two views (the frame and the keyframe it was matched
/// to; the new and the old keyframe of a loop), scaled to metres by its segment's alignment,
/// against the true one.
struct EventAudit {
  std::string kind;            ///< relocalization | loop
  std::uint64_t seq = 0;       ///< the frame (relocalization) or the new keyframe's (loop)
  double t_s = 0.0;            ///< its timestamp, s
  double other_t_s = 0.0;      ///< the matched keyframe's timestamp, s
  std::uint16_t segment = 0;   ///< segment it happened in
  bool scored = false;         ///< both views had ground truth and the segment a scale
  double gt_distance_m = 0.0;  ///< true distance between the two camera centres
  double error_m = 0.0;        ///< estimated vs true relative position
  double error_deg = 0.0;      ///< estimated vs true relative rotation
  bool wrong = false;          ///< error_m above kWrongRelocalizationM / kWrongLoopM
  double found_new = 0.0;      ///< loop: LoopClosureEvent::found_new
  double found_old = 0.0;      ///< loop: LoopClosureEvent::found_old
  double found_usual = 0.0;    ///< loop: LoopClosureEvent::found_usual
  int rival_inliers = 0;       ///< loop: LoopClosureEvent::rival_inliers
  int inliers = 0;             ///< loop: LoopClosureEvent::inliers
  double drift = 0.0;          ///< loop: LoopClosureEvent::drift
  bool connected = false;      ///< loop: LoopClosureEvent::connected
  bool confirmed = false;      ///< relocalization: confirmed on following frames
  double found_ratio = 0.0;    ///< relocalization: RelocalizationEvent::found_ratio
};

/// Ground-truth audit of a run's relocalizations and loop closures.
struct EventAuditReport {
  bool available = false;         ///< the source had ground truth
  std::string note;               ///< why not
  int relocalizations = 0;        ///< accepted relocalizations scored
  int relocalizations_wrong = 0;  ///< of those, more than kWrongRelocalizationM off
  int loops = 0;                  ///< closed loops scored
  int loops_wrong = 0;            ///< of those, more than kWrongLoopM off
  std::vector<EventAudit> events;
};

/// Scores the run's accepted relocalizations and closed loops (PipelineStats) against
/// `dir`/groundtruth.txt; `segments` are the per-segment ATE reports (their Sim(3) scale turns
/// map units into metres), in the order of stats.segments.
EventAuditReport audit_events(const std::string& dir, const pipeline::PipelineStats& stats,
                              const std::vector<AccuracyReport>& segments);

/// Reads `path` (frame_anchors.txt: `t kf_t segment tx ty tz qx qy qz qw`, kf_t `-` for a
/// frame without anchor; without the segment field, segment 0) into `frames`, whose t_ns and
/// T_w_c (from trajectory.txt) are set. `segment_scale` (per segment id: the scale from its
/// units into trajectory.txt's, 0 when its frames are not there; empty: every line is
/// trajectory.txt's, scale 1) selects the lines, in order: each must carry the next frame's
/// timestamp and every frame must have one. Anchors are scaled into trajectory.txt's units;
/// a frame without anchor of `main_segment` must repeat its trajectory.txt pose. Errors name
/// the file and line.
Status read_frame_anchors(const std::string& path, std::vector<pipeline::AnchoredFrame>& frames,
                          std::span<const double> segment_scale = {},
                          std::uint16_t main_segment = 0);

/// Writes `dir`/trajectory_final.txt: every pose of `dir`/trajectory.txt re-anchored to
/// `keyframes` (the final map, Pipeline::final_keyframe_poses) through
/// `dir`/frame_anchors.txt (pipeline/final_trajectory.h). Written atomically.
/// `segment_scale`, `main_segment`: as read_frame_anchors.
Status write_final_trajectory(const std::string& dir,
                              std::span<const pipeline::FinalKeyframePose> keyframes,
                              pipeline::FinalTrajectoryStats& stats,
                              std::span<const double> segment_scale = {},
                              std::uint16_t main_segment = 0);

/// --gt-check, after every output is written: loads `dir`/groundtruth.txt, runs the
/// ground-truth check (eval/groundtruth_check.h; it changes the map) on the pipeline's
/// finished map with at most `max_iterations` per full BA, writes
/// the keyframe poses it converged to (keyframes_gt_converged.txt) and those with shuffled
/// keypoint errors (keyframes_gt_shuffled.txt) and scores both as keyframes_final.txt is.
/// A source without ground truth, or a check that cannot run, leaves its reason in
/// `report.note` and is not an error; a file that cannot be written is.
Status run_gt_check(const std::string& dir, SensorMode sensor_mode, int max_iterations,
                    pipeline::Pipeline& pipe, eval::GroundTruthCheckReport& report,
                    AccuracyReport& converged, AccuracyReport& shuffled,
                    AccuracyReport& shuffled_detected);

}  // namespace mer::app
