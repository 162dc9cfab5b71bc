#pragma once
/// @file accuracy.h
/// Trajectory accuracy of a finished run, for summary.json: when the source knew the true
/// poses (synthetic camera, datasets with ground truth), the estimate (trajectory.txt) is
/// scored against them (groundtruth.txt) with the project's evaluator — ATE after Sim(3)
/// alignment for monocular runs (scale is unobservable), SE(3) for RGB-D.

#include <cstddef>
#include <span>
#include <string>
#include <vector>

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
};

/// Scores `dir`/`trajectory` (trajectory.txt by default) against `dir`/groundtruth.txt.
AccuracyReport evaluate_run(const std::string& dir, const std::string& sensor_mode,
                            const pipeline::PipelineStats& stats,
                            const std::string& trajectory = "trajectory.txt");

/// Reads `path` (frame_anchors.txt: `t kf_t tx ty tz qx qy qz qw`, kf_t `-` for a frame
/// without anchor) into `frames`, whose t_ns and T_w_c (from trajectory.txt) are set:
/// line k must carry frame k's timestamp. Errors name the file and line.
Status read_frame_anchors(const std::string& path, std::vector<pipeline::AnchoredFrame>& frames);

/// Writes `dir`/trajectory_final.txt: every pose of `dir`/trajectory.txt re-anchored to
/// `keyframes` (the final map, Pipeline::final_keyframe_poses) through
/// `dir`/frame_anchors.txt (pipeline/final_trajectory.h). Written atomically.
Status write_final_trajectory(const std::string& dir,
                              std::span<const pipeline::FinalKeyframePose> keyframes,
                              pipeline::FinalTrajectoryStats& stats);

/// --gt-check, after every output is written: loads `dir`/groundtruth.txt, runs the
/// ground-truth check (eval/groundtruth_check.h; it changes the map) on the pipeline's
/// finished map with at most `max_iterations` per full BA, writes
/// the keyframe poses it converged to (keyframes_gt_converged.txt) and those with shuffled
/// keypoint errors (keyframes_gt_shuffled.txt) and scores both as keyframes_final.txt is.
/// A source without ground truth, or a check that cannot run, leaves its reason in
/// `report.note` and is not an error; a file that cannot be written is.
Status run_gt_check(const std::string& dir, const std::string& sensor_mode, int max_iterations,
                    pipeline::Pipeline& pipe, eval::GroundTruthCheckReport& report,
                    AccuracyReport& converged, AccuracyReport& shuffled,
                    AccuracyReport& shuffled_detected);

}  // namespace mer::app
