#pragma once
/// @file ground_truth.h
/// Ground-truth trajectories in one common form, from whichever format a dataset uses,
/// for the evaluator (mer_eval), summary.json's ATE and tests.

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "core/pose.h"
#include "core/status.h"

namespace mer::hal {

/// A trajectory: camera-to-world poses sorted by time.
struct Trajectory {
  std::vector<StampedPose> poses;  ///< sorted by t_ns, strictly increasing
  std::string source;              ///< file it was read from
  /// Samples dropped when read because their timestamp repeated the previous one (the
  /// first sample of a timestamp is kept, as evo's association does). Real ground truth
  /// has them (TUM fr2/desk line 10863); readers report the count instead of failing.
  std::size_t duplicates_dropped = 0;
  int first_duplicate_line = 0;  ///< line of the first dropped sample (0: none)
};

/// Reads a TUM trajectory (`t tx ty tz qx qy qz qw` per line; '#' comments). Errors name
/// the file and line; decreasing timestamps are an error, a repeated timestamp drops the
/// repeated sample and counts it (Trajectory::duplicates_dropped).
Result<Trajectory> load_tum_trajectory(const std::string& path);

/// Reads KITTI poses (12 numbers per line, row-major 3x4 T_w_c); timestamps from
/// `times_path` (one per line, seconds) when given, else the line index in seconds.
/// `times_path` may list more times than there are poses (KITTI clips whose last images
/// have no pose); fewer times than poses is an error naming both files.
Result<Trajectory> load_kitti_trajectory(const std::string& path,
                                         const std::string& times_path = {});

/// Writes a trajectory in TUM format (`t tx ty tz qx qy qz qw`, seconds with 9 decimals,
/// one header comment line). Written to a temporary file and renamed, so a reader never
/// sees a half-written file.
Status save_tum_trajectory(const std::string& path, const Trajectory& traj);

/// The pose of `traj` at time `t_ns`, interpolated between the two samples that bracket it
/// (translation linearly, rotation by quaternion slerp with weight
/// a = (t - t0) / (t1 - t0)). Both bracketing samples must lie within `max_dt_ns` of
/// `t_ns`; a time equal to a sample returns that sample. Returns nullopt otherwise (before
/// the first or after the last sample, or inside a gap in the ground truth), so a frame is
/// never given a pose extrapolated or interpolated across a gap.
std::optional<SE3d> interpolate_pose(const Trajectory& traj, std::int64_t t_ns,
                                     std::int64_t max_dt_ns);

}  // namespace mer::hal
