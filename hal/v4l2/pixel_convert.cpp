#include "hal/v4l2/pixel_convert.h"

#include <array>
#include <cstring>

namespace mer::hal {
namespace {

constexpr int kYuyvBytesPerPixel = 2;  // Y and one of U/V per pixel
constexpr int kLumaBytesPerPixel = 1;  // GREY, and NV12's Y plane

struct FormatName {
  PixelFormat format;
  std::string_view name;
};
constexpr std::array<FormatName, 3> kFormatNames{{
    {PixelFormat::kGrey, "GREY"},
    {PixelFormat::kYuyv, "YUYV"},
    {PixelFormat::kNv12, "NV12"},
}};

int bytes_per_pixel(PixelFormat format) noexcept {
  return format == PixelFormat::kYuyv ? kYuyvBytesPerPixel : kLumaBytesPerPixel;
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
    if (format == PixelFormat::kYuyv) {
      // Every other byte is luma; a plain loop the compiler vectorizes.
      for (std::size_t x = 0; x < width; ++x) out[x] = row[x * kYuyvBytesPerPixel];
    } else {
      std::memcpy(out, row, width);  // GREY, or NV12's Y plane
    }
  }
  return true;
}

}  // namespace mer::hal
