#include "hal/camera_factory.h"

#include <gtest/gtest.h>

namespace mer::hal {
namespace {

TEST(InputUri, ParsesSchemeAndPath) {
  auto u = parse_input_uri("kitti:/data/seq 00");
  ASSERT_TRUE(u.is_ok());
  EXPECT_EQ(u.value().scheme, "kitti");
  EXPECT_EQ(u.value().path, "/data/seq 00");
  auto v = parse_input_uri("v4l2:/dev/video0");
  ASSERT_TRUE(v.is_ok());
  EXPECT_EQ(v.value().path, "/dev/video0");
}

TEST(InputUri, RejectsUnknownSchemeMissingColonAndEmptyPath) {
  for (const char* bad : {"foo:bar", "synthetic", "synthetic:", ""}) {
    auto u = parse_input_uri(bad);
    ASSERT_FALSE(u.is_ok()) << bad;
    EXPECT_EQ(u.status().code(), StatusCode::kInvalidArgument);
    EXPECT_NE(u.status().message().find("--input"), std::string::npos);
  }
}

TEST(CameraFactory, EverySchemeReachesItsBackend) {
  CameraOptions opts;
  ASSERT_TRUE(make_camera({"synthetic", "room_orbit"}, opts, false).is_ok());
  // Dataset folders that do not exist: the backend's error names the path.
  for (const char* scheme : {"tum", "euroc", "kitti", "rec", "v4l2"}) {
    auto cam = make_camera({scheme, "/nonexistent/mer_input"}, opts, false);
    Status s = cam.is_ok() ? cam.value()->open(8) : cam.status();
    ASSERT_FALSE(s.is_ok()) << scheme;
    EXPECT_NE(s.message().find("/nonexistent/mer_input"), std::string::npos)
        << scheme << ": " << s.message();
  }
}

TEST(CameraFactory, CalibrationOverride) {
  CameraIntrinsics src{640, 480, 500, 500, 320, 240, {}, true};
  CalibrationOptions none;
  EXPECT_DOUBLE_EQ(effective_intrinsics(src, none).fx, 500.0);
  CalibrationOptions c;
  c.fx = 400;
  c.fy = 410;
  c.cx = 300;
  c.cy = 200;
  c.k1 = 0.1;
  const CameraIntrinsics k = effective_intrinsics(src, c);
  EXPECT_DOUBLE_EQ(k.fx, 400.0);
  EXPECT_DOUBLE_EQ(k.fy, 410.0);
  EXPECT_DOUBLE_EQ(k.cy, 200.0);
  EXPECT_DOUBLE_EQ(k.dist[0], 0.1);
  EXPECT_EQ(k.width, 640);
}

}  // namespace
}  // namespace mer::hal
