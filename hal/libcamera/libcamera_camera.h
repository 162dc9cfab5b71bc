#pragma once
/// @file libcamera_camera.h
/// `libcamera:ID` — cameras through libcamera (Raspberry Pi CSI cameras, UVC, vimc, ...).
/// Optional backend: built when libcamera-dev is found (Debian 12 ships 0.0.3). libcamera
/// headers stay inside libcamera_camera.cpp.
///
/// Completed requests are handed from libcamera's callback thread straight into a lock-free
/// ring of buffer indices; acquire() converts the mapped buffer to gray in a pool frame and
/// re-queues the request. ID is a libcamera camera id, an index ("0"), or "auto" (first).

#include <memory>
#include <string>

#include "core/options.h"
#include "core/status.h"
#include "hal/camera.h"

namespace mer::hal {

inline constexpr std::array<std::string_view, 7> kLibcameraFormats{
    "auto", "R8", "YUYV", "NV12", "BGR888", "RGB888", "XRGB8888"};

/// Options of the libcamera backend (config section `camera.libcamera`).
struct LibcameraOptions {
  int width = 640;
  int height = 480;
  double fps = 30.0;
  std::string pixel_format = "auto";
  int buffers = 4;
  int dequeue_timeout_ms = 1000;
  double hfov_deg = 60.0;

  template <class V>
  void visit(V& v) {
    v.field("width", width, "requested width, px", options::Range<int>{16, 8192});
    v.field("height", height, "requested height, px", options::Range<int>{16, 8192});
    v.field("fps", fps, "requested frame rate, Hz", options::Range<double>{1.0, 1000.0});
    v.field("pixel_format", pixel_format, "stream pixel format", options::OneOf{kLibcameraFormats});
    v.field("buffers", buffers, "frame buffers allocated by libcamera", options::Range<int>{2, 32});
    v.field("hfov_deg", hfov_deg,
            "assumed horizontal field of view: initial focal guess (focal_known = false)",
            options::Range<double>{10.0, 170.0});
    v.field("dequeue_timeout_ms", dequeue_timeout_ms, "wait for a completed request, ms",
            options::Range<int>{1, 60000});
  }
};

/// True when this build includes the libcamera backend.
bool libcamera_backend_built();

/// Creates (not opens) a libcamera source for camera `id`; kUnavailable when the backend
/// was not built.
Result<std::unique_ptr<CameraSource>> make_libcamera_camera(const std::string& id,
                                                            const LibcameraOptions& opts);

}  // namespace mer::hal
