// Host-side tests of the V4L2 camera that need no video device: options validation,
// the factory, and the errors for a missing node, a non-V4L2 character device and a
// regular file. The real driver is exercised by tests/hw (vivid in a VM).
#include "hal/v4l2/v4l2_camera.h"

#include <cstdio>
#include <fstream>
#include <string>

#include <gtest/gtest.h>

#include "hal/v4l2/v4l2_controls.h"

namespace mer::hal {
namespace {

constexpr std::size_t kPool = 4;
constexpr std::int64_t kShortTimeoutNs = 1'000'000;

bool contains(const std::string& s, const std::string& part) {
  return s.find(part) != std::string::npos;
}

TEST(V4l2Options, DefaultsAreValid) {
  V4l2Options o;
  EXPECT_TRUE(options::validate(o).is_ok());
}

TEST(V4l2Options, RejectsBadValuesNamingTheKey) {
  {
    V4l2Options o;
    o.pixel_format = "MJPG";
    const Status s = options::validate(o);
    ASSERT_FALSE(s.is_ok());
    EXPECT_TRUE(contains(s.message(), "pixel_format")) << s.message();
    EXPECT_TRUE(contains(s.message(), "GREY")) << s.message();
  }
  {
    V4l2Options o;
    o.on_error = "ignore";
    const Status s = options::validate(o);
    ASSERT_FALSE(s.is_ok());
    EXPECT_TRUE(contains(s.message(), "on_error")) << s.message();
  }
  {
    V4l2Options o;
    o.buffers = kV4l2MaxBuffers + 1;
    const Status s = options::validate(o);
    ASSERT_FALSE(s.is_ok());
    EXPECT_TRUE(contains(s.message(), "buffers")) << s.message();
  }
  {
    V4l2Options o;
    o.buffers = kV4l2MinBuffers - 1;
    EXPECT_FALSE(options::validate(o).is_ok());
  }
  {
    V4l2Options o;
    o.fps = 0.0;
    const Status s = options::validate(o);
    ASSERT_FALSE(s.is_ok());
    EXPECT_TRUE(contains(s.message(), "fps")) << s.message();
  }
  {
    V4l2Options o;
    o.dequeue_timeout_ms = 0;
    EXPECT_FALSE(options::validate(o).is_ok());
  }
  for (const char* fmt : {"auto", "GREY", "YUYV", "NV12"}) {
    V4l2Options o;
    o.pixel_format = fmt;
    EXPECT_TRUE(options::validate(o).is_ok()) << fmt;
  }
}

TEST(V4l2Factory, CreatesWithoutOpening) {
  auto cam = make_v4l2_camera("/dev/video99", V4l2Options{});
  ASSERT_TRUE(cam.is_ok()) << cam.status().message();
  EXPECT_TRUE(contains(cam.value()->describe(), "v4l2:/dev/video99"));
  EXPECT_TRUE(cam.value()->capabilities().live);
}

TEST(V4l2Factory, RejectsInvalidOptionsAndEmptyPath) {
  V4l2Options o;
  o.on_error = "explode";
  auto cam = make_v4l2_camera("/dev/video0", o);
  ASSERT_FALSE(cam.is_ok());
  EXPECT_EQ(cam.status().code(), StatusCode::kInvalidArgument);
  EXPECT_TRUE(contains(cam.status().message(), "on_error"));
  auto empty = make_v4l2_camera("", V4l2Options{});
  ASSERT_FALSE(empty.is_ok());
  EXPECT_EQ(empty.status().code(), StatusCode::kInvalidArgument);
}

TEST(V4l2Camera, MissingDeviceNamesThePath) {
  V4l2Camera cam("/dev/video99", V4l2Options{});
  const Status s = cam.open(kPool);
  ASSERT_FALSE(s.is_ok());
  EXPECT_EQ(s.code(), StatusCode::kInputError);
  EXPECT_TRUE(contains(s.message(), "/dev/video99")) << s.message();
  EXPECT_TRUE(contains(s.message(), "ENOENT")) << s.message();
  // Never opened: start fails cleanly, acquire reports end of stream, stop is a no-op.
  EXPECT_FALSE(cam.start().is_ok());
  FrameHandle h;
  EXPECT_EQ(cam.acquire(h, kShortTimeoutNs), AcquireStatus::kEndOfStream);
  cam.stop();
}

TEST(V4l2Camera, CharacterDeviceThatIsNotV4l2) {
  V4l2Camera cam("/dev/null", V4l2Options{});
  const Status s = cam.open(kPool);
  ASSERT_FALSE(s.is_ok());
  EXPECT_EQ(s.code(), StatusCode::kInputError);
  EXPECT_TRUE(contains(s.message(), "/dev/null")) << s.message();
  EXPECT_TRUE(contains(s.message(), "not a V4L2 device")) << s.message();
  EXPECT_TRUE(contains(s.message(), "VIDIOC_QUERYCAP")) << s.message();
}

TEST(V4l2Camera, RegularFileIsNotADevice) {
  const std::string path = ::testing::TempDir() + "mer_v4l2_not_a_device";
  { std::ofstream(path) << "not a camera"; }
  V4l2Camera cam(path, V4l2Options{});
  const Status s = cam.open(kPool);
  std::remove(path.c_str());
  ASSERT_FALSE(s.is_ok());
  EXPECT_TRUE(contains(s.message(), path)) << s.message();
  EXPECT_TRUE(contains(s.message(), "not a character device")) << s.message();
}

TEST(V4l2Camera, InvalidOptionsAndPoolSizeAtOpen) {
  V4l2Options o;
  o.width = 1;
  V4l2Camera bad("/dev/null", o);
  const Status s = bad.open(kPool);
  ASSERT_FALSE(s.is_ok());
  EXPECT_EQ(s.code(), StatusCode::kInvalidArgument);
  EXPECT_TRUE(contains(s.message(), "width")) << s.message();
  V4l2Camera zero("/dev/null", V4l2Options{});
  EXPECT_EQ(zero.open(0).code(), StatusCode::kInvalidArgument);
}

TEST(V4l2Controls, MissingDeviceAndUnknownName) {
  auto list = list_v4l2_controls("/dev/video99");
  ASSERT_FALSE(list.is_ok());
  EXPECT_TRUE(contains(list.status().message(), "/dev/video99"));
  std::vector<V4l2Control> controls(2);
  controls[0].name = "Brightness";
  controls[1].name = "Inject VIDIOC_STREAMON Error";
  auto found = find_v4l2_control(controls, "streamon error");
  ASSERT_TRUE(found.is_ok());
  EXPECT_EQ(found.value().name, "Inject VIDIOC_STREAMON Error");
  auto missing = find_v4l2_control(controls, "disconnect");
  ASSERT_FALSE(missing.is_ok());
  EXPECT_TRUE(contains(missing.status().message(), "Brightness"));
}

}  // namespace
}  // namespace mer::hal
