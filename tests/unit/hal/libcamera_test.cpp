// libcamera backend: pixel conversion (pure) and device errors on a host without cameras.
#include <vector>

#include <gtest/gtest.h>

#include "hal/libcamera/libcamera_camera.h"

namespace mer::hal {
namespace {

constexpr int kW = 6;
constexpr int kH = 3;
constexpr std::size_t kPad = 5;  // extra bytes per row: conversion must honour the stride

TEST(LibcameraConvert, GreyAndLumaFormatsCopyLuma) {
  for (PackedFormat f : {PackedFormat::kGrey8, PackedFormat::kNv12, PackedFormat::kYuyv}) {
    const std::size_t bpp = f == PackedFormat::kYuyv ? 2 : 1;
    const std::size_t stride = kW * bpp + kPad;
    std::vector<std::uint8_t> buf(stride * kH, 0xEE);
    for (int y = 0; y < kH; ++y) {
      for (int x = 0; x < kW; ++x) {
        buf[y * stride + x * bpp] = static_cast<std::uint8_t>(10 * y + x);
        if (bpp == 2) buf[y * stride + x * bpp + 1] = 0x80;  // chroma
      }
    }
    cv::Mat gray(kH, kW, CV_8UC1);
    convert_to_gray(f, buf.data(), stride, gray);
    for (int y = 0; y < kH; ++y) {
      for (int x = 0; x < kW; ++x) EXPECT_EQ(gray.at<std::uint8_t>(y, x), 10 * y + x);
    }
  }
}

TEST(LibcameraConvert, RgbFormatsUseBt601LumaInTheirByteOrder) {
  // One pure-red pixel per format, in that format's memory order.
  struct Case {
    PackedFormat f;
    std::size_t bpp;
    std::vector<std::uint8_t> red;
  };
  for (const Case& c :
       {Case{PackedFormat::kRgb888, 3, {0, 0, 255}}, Case{PackedFormat::kBgr888, 3, {255, 0, 0}},
        Case{PackedFormat::kXrgb8888, 4, {0, 0, 255, 0}}}) {
    const std::size_t stride = kW * c.bpp + kPad;
    std::vector<std::uint8_t> buf(stride * kH, 0);
    for (int y = 0; y < kH; ++y) {
      for (std::size_t b = 0; b < c.red.size(); ++b) buf[y * stride + b] = c.red[b];
    }
    cv::Mat gray(kH, kW, CV_8UC1);
    convert_to_gray(c.f, buf.data(), stride, gray);
    EXPECT_EQ(gray.at<std::uint8_t>(0, 0), (77 * 255) >> 8);  // red weight 0.299
    EXPECT_EQ(gray.at<std::uint8_t>(1, 1), 0);
  }
}

TEST(LibcameraCamera, UnknownCameraIsAClearInputError) {
  auto cam = make_libcamera_camera("no-such-camera", LibcameraOptions{});
  if (!libcamera_backend_built()) {
    ASSERT_FALSE(cam.is_ok());
    EXPECT_EQ(cam.status().code(), StatusCode::kUnavailable);
    EXPECT_NE(cam.status().message().find("libcamera-dev"), std::string::npos);
    return;
  }
  ASSERT_TRUE(cam.is_ok());
  const Status s = cam.value()->open(4);
  ASSERT_EQ(s.code(), StatusCode::kInputError);
  EXPECT_NE(s.message().find("no-such-camera"), std::string::npos) << s.message();
  EXPECT_NE(s.message().find("available:"), std::string::npos) << s.message();
}

}  // namespace
}  // namespace mer::hal
