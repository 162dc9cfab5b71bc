#pragma once
/// @file tum_loader.h
/// `tum:DIR` — a TUM RGB-D folder:
/// - `rgb.txt`: `timestamp filename` lines ('#' comments), images relative to DIR (color or
///   gray PNG, converted to 8-bit gray);
/// - `depth.txt` + 16-bit depth PNGs (RGB-D mode only; depth in metres = value / depth_scale,
///   0 = no measurement); each rgb frame takes the depth image with the nearest timestamp
///   if it is within `max_dt_ns`, otherwise the frame is skipped (counted) in RGB-D mode;
/// - optional `groundtruth.txt` (TUM trajectory): each frame gets the pose interpolated at
///   its time when ground-truth samples bracket it within `max_dt_ns` (interpolate_pose()).
/// TUM folders carry no intrinsics: they must come from the calibration override
/// (`--intrinsics` / `camera.calibration`); open() fails with kInvalidArgument otherwise.
/// Errors and skips: see folder_loader.h.

#include "hal/replay/folder_loader.h"

namespace mer::hal {

/// Loader of a TUM RGB-D folder.
class TumLoader final : public FolderLoader {
 public:
  /// `rgbd` loads depth; `depth_scale` is depth units per metre (5000 for TUM);
  /// `max_dt_ns` bounds rgb-depth association and ground-truth interpolation.
  TumLoader(std::string dir, const CalibrationOptions& calib, bool rgbd, double depth_scale,
            std::int64_t max_dt_ns);

  Status open() override;

 private:
  std::int64_t max_dt_ns_;
};

}  // namespace mer::hal
