#pragma once
/// @file summary.h
/// summary.json (stable key names; later features add keys, never rename them) and the
/// human-readable summary printed at the end of a run.
///
/// Keys: frames_in, frames_processed, frames_dropped, frames_lost, keyframes, map_points
/// (alive at the end), map {..., live_keyframes, live_points, keyframe_slots_used,
/// point_slots_used, culled_keyframes, culled_points, culled_keyframes_at_capacity,
/// culled_points_at_capacity, bad_points, reused_keyframe_slots, reused_point_slots,
/// culling_mean_ms, culling_max_ms}, wall_time_s, latency_ms {stage: {p50, p90, p99, max, mean,
/// count, budget}}, budget_overruns {stage: n}, allocs_per_frame {thread: n}, plus run details
/// (input, mode, pose_source, end_reason, pool_exhausted, output_overflows,
/// source_counters {skipped, error_frames, seq_gaps, restarts, damage}, threads, ...).

#include <ostream>
#include <string>

#include "app/accuracy.h"
#include "core/sensor_mode.h"
#include "core/status.h"
#include "hal/camera.h"
#include "pipeline/pipeline.h"

namespace mer::app {

/// Run details that are not pipeline counters.
struct RunInfo {
  std::string input;                           ///< --input URI
  std::string source;                          ///< the source's description
  hal::CameraIntrinsics intrinsics;            ///< calibration in use
  SensorMode sensor_mode = SensorMode::kMono;  ///< pipeline.mode
  bool stopped_by_signal = false;
  std::string error;                  ///< non-empty when the run failed
  AccuracyReport accuracy;            ///< ATE against the source's ground truth (when it had one)
  AccuracyReport accuracy_keyframes;  ///< ATE of keyframes_final.txt (the final map)
  /// ATE of each segment's own trajectory file, aligned on its own (PipelineStats::segments)
  std::vector<AccuracyReport> accuracy_segments;
  /// ATE of the frames each segment tracked itself, aligned on their own (differs from
  /// accuracy_segments for segments whose frames were joined with a merged segment's)
  std::vector<AccuracyReport> accuracy_segments_own;
  EventAuditReport events;                ///< relocalizations and loops against the ground truth
  bool final_trajectory_written = false;  ///< trajectory_final.txt was written
  pipeline::FinalTrajectoryStats final_trajectory;  ///< how its frames were re-anchored
  AccuracyReport accuracy_final;          ///< ATE of trajectory_final.txt (frames on the final map)
  bool gt_check_requested = false;        ///< --gt-check
  eval::GroundTruthCheckReport gt_check;  ///< its result
  AccuracyReport accuracy_gt_converged;   ///< ATE of keyframes_gt_converged.txt
  AccuracyReport accuracy_gt_shuffled;    ///< ATE of keyframes_gt_shuffled.txt
  AccuracyReport accuracy_gt_shuffled_detected;  ///< of keyframes_gt_shuffled_detected.txt
};

/// Renders summary.json.
std::string summary_json(const pipeline::PipelineStats& stats, const RunInfo& info);

/// Writes `text` to `path` atomically (temporary file + rename).
Status write_file_atomic(const std::string& path, const std::string& text);

/// Prints the human-readable summary (latency table, allocation counts, counters).
void print_summary(std::ostream& os, const pipeline::PipelineStats& stats, const RunInfo& info);

}  // namespace mer::app
