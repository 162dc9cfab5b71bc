#pragma once
/// @file v4l2_controls.h
/// Enumerating and setting V4L2 controls by name (VIDIOC_QUERY_EXT_CTRL,
/// VIDIOC_S_EXT_CTRLS) without exposing the V4L2 header: camera tuning (exposure, gain)
/// and, in the hardware test, vivid's fault-injection controls. Not for the capture thread
/// (opens the device node per call and allocates).

#include <cstdint>
#include <string>
#include <string_view>
#include <vector>

#include "core/status.h"

namespace mer::hal {

/// One control of a V4L2 device.
struct V4l2Control {
  std::uint32_t id = 0;            ///< control id (V4L2_CID_* or a driver-private id)
  std::string name;                ///< driver's name, e.g. "Inject VIDIOC_STREAMON Error"
  std::int64_t minimum = 0;        ///< smallest value
  std::int64_t maximum = 0;        ///< largest value
  std::int64_t default_value = 0;  ///< value after reset
  bool is_button = false;          ///< a button: setting any value triggers the action
  bool is_integer64 = false;       ///< set through value64
  bool read_only = false;          ///< cannot be set
};

/// Every control of the device node `device` (control-class headings skipped).
Result<std::vector<V4l2Control>> list_v4l2_controls(const std::string& device);

/// The first control whose name contains `needle`, case-insensitively; an error listing
/// the names when none does.
Result<V4l2Control> find_v4l2_control(const std::vector<V4l2Control>& controls,
                                      std::string_view needle);

/// Sets control `control` of `device` to `value` (any value presses a button).
Status set_v4l2_control(const std::string& device, const V4l2Control& control, std::int64_t value);

}  // namespace mer::hal
