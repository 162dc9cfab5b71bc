#pragma once
/// @file accuracy.h
/// Trajectory accuracy of a finished run, for summary.json: when the source knew the true
/// poses (synthetic camera, datasets with ground truth), the estimate (trajectory.txt) is
/// scored against them (groundtruth.txt) with the project's evaluator — ATE after Sim(3)
/// alignment for monocular runs (scale is unobservable), SE(3) for RGB-D.

#include <cstddef>
#include <string>

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

/// Writes `dir`/trajectory_final_ba.txt: every pose of `dir`/trajectory.txt moved with the
/// correction the full-graph optimization applied to its keyframe (the latest keyframe at or
/// before the frame; the first keyframe for earlier frames): T' = T_kf_after T_kf_before^-1 T.
/// The file is written atomically; trajectory.txt is not touched.
Status write_final_ba_trajectory(const std::string& dir,
                                 const std::vector<pipeline::KeyframeCorrection>& corrections);

}  // namespace mer::app
