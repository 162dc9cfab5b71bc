#pragma once
/// @file camera_factory.h
/// Opens a CameraSource from an input URI (the `--input` contract of mer_slam):
///   synthetic:NAME  tum:DIR  euroc:DIR  kitti:DIR  rec:FILE  v4l2:/dev/videoN  libcamera:ID

#include <memory>
#include <string>
#include <string_view>

#include "core/options.h"
#include "core/status.h"
#include "hal/calibration.h"
#include "hal/camera.h"
#include "hal/libcamera/libcamera_camera.h"
#include "hal/replay/replay_camera.h"
#include "hal/synthetic/synthetic_camera.h"
#include "hal/v4l2/v4l2_options.h"

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

/// Options of the camera layer (config section `camera`).
struct CameraOptions {
  int pool_size = 8;
  CalibrationOptions calibration;
  SyntheticOptions synthetic;
  ReplayOptions replay;
  V4l2Options v4l2;
  LibcameraOptions libcamera;

  template <class V>
  void visit(V& v) {
    v.field("pool_size", pool_size, "frame buffers in the capture pool (frames in flight)",
            options::Range<int>{2, 1024});
    v.section("calibration", calibration, "intrinsics override (fx = 0: use the source's)");
    v.section("synthetic", synthetic, "synthetic camera (synthetic:NAME inputs)");
    v.section("replay", replay, "dataset and recording replay (tum:, euroc:, kitti:, rec:)");
    v.section("v4l2", v4l2, "V4L2 devices (v4l2:/dev/videoN inputs)");
    v.section("libcamera", libcamera, "libcamera devices (libcamera:ID inputs)");
  }
};

/// Creates (but does not open) the source for `uri`. `paced` asks finite sources to
/// deliver at their recorded/nominal rate (threaded mode) instead of as fast as possible;
/// `rgbd` asks dataset readers for depth images too.
Result<std::unique_ptr<CameraSource>> make_camera(const InputUri& uri, const CameraOptions& opts,
                                                  bool paced, bool rgbd = false);

}  // namespace mer::hal
