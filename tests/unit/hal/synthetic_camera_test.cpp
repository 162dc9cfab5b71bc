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

// Distance from a world point to the nearest scene surface (room walls or box faces).
double distance_to_scene(const Eigen::Vector3d& p, const SyntheticCamera& cam) {
  const Eigen::Vector3d room_lo = cam.room_lo();
  const Eigen::Vector3d room_hi = cam.room_hi();
  double best = 1e9;
  for (int a = 0; a < 3; ++a) {
    best = std::min({best, std::abs(p[a] - room_lo[a]), std::abs(p[a] - room_hi[a])});
  }
  for (const auto& b : cam.boxes()) {
    const Eigen::Vector3d lo = b.lo.cast<double>();
    const Eigen::Vector3d hi = b.hi.cast<double>();
    const bool inside_xy = p.x() >= lo.x() - 1e-3 && p.x() <= hi.x() + 1e-3 &&
                           p.y() >= lo.y() - 1e-3 && p.y() <= hi.y() + 1e-3 &&
                           p.z() >= lo.z() - 1e-3 && p.z() <= hi.z() + 1e-3;
    if (!inside_xy) continue;
    for (int a = 0; a < 3; ++a) {
      best = std::min({best, std::abs(p[a] - lo[a]), std::abs(p[a] - hi[a])});
    }
  }
  return best;
}

// Depth is geometry: back-projecting a pixel with its depth must land on a scene surface.
TEST(SyntheticCamera, DepthBackProjectsOntoTheScene) {
  for (const char* scenario : {"room_orbit", "room_loop", "hall_drive"}) {
    SyntheticOptions o = small_options();
    SyntheticCamera cam(scenario, o, false);
    ASSERT_TRUE(cam.open(2).is_ok());
    ASSERT_TRUE(cam.start().is_ok());
    ASSERT_FALSE(cam.boxes().empty());
    const CameraIntrinsics& K = cam.intrinsics();
    int checked = 0;
    for (int i = 0; i < 20; ++i) {
      FrameHandle f;
      ASSERT_EQ(cam.acquire(f, 0), AcquireStatus::kFrame);
      if (i % 6 != 0) continue;
      for (int v = 0; v < o.height; v += 7) {
        for (int u = 0; u < o.width; u += 7) {
          const double z = f->depth.at<float>(v, u);
          ASSERT_GT(z, 0.0);
          const Eigen::Vector3d p_c((u - K.cx) / K.fx * z, (v - K.cy) / K.fy * z, z);
          const Eigen::Vector3d p_w = f->T_w_c_gt * p_c;
          // float ray casting: relative precision, the hall reaches 60 m
          EXPECT_LT(distance_to_scene(p_w, cam), 1e-3 * std::max(1.0, 0.1 * z))
              << scenario << " frame " << i << " pixel " << u << "," << v;
          ++checked;
        }
      }
    }
    EXPECT_GT(checked, 1000) << scenario;
  }
}

TEST(SyntheticCamera, BoxesStandInsideTheRoomClearOfTheCamera) {
  SyntheticOptions o = small_options();
  o.num_frames = 600;
  for (const char* scenario : {"room_orbit", "room_loop"}) {
    SyntheticCamera cam(scenario, o, false);
    ASSERT_TRUE(cam.open(2).is_ok());
    EXPECT_EQ(cam.boxes().size(), static_cast<std::size_t>(o.num_boxes));
    for (int i = 0; i < 600; i += 5) {
      const Eigen::Vector3d c = cam.sample_at(i / 30.0).T_w_c.translation();
      for (const auto& b : cam.boxes()) {
        const bool inside = (c.array() > b.lo.cast<double>().array() - 0.3).all() &&
                            (c.array() < b.hi.cast<double>().array() + 0.3).all();
        EXPECT_FALSE(inside) << scenario << " camera within 0.3 m of a box at t=" << i / 30.0;
      }
    }
  }
}

