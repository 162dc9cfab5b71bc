// libcamera backend: device errors on a host without cameras (the real camera path is
// tested against vimc in tests/hw).
#include <gtest/gtest.h>

#include "hal/libcamera/libcamera_camera.h"

namespace mer::hal {
namespace {

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
