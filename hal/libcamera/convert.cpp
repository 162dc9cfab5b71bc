#include <cstring>

#include "hal/libcamera/libcamera_camera.h"

namespace mer::hal {
namespace {
constexpr int kWr = 77;  // BT.601 luma weights in 1/256
constexpr int kWg = 150;
constexpr int kWb = 29;
constexpr int kShift = 8;
}  // namespace

void convert_to_gray(PackedFormat format, const std::uint8_t* src, std::size_t stride,
                     cv::Mat& dst) {
  const int w = dst.cols;
  for (int y = 0; y < dst.rows; ++y) {
    const std::uint8_t* s = src + static_cast<std::size_t>(y) * stride;
    std::uint8_t* d = dst.ptr<std::uint8_t>(y);
    switch (format) {
      case PackedFormat::kGrey8:
      case PackedFormat::kNv12:  // the full-resolution luma plane comes first
        std::memcpy(d, s, static_cast<std::size_t>(w));
        break;
      case PackedFormat::kYuyv:
        for (int x = 0; x < w; ++x) d[x] = s[2 * x];
        break;
      // libcamera names packed RGB formats by DRM fourcc, little-endian words: RGB888 is
      // stored B, G, R in memory; BGR888 is stored R, G, B; XRGB8888 is B, G, R, X.
      case PackedFormat::kRgb888:
        for (int x = 0; x < w; ++x) {
          const std::uint8_t* p = s + 3 * x;
          d[x] = static_cast<std::uint8_t>((kWb * p[0] + kWg * p[1] + kWr * p[2]) >> kShift);
        }
        break;
      case PackedFormat::kBgr888:
        for (int x = 0; x < w; ++x) {
          const std::uint8_t* p = s + 3 * x;
          d[x] = static_cast<std::uint8_t>((kWr * p[0] + kWg * p[1] + kWb * p[2]) >> kShift);
        }
        break;
      case PackedFormat::kXrgb8888:
        for (int x = 0; x < w; ++x) {
          const std::uint8_t* p = s + 4 * x;
          d[x] = static_cast<std::uint8_t>((kWb * p[0] + kWg * p[1] + kWr * p[2]) >> kShift);
        }
        break;
    }
  }
}

}  // namespace mer::hal