TEST(SyntheticCamera, HallDriveIsACarRoundABlock) {
  SyntheticOptions o = small_options();
  SyntheticCamera cam("hall_drive", o, false);
  ASSERT_TRUE(cam.open(2).is_ok());
  EXPECT_DOUBLE_EQ(cam.room_hi().x() - cam.room_lo().x(), o.hall_size_x);
  EXPECT_DOUBLE_EQ(cam.room_hi().z(), o.hall_height);
  EXPECT_EQ(cam.boxes().size(), static_cast<std::size_t>(o.num_boxes));
  // Default hall: the path is a 48 x 30 m block with 12 m corners, 135.4 m round.
  const double pi = 3.14159265358979;
  const double lap = 2.0 * (24.0 + 6.0) + 2.0 * pi * 12.0;
  const double lap_s = lap / o.drive_speed_mps;
  const double dt = lap_s / 500.0;
  double turned = 0.0;
  double length = 0.0;
  double min_box_distance = 1e9;
  Eigen::Vector3d prev = cam.sample_at(0.0).T_w_c.translation();
  double prev_heading = 0.0;
  for (int i = 1; i <= 500; ++i) {
    const double t = i * dt;
    const SE3d T = cam.sample_at(t).T_w_c;
    const Eigen::Vector3d c = T.translation();
    const Eigen::Vector3d axis = T.linear().col(2);  // optical axis, world
    EXPECT_NEAR(c.z(), 1.65, 0.03) << "t=" << t;
    EXPECT_LT(std::abs(axis.z()), 0.015) << "looks level, t=" << t;
    // Looks where it goes: the optical axis follows the motion within 1 degree.
    const Eigen::Vector3d step = c - prev;
    const Eigen::Vector2d move = step.head<2>().normalized();
    EXPECT_GT(move.dot(axis.head<2>().normalized()), std::cos(1.0 * 3.14159265358979 / 180.0))
        << "t=" << t;
    EXPECT_NEAR(step.head<2>().norm() / dt, o.drive_speed_mps, 0.01 * o.drive_speed_mps)
        << "t=" << t;
    const double heading = std::atan2(axis.y(), axis.x());
    turned += std::remainder(heading - prev_heading, 2.0 * 3.14159265358979);
    prev_heading = heading;
    length += step.head<2>().norm();
    prev = c;
    for (const auto& b : cam.boxes()) {
      const double gx = std::max({0.0, b.lo.x() - c.x(), c.x() - b.hi.x()});
      const double gy = std::max({0.0, b.lo.y() - c.y(), c.y() - b.hi.y()});
      min_box_distance = std::min(min_box_distance, std::hypot(gx, gy));
    }
    EXPECT_TRUE((c.head<2>().array() > cam.room_lo().head<2>().array() + 5.0).all() &&
                (c.head<2>().array() < cam.room_hi().head<2>().array() - 5.0).all())
        << "t=" << t;
  }
  // One lap: the length of the block, one full turn to the left, back where it started.
  EXPECT_NEAR(length, lap, 0.01 * lap);
  EXPECT_NEAR(turned, 2.0 * pi, 0.01);
  EXPECT_LT((cam.sample_at(lap_s).T_w_c.translation() - cam.sample_at(0.0).T_w_c.translation())
                .head<2>()
                .norm(),
            1e-6);
  EXPECT_GE(min_box_distance, 3.0 - 1e-6) << "boxes stay clear of the road";
}

TEST(SyntheticCamera, LoopReturnsToItsStart) {
  SyntheticCamera cam("room_loop", small_options(), false);
  ASSERT_TRUE(cam.open(2).is_ok());
  const SE3d a = cam.sample_at(0.0).T_w_c;
  const SE3d b = cam.sample_at(20.0).T_w_c;
  const SE3d mid = cam.sample_at(10.0).T_w_c;
  EXPECT_LT((a.translation() - b.translation()).norm(), 1e-9);
  EXPECT_LT(Eigen::Quaterniond(a.linear()).angularDistance(Eigen::Quaterniond(b.linear())), 1e-9);
  EXPECT_GT((a.translation() - mid.translation()).norm(), 2.0) << "the loop must go somewhere";
}

TEST(SyntheticCamera, KidnapBlacksOutThenReappearsEarlier) {
  SyntheticOptions o = small_options();
  o.fps = 10.0;
  o.num_frames = 120;
  SyntheticCamera cam("room_kidnap", o, false);
  ASSERT_TRUE(cam.open(2).is_ok());
  ASSERT_TRUE(cam.start().is_ok());
  std::vector<SE3d> poses;
  for (int i = 0; i < 120; ++i) {
    FrameHandle f;
    ASSERT_EQ(cam.acquire(f, 0), AcquireStatus::kFrame);
    const double t = i / 10.0;
    const bool black = t >= o.kidnap_start_s && t < o.kidnap_start_s + o.kidnap_black_s;
    EXPECT_EQ(f->has_ground_truth, !black) << "t=" << t;
    if (black) {
      EXPECT_EQ(cv::countNonZero(f->gray), 0) << "t=" << t;
    }
    poses.push_back(f->T_w_c_gt);
  }
  // First frame after the blackout (t = 9 s) shows the place of t = 2 s.
  EXPECT_LT((poses[90].translation() - poses[20].translation()).norm(), 1e-9);
  EXPECT_GT((poses[90].translation() - poses[79].translation()).norm(), 0.5);
}

TEST(SyntheticCamera, FastRotationTurnsQuickly) {
  SyntheticCamera cam("room_fast_rotation", small_options(), false);
  ASSERT_TRUE(cam.open(2).is_ok());
  double peak_deg_s = 0.0;
  const double dt = 1.0 / 30.0;
  for (double t = 0.0; t < 8.0; t += dt) {
    const Eigen::Quaterniond a(cam.sample_at(t).T_w_c.linear());
    const Eigen::Quaterniond b(cam.sample_at(t + dt).T_w_c.linear());
    peak_deg_s = std::max(peak_deg_s, a.angularDistance(b) / dt * 180.0 / 3.14159265358979);
  }
  EXPECT_GT(peak_deg_s, 200.0);  // 1.5 * 360 / 2 s = 270 deg/s plus the orbit's own turn
}

TEST(SyntheticCamera, ExposureVariesBrightness) {
  SyntheticOptions o = small_options();
  o.exposure_amplitude = 0.5;
  o.exposure_period_s = 2.0;
  o.noise_sigma = 0.0;
  SyntheticCamera cam("room_orbit", o, false);
  ASSERT_TRUE(cam.open(2).is_ok());
  cv::Mat bright(o.height, o.width, CV_8UC1);
  cv::Mat dark(o.height, o.width, CV_8UC1);
  const SE3d T = cam.sample_at(0.0).T_w_c;
  cam.render(T, bright, nullptr, 0, 1.5F);
  cam.render(T, dark, nullptr, 0, 0.5F);
  EXPECT_GT(cv::mean(bright)[0], 1.5 * cv::mean(dark)[0]);
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
