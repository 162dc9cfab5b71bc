#pragma once
/// @file pixel_convert.h
/// Conversion of camera pixel formats (V4L2 and libcamera backends) to the 8-bit gray
/// image of a Frame. Pure functions over byte spans (no device header, no allocation), so
/// they are unit-tested on synthetic buffers.
///
/// For YUV formats gray is the luma channel Y, copied as is:
///   GREY  row r = bytes [r * bpl, r * bpl + w)
///   YUYV  row r, pixel x = byte r * bpl + 2x        (Y0 U0 Y1 V0 Y2 U2 ...)
///   NV12  row r = bytes [r * bpl, r * bpl + w) of the Y plane (the CbCr plane follows
///         and is not read)
/// For packed RGB formats gray is the ITU-R BT.601 luma (77 R + 150 G + 29 B) / 256.
/// They are named by DRM fourcc as libcamera does (little-endian words): RGB888 is stored
/// B, G, R in memory, BGR888 is R, G, B, XRGB8888 is B, G, R, X.
/// bpl (bytes per line) may exceed the minimum (row padding).

#include <cstddef>
#include <cstdint>
#include <optional>
#include <span>
#include <string_view>

#include <opencv2/core/mat.hpp>

namespace mer::hal {

/// Capture pixel formats the camera backends convert to gray.
enum class PixelFormat {
  kGrey,      ///< 8-bit luma only (V4L2 GREY, libcamera R8)
  kYuyv,      ///< packed 4:2:2, Y0 U Y1 V (V4L2_PIX_FMT_YUYV)
  kNv12,      ///< planar 4:2:0, Y plane then interleaved CbCr plane (V4L2_PIX_FMT_NV12)
  kRgb888,    ///< packed 24-bit, memory order B G R (DRM RGB888)
  kBgr888,    ///< packed 24-bit, memory order R G B (DRM BGR888)
  kXrgb8888,  ///< packed 32-bit, memory order B G R X (DRM XRGB8888)
};

/// The format's name: "GREY", "YUYV", "NV12", "RGB888", "BGR888" or "XRGB8888".
std::string_view pixel_format_name(PixelFormat format) noexcept;

/// Parses a FourCC name (exact, as in the options); nullopt when unknown.
std::optional<PixelFormat> parse_pixel_format(std::string_view name) noexcept;

/// Geometry of one image in a driver buffer (what VIDIOC_S_FMT returned).
struct ImageLayout {
  int width = 0;           ///< pixels per row
  int height = 0;          ///< rows
  int bytes_per_line = 0;  ///< stride of the packed / luma plane, bytes (>= the minimum)
};

/// Smallest stride a row of `width` pixels can have in `format`, bytes.
int min_bytes_per_line(PixelFormat format, int width) noexcept;

/// Bytes a buffer must hold for convert_to_gray() to read every luma byte of `layout`:
/// (height - 1) full strides plus one unpadded row. 0 when the layout is invalid
/// (non-positive size, stride below min_bytes_per_line()).
std::size_t min_bytes_for_gray(PixelFormat format, const ImageLayout& layout) noexcept;

/// Writes the luma of the image in `src` into `dst`, which must already be a CV_8UC1
/// image of layout.width x layout.height (it is a pool buffer: never reallocated here).
/// Returns false and leaves `dst` untouched when `src` is shorter than
/// min_bytes_for_gray(), the layout is invalid, or `dst` does not match. No allocation.
[[nodiscard]] bool convert_to_gray(PixelFormat format, std::span<const std::uint8_t> src,
                                   const ImageLayout& layout, cv::Mat& dst) noexcept;

}  // namespace mer::hal
