#pragma once
/// @file v4l2_options.h
/// Options of the V4L2 camera (config section `camera.v4l2`). Kept apart from
/// v4l2_camera.h so the camera factory's options can include it cheaply.

#include <array>
#include <string>
#include <string_view>

#include "core/options.h"

namespace mer::hal {

/// Accepted values of V4l2Options::pixel_format ("auto": GREY, else NV12, else YUYV —
/// cheapest conversion to gray first).
inline constexpr std::array<std::string_view, 4> kV4l2PixelFormatWords{"auto", "GREY", "YUYV",
                                                                       "NV12"};
/// Accepted values of V4l2Options::on_error.
inline constexpr std::array<std::string_view, 2> kV4l2ErrorPolicyWords{"stop", "retry"};
/// Most mmap buffers the backend handles (the driver queue; frames live in the pool).
inline constexpr int kV4l2MaxBuffers = 32;
/// Fewest mmap buffers that keep a driver streaming while one is being converted.
inline constexpr int kV4l2MinBuffers = 2;

/// Options of a `v4l2:/dev/videoN` camera.
struct V4l2Options {
  int width = 640;
  int height = 480;
  double fps = 30.0;
  std::string pixel_format = "auto";
  int buffers = 4;
  std::string on_error = "stop";
  int max_retries = 3;
  int retry_delay_ms = 500;
  int dequeue_timeout_ms = 2000;
  double hfov_deg = 60.0;

  template <class V>
  void visit(V& v) {
    v.field("width", width, "image width, px (must be a size the device offers)",
            options::Range<int>{16, 8192});
    v.field("height", height, "image height, px", options::Range<int>{16, 8192});
    v.field("fps", fps, "frame rate set on the device (VIDIOC_S_PARM), Hz",
            options::Range<double>{1.0, 1000.0});
    v.field("pixel_format", pixel_format,
            "capture format (auto: GREY, else NV12, else YUYV; all converted to gray)",
            options::OneOf{kV4l2PixelFormatWords});
    v.field("buffers", buffers, "mmap buffers queued in the driver",
            options::Range<int>{kV4l2MinBuffers, kV4l2MaxBuffers});
    v.field("on_error", on_error,
            "mid-stream device error (disconnect, I/O error, stall): stop, or retry "
            "(close, reopen, restart)",
            options::OneOf{kV4l2ErrorPolicyWords});
    v.field("max_retries", max_retries, "reopen attempts per error before giving up (retry)",
            options::Range<int>{0, 1000});
    v.field("retry_delay_ms", retry_delay_ms, "wait before each reopen attempt, ms",
            options::Range<int>{0, 60000});
    v.field("dequeue_timeout_ms", dequeue_timeout_ms,
            "no frame for this long while streaming counts as a device error, ms",
            options::Range<int>{10, 600000});
    v.field("hfov_deg", hfov_deg,
            "horizontal field of view guess for the initial focal length (focal unknown), deg",
            options::Range<double>{10.0, 170.0});
  }
};

}  // namespace mer::hal
