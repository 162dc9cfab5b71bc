#pragma once
/// @file kitti_loader.h
/// `kitti:DIR` — a KITTI odometry sequence folder:
/// - `image_0/NNNNNN.png` (6-digit frame index; rectified 8-bit gray);
/// - `calib.txt`: `P0:` 3x4 projection -> fx = P[0][0], fy = P[1][1], cx = P[0][2],
///   cy = P[1][2], no distortion (the calibration override replaces them when set);
/// - `times.txt`: one time in seconds per line; it defines the frames (frame i is
///   `image_0/` i); images beyond it are ignored;
/// - optional `poses.txt`: 12 numbers per line, row-major 3x4 T_w_c of frame i on line i.
///   It may hold FEWER poses than frames (frames beyond have no ground truth); more poses
///   than frames is an error.
/// Errors and skips: see folder_loader.h.

#include "hal/replay/folder_loader.h"

namespace mer::hal {

/// Loader of a KITTI odometry sequence (left gray camera).
class KittiLoader final : public FolderLoader {
 public:
  KittiLoader(std::string dir, const CalibrationOptions& calib);

  Status open() override;
};

}  // namespace mer::hal
