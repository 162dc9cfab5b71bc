#include "hal/pixel_convert.h"

#include <cstdint>
#include <vector>

#include <gtest/gtest.h>
#include <opencv2/core.hpp>

namespace mer::hal {
namespace {

constexpr int kW = 6;
constexpr int kH = 4;
constexpr int kPad = 10;              // bytes of row padding beyond the minimum stride
constexpr std::uint8_t kJunk = 0xEE;  // padding / chroma filler that must never reach gray

// Known luma of pixel (x, y): distinct for every pixel.
std::uint8_t luma(int x, int y) {
  return static_cast<std::uint8_t>(10 * y + x + 1);
}

cv::Mat expected_gray() {
  cv::Mat m(kH, kW, CV_8UC1);
  for (int y = 0; y < kH; ++y) {
    for (int x = 0; x < kW; ++x) m.at<std::uint8_t>(y, x) = luma(x, y);
  }
  return m;
}

bool equal(const cv::Mat& a, const cv::Mat& b) {
  if (a.size() != b.size() || a.type() != b.type()) return false;
  for (int y = 0; y < a.rows; ++y) {
    for (int x = 0; x < a.cols; ++x) {
      if (a.at<std::uint8_t>(y, x) != b.at<std::uint8_t>(y, x)) return false;
    }
  }
  return true;
}

// GREY (or NV12's Y plane) with `stride` bytes per row, padding filled with junk.
std::vector<std::uint8_t> make_luma_plane(int stride) {
  std::vector<std::uint8_t> buf(static_cast<std::size_t>(stride * kH), kJunk);
  for (int y = 0; y < kH; ++y) {
    for (int x = 0; x < kW; ++x) buf[static_cast<std::size_t>(y * stride + x)] = luma(x, y);
  }
  return buf;
}

// YUYV: Y0 U Y1 V per pixel pair; chroma bytes junk.
std::vector<std::uint8_t> make_yuyv(int stride) {
  std::vector<std::uint8_t> buf(static_cast<std::size_t>(stride * kH), kJunk);
  for (int y = 0; y < kH; ++y) {
    for (int x = 0; x < kW; ++x) buf[static_cast<std::size_t>(y * stride + 2 * x)] = luma(x, y);
  }
  return buf;
}

TEST(PixelConvert, GreyUnpadded) {
  const auto buf = make_luma_plane(kW);
  cv::Mat dst(kH, kW, CV_8UC1, cv::Scalar(0));
  ASSERT_TRUE(convert_to_gray(PixelFormat::kGrey, buf, {kW, kH, kW}, dst));
  EXPECT_TRUE(equal(dst, expected_gray()));
}

TEST(PixelConvert, GreyWithRowPadding) {
  const int stride = kW + kPad;
  const auto buf = make_luma_plane(stride);
  cv::Mat dst(kH, kW, CV_8UC1, cv::Scalar(0));
  ASSERT_TRUE(convert_to_gray(PixelFormat::kGrey, buf, {kW, kH, stride}, dst));
  EXPECT_TRUE(equal(dst, expected_gray()));
}

TEST(PixelConvert, YuyvTakesEveryOtherByte) {
  const int stride = 2 * kW;
  const auto buf = make_yuyv(stride);
  cv::Mat dst(kH, kW, CV_8UC1, cv::Scalar(0));
  ASSERT_TRUE(convert_to_gray(PixelFormat::kYuyv, buf, {kW, kH, stride}, dst));
  EXPECT_TRUE(equal(dst, expected_gray()));
}

TEST(PixelConvert, YuyvWithRowPadding) {
  const int stride = 2 * kW + kPad;
  const auto buf = make_yuyv(stride);
  cv::Mat dst(kH, kW, CV_8UC1, cv::Scalar(0));
  ASSERT_TRUE(convert_to_gray(PixelFormat::kYuyv, buf, {kW, kH, stride}, dst));
  EXPECT_TRUE(equal(dst, expected_gray()));
}

TEST(PixelConvert, Nv12ReadsOnlyTheYPlane) {
  const int stride = kW + kPad;
  auto buf = make_luma_plane(stride);
  // Interleaved CbCr plane: height/2 rows of the same stride, junk values.
  buf.resize(buf.size() + static_cast<std::size_t>(stride * kH / 2), kJunk);
  cv::Mat dst(kH, kW, CV_8UC1, cv::Scalar(0));
  ASSERT_TRUE(convert_to_gray(PixelFormat::kNv12, buf, {kW, kH, stride}, dst));
  EXPECT_TRUE(equal(dst, expected_gray()));
}

TEST(PixelConvert, MinimumSizeExcludesLastRowPadding) {
  const int stride = kW + kPad;
  EXPECT_EQ(min_bytes_for_gray(PixelFormat::kGrey, {kW, kH, stride}),
            static_cast<std::size_t>((kH - 1) * stride + kW));
  EXPECT_EQ(min_bytes_for_gray(PixelFormat::kYuyv, {kW, kH, 2 * kW}),
            static_cast<std::size_t>(kH * 2 * kW));
  // The exact minimum converts: a buffer whose last row is unpadded is fine.
  auto buf = make_luma_plane(stride);
  buf.resize(min_bytes_for_gray(PixelFormat::kGrey, {kW, kH, stride}));
  cv::Mat dst(kH, kW, CV_8UC1, cv::Scalar(0));
  ASSERT_TRUE(convert_to_gray(PixelFormat::kGrey, buf, {kW, kH, stride}, dst));
  EXPECT_TRUE(equal(dst, expected_gray()));
}

TEST(PixelConvert, ShortBufferIsRejectedAndDstUntouched) {
  const int stride = 2 * kW;
  auto buf = make_yuyv(stride);
  buf.pop_back();  // one byte short of the last luma sample
  cv::Mat dst(kH, kW, CV_8UC1, cv::Scalar(7));
  EXPECT_FALSE(convert_to_gray(PixelFormat::kYuyv, buf, {kW, kH, stride}, dst));
  EXPECT_EQ(cv::countNonZero(dst != 7), 0);
}

TEST(PixelConvert, InvalidLayoutsAreRejected) {
  const auto buf = make_yuyv(2 * kW);
  cv::Mat dst(kH, kW, CV_8UC1);
  // Stride below the minimum for YUYV.
  EXPECT_EQ(min_bytes_for_gray(PixelFormat::kYuyv, {kW, kH, kW}), 0U);
  EXPECT_FALSE(convert_to_gray(PixelFormat::kYuyv, buf, {kW, kH, kW}, dst));
  EXPECT_FALSE(convert_to_gray(PixelFormat::kGrey, buf, {0, kH, kW}, dst));
  // Destination of the wrong size or type is never reallocated.
  cv::Mat small(kH - 1, kW, CV_8UC1);
  EXPECT_FALSE(convert_to_gray(PixelFormat::kGrey, buf, {kW, kH, kW}, small));
  EXPECT_EQ(small.rows, kH - 1);
  cv::Mat wrong_type(kH, kW, CV_16UC1);
  EXPECT_FALSE(convert_to_gray(PixelFormat::kGrey, buf, {kW, kH, kW}, wrong_type));
}

TEST(PixelConvert, WritesIntoTheGivenBuffer) {
  const auto buf = make_luma_plane(kW);
  cv::Mat dst(kH, kW, CV_8UC1);
  const std::uint8_t* before = dst.data;
  ASSERT_TRUE(convert_to_gray(PixelFormat::kNv12, buf, {kW, kH, kW}, dst));
  EXPECT_EQ(dst.data, before);
}

TEST(PixelConvert, FormatNamesRoundTrip) {
  for (PixelFormat f : {PixelFormat::kGrey, PixelFormat::kYuyv, PixelFormat::kNv12,
                        PixelFormat::kRgb888, PixelFormat::kBgr888, PixelFormat::kXrgb8888}) {
    const auto parsed = parse_pixel_format(pixel_format_name(f));
    ASSERT_TRUE(parsed.has_value());
    EXPECT_EQ(*parsed, f);
  }
  EXPECT_FALSE(parse_pixel_format("MJPG").has_value());
  EXPECT_FALSE(parse_pixel_format("grey").has_value());
}

// Packed RGB (libcamera): BT.601 luma, each format in its own memory order, with padding.
TEST(PixelConvert, RgbFormatsUseBt601LumaInTheirByteOrder) {
  struct Case {
    PixelFormat f;
    int bpp;
    std::vector<std::uint8_t> red;  // one pure-red pixel in memory order
  };
  for (const Case& c :
       {Case{PixelFormat::kRgb888, 3, {0, 0, 255}}, Case{PixelFormat::kBgr888, 3, {255, 0, 0}},
        Case{PixelFormat::kXrgb8888, 4, {0, 0, 255, 0}}}) {
    const int stride = kW * c.bpp + kPad;
    std::vector<std::uint8_t> buf(static_cast<std::size_t>(stride * kH), 0);
    for (int y = 0; y < kH; ++y) {
      for (std::size_t b = 0; b < c.red.size(); ++b) buf[y * stride + b] = c.red[b];
    }
    cv::Mat gray(kH, kW, CV_8UC1, cv::Scalar(1));
    ASSERT_TRUE(convert_to_gray(c.f, buf, {kW, kH, stride}, gray)) << pixel_format_name(c.f);
    EXPECT_EQ(gray.at<std::uint8_t>(0, 0), (77 * 255) >> 8) << pixel_format_name(c.f);
    EXPECT_EQ(gray.at<std::uint8_t>(1, 1), 0) << pixel_format_name(c.f);
    // One byte short of the last row: rejected.
    buf.resize(static_cast<std::size_t>(stride * (kH - 1) + kW * c.bpp - 1));
    EXPECT_FALSE(convert_to_gray(c.f, buf, {kW, kH, stride}, gray)) << pixel_format_name(c.f);
  }
}

}  // namespace
}  // namespace mer::hal
