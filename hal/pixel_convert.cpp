#include "hal/pixel_convert.h"

#include <array>
#include <cstring>

namespace mer::hal {
namespace {

constexpr int kYuyvBytesPerPixel = 2;  // Y and one of U/V per pixel
constexpr int kLumaBytesPerPixel = 1;  // GREY, and NV12's Y plane
constexpr int kRgbBytesPerPixel = 3;   // RGB888 / BGR888
constexpr int kXrgbBytesPerPixel = 4;  // XRGB8888
// BT.601 luma weights in 1/256.
constexpr int kWeightR = 77;
constexpr int kWeightG = 150;
constexpr int kWeightB = 29;
constexpr int kWeightShift = 8;

struct FormatName {
  PixelFormat format;
  std::string_view name;
};
constexpr std::array<FormatName, 6> kFormatNames{{
    {PixelFormat::kGrey, "GREY"},
    {PixelFormat::kYuyv, "YUYV"},
    {PixelFormat::kNv12, "NV12"},
    {PixelFormat::kRgb888, "RGB888"},
    {PixelFormat::kBgr888, "BGR888"},
    {PixelFormat::kXrgb8888, "XRGB8888"},
}};

int bytes_per_pixel(PixelFormat format) noexcept {
  switch (format) {
    case PixelFormat::kYuyv:
      return kYuyvBytesPerPixel;
    case PixelFormat::kRgb888:
    case PixelFormat::kBgr888:
      return kRgbBytesPerPixel;
    case PixelFormat::kXrgb8888:
      return kXrgbBytesPerPixel;
    case PixelFormat::kGrey:
    case PixelFormat::kNv12:
      break;
  }
  return kLumaBytesPerPixel;
}

// Luma of one pixel whose red, green and blue bytes sit at p[r], p[g], p[b].
inline std::uint8_t luma(const std::uint8_t* p, int r, int g, int b) noexcept {
  return static_cast<std::uint8_t>((kWeightR * p[r] + kWeightG * p[g] + kWeightB * p[b]) >>
                                   kWeightShift);
}

}  // namespace

std::string_view pixel_format_name(PixelFormat format) noexcept {
  for (const auto& f : kFormatNames) {
    if (f.format == format) return f.name;
  }
  return "?";
}

std::optional<PixelFormat> parse_pixel_format(std::string_view name) noexcept {
  for (const auto& f : kFormatNames) {
    if (f.name == name) return f.format;
  }
  return std::nullopt;
}

int min_bytes_per_line(PixelFormat format, int width) noexcept {
  return width * bytes_per_pixel(format);
}

std::size_t min_bytes_for_gray(PixelFormat format, const ImageLayout& layout) noexcept {
  const int row_bytes = min_bytes_per_line(format, layout.width);
  if (layout.width <= 0 || layout.height <= 0 || layout.bytes_per_line < row_bytes) return 0;
  return static_cast<std::size_t>(layout.height - 1) *
             static_cast<std::size_t>(layout.bytes_per_line) +
         static_cast<std::size_t>(row_bytes);
}

bool convert_to_gray(PixelFormat format, std::span<const std::uint8_t> src,
                     const ImageLayout& layout, cv::Mat& dst) noexcept {
  const std::size_t need = min_bytes_for_gray(format, layout);
  if (need == 0 || src.size() < need) return false;
  if (dst.type() != CV_8UC1 || dst.cols != layout.width || dst.rows != layout.height) return false;
  const auto width = static_cast<std::size_t>(layout.width);
  const auto stride = static_cast<std::size_t>(layout.bytes_per_line);
  const std::uint8_t* row = src.data();
  for (int r = 0; r < layout.height; ++r, row += stride) {
    std::uint8_t* out = dst.ptr<std::uint8_t>(r);
    switch (format) {
      case PixelFormat::kYuyv:
        // Every other byte is luma; a plain loop the compiler vectorizes.
        for (std::size_t x = 0; x < width; ++x) out[x] = row[x * kYuyvBytesPerPixel];
        break;
      case PixelFormat::kGrey:
      case PixelFormat::kNv12:
        std::memcpy(out, row, width);  // GREY, or NV12's Y plane
        break;
      case PixelFormat::kRgb888:  // B G R
        for (std::size_t x = 0; x < width; ++x) out[x] = luma(row + x * kRgbBytesPerPixel, 2, 1, 0);
        break;
      case PixelFormat::kBgr888:  // R G B
        for (std::size_t x = 0; x < width; ++x) out[x] = luma(row + x * kRgbBytesPerPixel, 0, 1, 2);
        break;
      case PixelFormat::kXrgb8888:  // B G R X
        for (std::size_t x = 0; x < width; ++x)
          out[x] = luma(row + x * kXrgbBytesPerPixel, 2, 1, 0);
        break;
    }
  }
  return true;
}

}  // namespace mer::hal
