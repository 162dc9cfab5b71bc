#pragma once
/// @file euroc_loader.h
/// `euroc:DIR` — a EuRoC MAV (ASL) folder, DIR being the folder that holds `mav0/` (or
/// `mav0/` itself):
/// - `mav0/cam0/data.csv` (`#timestamp [ns],filename`) and the PNGs in `mav0/cam0/data/`,
///   left as they are (distorted; the intrinsics carry the distortion);
/// - `mav0/cam0/sensor.yaml`: `resolution`, `intrinsics: [fu, fv, cu, cv]`,
///   `distortion_coefficients: [k1, k2, p1, p2]` (radtan) and `T_BS` (camera to body);
///   the resolution must match the images; the calibration override replaces the
///   intrinsics when set;
/// - optional `mav0/state_groundtruth_estimate0/data.csv` (body poses T_w_b), converted to
///   camera poses T_w_c = T_w_b * T_BS and interpolated at the frame times
///   (interpolate_pose() within `max_dt_ns`).
/// Errors and skips: see folder_loader.h.

#include "hal/replay/folder_loader.h"

namespace mer::hal {

/// Loader of a EuRoC folder (cam0 only; monocular).
class EurocLoader final : public FolderLoader {
 public:
  /// `max_dt_ns` bounds ground-truth interpolation.
  EurocLoader(std::string dir, const CalibrationOptions& calib, std::int64_t max_dt_ns);

  Status open() override;

  /// The camera-to-body extrinsic read from sensor.yaml (valid after open()).
  const SE3d& T_b_c() const { return T_b_c_; }

 private:
  std::int64_t max_dt_ns_;
  SE3d T_b_c_ = SE3d::Identity();
};

}  // namespace mer::hal
