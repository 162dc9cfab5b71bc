// Synthetic camera: determinism, geometry of the rendered depth, pool and stream behaviour.
#include "hal/synthetic/synthetic_camera.h"

#include <cmath>

#include <gtest/gtest.h>
#include <opencv2/core.hpp>

#include "platform/alloc_counter.h"

namespace mer::hal {
namespace {

SyntheticOptions small_options() {
  SyntheticOptions o;
  o.width = 160;
  o.height = 120;
  o.num_frames = 20;
  return o;
}

TEST(SyntheticCamera, UnknownScenarioIsAnInputError) {
  SyntheticCamera cam("no_such_scene", small_options(), false);
  const Status s = cam.open(4);
  ASSERT_EQ(s.code(), StatusCode::kInputError);
  EXPECT_NE(s.message().find("no_such_scene"), std::string::npos);
  EXPECT_NE(s.message().find("room_orbit"), std::string::npos);
}

TEST(SyntheticCamera, DeliversSequenceThenEndOfStream) {
  SyntheticCamera cam("room_orbit", small_options(), false);
  ASSERT_TRUE(cam.open(4).is_ok());
  ASSERT_TRUE(cam.start().is_ok());
  for (std::uint64_t i = 0; i < 20; ++i) {
    FrameHandle f;
    ASSERT_EQ(cam.acquire(f, 1'000'000'000), AcquireStatus::kFrame);
    EXPECT_EQ(f->seq, i);
    EXPECT_EQ(f->t_ns, static_cast<std::int64_t>(i) * static_cast<std::int64_t>(1e9 / 30.0));
    EXPECT_TRUE(f->has_ground_truth);
    EXPECT_EQ(f->gray.cols, 160);
    EXPECT_EQ(f->gray.rows, 120);
  }
  FrameHandle f;
  EXPECT_EQ(cam.acquire(f, 0), AcquireStatus::kEndOfStream);
}

TEST(SyntheticCamera, PoolExhaustionIsReportedNotFatal) {
  SyntheticCamera cam("room_orbit", small_options(), false);
  ASSERT_TRUE(cam.open(2).is_ok());
  ASSERT_TRUE(cam.start().is_ok());
  FrameHandle a;
  FrameHandle b;
  FrameHandle c;
  ASSERT_EQ(cam.acquire(a, 0), AcquireStatus::kFrame);
  ASSERT_EQ(cam.acquire(b, 0), AcquireStatus::kFrame);
  EXPECT_EQ(cam.acquire(c, 0), AcquireStatus::kPoolEmpty);
  cam.release(std::move(a));
  ASSERT_EQ(cam.acquire(c, 0), AcquireStatus::kFrame);
  EXPECT_EQ(c->seq, 2U) << "a frame that found no buffer is delivered on the next call";
}

TEST(SyntheticCamera, SameSeedSameImagesDifferentSeedDifferentImages) {
  auto first_frame = [](int seed) {
    SyntheticOptions o = small_options();
    o.seed = seed;
    SyntheticCamera cam("room_orbit", o, false);
    EXPECT_TRUE(cam.open(2).is_ok());
    EXPECT_TRUE(cam.start().is_ok());
    FrameHandle f;
    EXPECT_EQ(cam.acquire(f, 0), AcquireStatus::kFrame);
    return f->gray.clone();
  };
  const cv::Mat a = first_frame(1);
  const cv::Mat b = first_frame(1);
  const cv::Mat c = first_frame(2);
  EXPECT_EQ(cv::norm(a, b, cv::NORM_L1), 0.0);
  EXPECT_GT(cv::norm(a, c, cv::NORM_L1), 1000.0);
}

// Depth is geometry: back-projecting a pixel with its depth must land on a wall of the room.
TEST(SyntheticCamera, DepthBackProjectsOntoTheRoomWalls) {
  SyntheticOptions o = small_options();
  SyntheticCamera cam("room_orbit", o, false);
  ASSERT_TRUE(cam.open(2).is_ok());
  ASSERT_TRUE(cam.start().is_ok());
  FrameHandle f;
  ASSERT_EQ(cam.acquire(f, 0), AcquireStatus::kFrame);
  const CameraIntrinsics& K = cam.intrinsics();
  int checked = 0;
  for (int v = 0; v < o.height; v += 7) {
    for (int u = 0; u < o.width; u += 7) {
      const double z = f->depth.at<float>(v, u);
      ASSERT_GT(z, 0.0);
      const Eigen::Vector3d p_c((u - K.cx) / K.fx * z, (v - K.cy) / K.fy * z, z);
      const Eigen::Vector3d p_w = f->T_w_c_gt * p_c;
      const double dx = std::abs(std::abs(p_w.x()) - 0.5 * o.room_size_x);
      const double dy = std::abs(std::abs(p_w.y()) - 0.5 * o.room_size_y);
      const double dz = std::min(std::abs(p_w.z()), std::abs(p_w.z() - o.room_height));
      EXPECT_LT(std::min({dx, dy, dz}), 1e-3) << "pixel " << u << "," << v;
      ++checked;
    }
  }
  EXPECT_GT(checked, 300);
}

TEST(SyntheticCamera, ImagesHaveTexture) {
  SyntheticCamera cam("room_orbit", small_options(), false);
  ASSERT_TRUE(cam.open(2).is_ok());
  ASSERT_TRUE(cam.start().is_ok());
  FrameHandle f;
  ASSERT_EQ(cam.acquire(f, 0), AcquireStatus::kFrame);
  cv::Scalar mean;
  cv::Scalar stddev;
  cv::meanStdDev(f->gray, mean, stddev);
  EXPECT_GT(stddev[0], 20.0) << "walls must carry texture for feature detection";
}

TEST(SyntheticCamera, AcquireDoesNotAllocateAfterStart) {
  SyntheticCamera cam("room_orbit", small_options(), false);
  ASSERT_TRUE(cam.open(2).is_ok());
  ASSERT_TRUE(cam.start().is_ok());
  ASSERT_TRUE(platform::alloc::counter_linked());
  for (int i = 0; i < 5; ++i) {
    FrameHandle f;
    const auto before = platform::alloc::thread_allocations();
    ASSERT_EQ(cam.acquire(f, 0), AcquireStatus::kFrame);
    f.reset();
    EXPECT_EQ(platform::alloc::thread_allocations() - before, 0U) << "frame " << i;
  }
}

TEST(SyntheticCamera, PacedCameraKeepsItsRate) {
  SyntheticOptions o = small_options();
  o.fps = 50.0;
  o.num_frames = 6;
  SyntheticCamera cam("room_orbit", o, true);
  ASSERT_TRUE(cam.open(2).is_ok());
  ASSERT_TRUE(cam.start().is_ok());
  std::int64_t first = 0;
  std::int64_t last = 0;
  for (int i = 0; i < 6; ++i) {
    FrameHandle f;
    ASSERT_EQ(cam.acquire(f, 1'000'000'000), AcquireStatus::kFrame);
    (i == 0 ? first : last) = f->t_ready_ns;
  }
  // 5 periods of 20 ms: at least 100 ms of wall time between first and last frame.
  EXPECT_GE(last - first, 95'000'000);
}

}  // namespace
}  // namespace mer::hal
