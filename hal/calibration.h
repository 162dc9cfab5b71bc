#pragma once
/// @file calibration.h
/// The calibration override shared by every camera backend (config `camera.calibration`,
/// or `--intrinsics`).

#include "core/options.h"
#include "hal/camera.h"

namespace mer::hal {

/// Calibration override (config section `camera.calibration`, or `--intrinsics`).
/// Zero focal length means "use the source's own calibration".
struct CalibrationOptions {
  double fx = 0.0;
  double fy = 0.0;
  double cx = 0.0;
  double cy = 0.0;
  double k1 = 0.0;
  double k2 = 0.0;
  double p1 = 0.0;
  double p2 = 0.0;

  template <class V>
  void visit(V& v) {
    v.field("fx", fx, "focal length x, px (0: from the source)", options::Range<double>{0.0, 1e5});
    v.field("fy", fy, "focal length y, px (0: from the source)", options::Range<double>{0.0, 1e5});
    v.field("cx", cx, "principal point x, px", options::Range<double>{0.0, 1e5});
    v.field("cy", cy, "principal point y, px", options::Range<double>{0.0, 1e5});
    v.field("k1", k1, "radial distortion k1", options::Range<double>{-10.0, 10.0});
    v.field("k2", k2, "radial distortion k2", options::Range<double>{-10.0, 10.0});
    v.field("p1", p1, "tangential distortion p1", options::Range<double>{-10.0, 10.0});
    v.field("p2", p2, "tangential distortion p2", options::Range<double>{-10.0, 10.0});
  }

  /// True when an override is set.
  bool is_set() const { return fx > 0.0; }
};

/// The source's intrinsics with `calib` applied when set (image size is kept).
inline CameraIntrinsics effective_intrinsics(const CameraIntrinsics& source,
                                             const CalibrationOptions& calib) {
  if (!calib.is_set()) return source;
  CameraIntrinsics k = source;
  k.fx = calib.fx;
  k.fy = calib.fy > 0.0 ? calib.fy : calib.fx;
  k.cx = calib.cx;
  k.cy = calib.cy;
  k.dist = {calib.k1, calib.k2, calib.p1, calib.p2};
  k.focal_known = true;
  return k;
}

}  // namespace mer::hal
