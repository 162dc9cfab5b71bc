#pragma once
/// @file camera_factory.h
/// Opens a CameraSource from an input URI (the `--input` contract of mer_slam):
///   synthetic:NAME  tum:DIR  euroc:DIR  kitti:DIR  rec:FILE  v4l2:/dev/videoN  libcamera:ID

#include <memory>
#include <string>
#include <string_view>

#include "core/options.h"
#include "core/status.h"
#include "hal/camera.h"
#include "hal/synthetic/synthetic_camera.h"

namespace mer::hal {

/// A parsed `--input` URI.
struct InputUri {
  std::string scheme;  ///< "synthetic", "tum", ...
  std::string path;    ///< everything after the first ':'
};

/// Known URI schemes, in the order of the CLI documentation.
std::span<const std::string_view> input_schemes();

/// Splits "scheme:path"; an unknown scheme or empty path is an error naming the URI.
Result<InputUri> parse_input_uri(std::string_view uri);

/// Calibration override (config section `camera.calibration`, or `--intrinsics`).
/// Zero focal length means "use the source's own calibration".
struct CalibrationOptions {
  double fx = 0.0;  ///< focal length x, px (0: from the source)
  double fy = 0.0;  ///< focal length y, px (0: from the source)
  double cx = 0.0;  ///< principal point x, px
  double cy = 0.0;  ///< principal point y, px
  double k1 = 0.0;  ///< radial distortion k1
  double k2 = 0.0;  ///< radial distortion k2
  double p1 = 0.0;  ///< tangential distortion p1
  double p2 = 0.0;  ///< tangential distortion p2

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
CameraIntrinsics effective_intrinsics(const CameraIntrinsics& source,
                                      const CalibrationOptions& calib);

/// Options of the camera layer (config section `camera`).
struct CameraOptions {
  int pool_size = 8;               ///< frame buffers in the capture pool (bounds frames in flight)
  CalibrationOptions calibration;  ///< intrinsics override
  SyntheticOptions synthetic;      ///< the synthetic camera (`synthetic:` inputs)

  template <class V>
  void visit(V& v) {
    v.field("pool_size", pool_size, "frame buffers in the capture pool (frames in flight)",
            options::Range<int>{2, 1024});
    v.section("calibration", calibration, "intrinsics override (fx = 0: use the source's)");
    v.section("synthetic", synthetic, "synthetic camera (synthetic:NAME inputs)");
  }
};

/// Creates (but does not open) the source for `uri`. `paced` asks finite sources to
/// deliver at their recorded/nominal rate (threaded mode) instead of as fast as possible.
Result<std::unique_ptr<CameraSource>> make_camera(const InputUri& uri, const CameraOptions& opts,
                                                  bool paced);

}  // namespace mer::hal
