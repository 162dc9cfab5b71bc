// Synthetic camera: determinism, geometry of the rendered depth, pool and stream behaviour.
#include "hal/synthetic/synthetic_camera.h"

#include <cmath>
#include <filesystem>
#include <set>

#include <gtest/gtest.h>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include "platform/alloc_counter.h"
#include "support/required_data.h"

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

// ---- Reproduction scenarios, photo textures and camera effects ----

constexpr double kPi = 3.14159265358979;
constexpr std::array<const char*, 7> kNewScenarios{
    "hall_turn",           "room_explore",  "room_rotation", "corridor",
    "room_kidnap_unknown", "room_repeated", "hall_repeated"};

// Small images and procedural textures: these tests need no photo package.
SyntheticOptions procedural_options() {
  SyntheticOptions o = small_options();
  o.texture = "procedural";
  return o;
}

bool have_photos() {
  return std::filesystem::is_directory(kDefaultPhotoDir);
}

#define SKIP_WITHOUT_PHOTOS()                                                            \
  MER_REQUIRE_DATA(have_photos()) << kDefaultPhotoDir << " is missing: apt-get install " \
                                  << kPhotoPackage << " (tools/dev.sh setup installs it)"

std::uint64_t fnv1a(const cv::Mat& m) {
  std::uint64_t h = 1469598103934665603ULL;
  for (int r = 0; r < m.rows; ++r) {
    const auto* p = m.ptr<std::uint8_t>(r);
    for (std::size_t i = 0; i < static_cast<std::size_t>(m.cols) * m.elemSize(); ++i) {
      h ^= p[i];
      h *= 1099511628211ULL;
    }
  }
  return h;
}

double heading_of(const SE3d& T) {
  const Eigen::Vector3d axis = T.linear().col(2);
  return std::atan2(axis.y(), axis.x());
}

// Mean squared Sobel gradient: drops when an image is blurred.
double gradient_energy(const cv::Mat& gray) {
  cv::Mat gx;
  cv::Mat gy;
  cv::Sobel(gray, gx, CV_32F, 1, 0);
  cv::Sobel(gray, gy, CV_32F, 0, 1);
  return cv::mean(gx.mul(gx) + gy.mul(gy))[0];
}

cv::Mat frame_at(SyntheticCamera& cam, int index) {
  EXPECT_TRUE(cam.start().is_ok());
  FrameHandle f;
  for (int i = 0; i <= index; ++i) {
    f.reset();
    EXPECT_EQ(cam.acquire(f, 0), AcquireStatus::kFrame);
  }
  return f->gray.clone();
}

// The existing scenarios render exactly as before the reproduction scenarios, photo
// textures and effects were added (hashes of frames 10, 100 and 290 taken before).
TEST(SyntheticCamera, ExistingScenariosUnchangedByDefault) {
  struct Expected {
    const char* scenario;
    std::array<std::uint64_t, 6> hashes;  // gray, depth at frames 10, 100, 290
  };
  const std::array<Expected, 5> expected{{
      {"room_orbit",
       {0x5de0b7c97ae03882ULL, 0x0e2d4f31f6ae513cULL, 0x5263e7286a0d0d77ULL, 0x547a2b72f89511c8ULL,
        0x023abc571e2f2aa6ULL, 0x5ee183d91bd9d284ULL}},
      {"room_loop",
       {0x1e38c3a11ef21f4bULL, 0xb0ff203b10dc1195ULL, 0x836adbd28c520797ULL, 0xb20ae9a835bccc60ULL,
        0xd331515d31263cdbULL, 0x5e29b29192f1f9fbULL}},
      {"room_kidnap",
       {0x5de0b7c97ae03882ULL, 0x0e2d4f31f6ae513cULL, 0x5263e7286a0d0d77ULL, 0x547a2b72f89511c8ULL,
        0x7f54b4d6911044a5ULL, 0x4cd3060c503805deULL}},
      {"room_fast_rotation",
       {0x5de0b7c97ae03882ULL, 0x0e2d4f31f6ae513cULL, 0xf3636cd13794c691ULL, 0x1702e2b07db31363ULL,
        0x023abc571e2f2aa6ULL, 0x5ee183d91bd9d284ULL}},
      {"hall_drive",
       {0x331121d2a180f498ULL, 0x577896cfd5270970ULL, 0xef563809e81953a0ULL, 0xc338b936b9164ff3ULL,
        0x3e5c2c8b58f3e4c3ULL, 0xb6e91f9f79e44952ULL}},
  }};
  for (const Expected& e : expected) {
    SyntheticOptions o = small_options();  // texture: auto, no blur, no steps
    o.num_frames = 300;
    SyntheticCamera cam(e.scenario, o, false);
    ASSERT_TRUE(cam.open(2).is_ok());
    ASSERT_TRUE(cam.start().is_ok());
    EXPECT_TRUE(cam.photo_files().empty()) << e.scenario << "auto stays procedural";
    std::size_t k = 0;
    for (int i = 0; i <= 290; ++i) {
      FrameHandle f;
      ASSERT_EQ(cam.acquire(f, 0), AcquireStatus::kFrame);
      if (i != 10 && i != 100 && i != 290) continue;
      EXPECT_EQ(fnv1a(f->gray), e.hashes[k]) << e.scenario << " frame " << i << " gray";
      EXPECT_EQ(fnv1a(f->depth), e.hashes[k + 1]) << e.scenario << " frame " << i << " depth";
      k += 2;
    }
  }
}

TEST(SyntheticCamera, NewScenariosRenderTexturedFramesWithSceneDepth) {
  for (const char* scenario : kNewScenarios) {
    SyntheticOptions o = procedural_options();
    SyntheticCamera cam(scenario, o, false);
    ASSERT_TRUE(cam.open(2).is_ok()) << scenario;
    ASSERT_TRUE(cam.start().is_ok());
    const CameraIntrinsics& K = cam.intrinsics();
    for (int i = 0; i < 20; ++i) {
      FrameHandle f;
      ASSERT_EQ(cam.acquire(f, 0), AcquireStatus::kFrame) << scenario;
      if (i % 9 != 0) continue;
      cv::Scalar mean;
      cv::Scalar stddev;
      cv::meanStdDev(f->gray, mean, stddev);
      EXPECT_GT(stddev[0], 3.0) << scenario << " frame " << i;
      for (int v = 0; v < o.height; v += 11) {
        for (int u = 0; u < o.width; u += 11) {
          const double z = f->depth.at<float>(v, u);
          ASSERT_GT(z, 0.0);
          const Eigen::Vector3d p_c((u - K.cx) / K.fx * z, (v - K.cy) / K.fy * z, z);
          EXPECT_LT(distance_to_scene(f->T_w_c_gt * p_c, cam), 1e-3 * std::max(1.0, 0.1 * z))
              << scenario << " frame " << i << " pixel " << u << "," << v;
        }
      }
    }
  }
}

TEST(SyntheticCamera, HallTurnStartsInASharpLowSpeedTurn) {
  SyntheticOptions o = procedural_options();
  o.fps = 10.0;
  o.num_frames = 160;
  SyntheticCamera cam("hall_turn", o, false);
  ASSERT_TRUE(cam.open(2).is_ok());
  // The first 4 s: 90-100 degrees to the left at 2.5-4.5 m/s, turning from the first frame.
  double turned = 0.0;
  double max_step_deg = 0.0;
  for (int i = 0; i < 40; ++i) {
    const SE3d a = cam.sample_at(i / 10.0).T_w_c;
    const SE3d b = cam.sample_at((i + 1) / 10.0).T_w_c;
    const double step = std::remainder(heading_of(b) - heading_of(a), 2.0 * kPi);
    turned += step;
    max_step_deg = std::max(max_step_deg, step * 180.0 / kPi);
    const double speed = (b.translation() - a.translation()).head<2>().norm() * 10.0;
    EXPECT_GE(speed, 2.5) << "frame " << i;
    EXPECT_LE(speed, 4.5) << "frame " << i;
    if (i == 0) {
      EXPECT_GT(step * 180.0 / kPi, 1.5) << "turning from the first frame";
    }
  }
  EXPECT_GE(turned * 180.0 / kPi, 90.0);
  EXPECT_LE(turned * 180.0 / kPi, 100.0);
  EXPECT_GT(max_step_deg, 2.8);
  EXPECT_LT(max_step_deg, 4.0);
  // Then it drives on and turns left again: 16 s make 185 degrees and over 50 m, inside the
  // hall, level and clear of the boxes.
  double length = 0.0;
  double total = 0.0;
  for (int i = 0; i < 160; ++i) {
    const SE3d a = cam.sample_at(i / 10.0).T_w_c;
    const SE3d b = cam.sample_at((i + 1) / 10.0).T_w_c;
    total += std::remainder(heading_of(b) - heading_of(a), 2.0 * kPi);
    length += (b.translation() - a.translation()).head<2>().norm();
    const Eigen::Vector3d c = b.translation();
    EXPECT_NEAR(c.z(), 1.65, 0.03);
    EXPECT_TRUE((c.head<2>().array() > cam.room_lo().head<2>().array() + 5.0).all() &&
                (c.head<2>().array() < cam.room_hi().head<2>().array() - 5.0).all());
    for (const auto& box : cam.boxes()) {
      const double gx = std::max({0.0, box.lo.x() - c.x(), c.x() - box.hi.x()});
      const double gy = std::max({0.0, box.lo.y() - c.y(), c.y() - box.hi.y()});
      EXPECT_GE(std::hypot(gx, gy), 2.9);
    }
  }
  EXPECT_NEAR(total * 180.0 / kPi, 185.0, 1.0);
  EXPECT_GT(length, 50.0);
  // A hall too small for the drive is refused, naming the options.
  o.hall_size_y = 30.0;
  SyntheticCamera small("hall_turn", o, false);
  const Status s = small.open(2);
  EXPECT_FALSE(s.is_ok());
  EXPECT_NE(s.message().find("hall_size"), std::string::npos) << s.message();
}

TEST(SyntheticCamera, RoomExploreWalksOutAndReturnsThroughItsStart) {
  SyntheticOptions o = procedural_options();
  o.room_size_x = 10.0;
  o.room_size_y = 8.0;
  o.num_boxes = 16;
  o.num_frames = 600;
  SyntheticCamera cam("room_explore", o, false);
  ASSERT_TRUE(cam.open(2).is_ok());
  EXPECT_EQ(cam.boxes().size(), 16U);
  const SE3d start = cam.sample_at(0.0).T_w_c;
  double closest_late = 1e9;  // closest approach to the start after 15 s
  double farthest = 0.0;
  double max_view_change = 0.0;  // largest heading difference from the start view
  double turned = 0.0;
  for (int i = 1; i < 600; ++i) {
    const SE3d a = cam.sample_at((i - 1) / 30.0).T_w_c;
    const SE3d b = cam.sample_at(i / 30.0).T_w_c;
    const double speed = (b.translation() - a.translation()).head<2>().norm() * 30.0;
    EXPECT_LT(speed, 0.5) << "hand-held walk, frame " << i;
    turned += std::remainder(heading_of(b) - heading_of(a), 2.0 * kPi);
    const double d = (b.translation() - start.translation()).norm();
    farthest = std::max(farthest, d);
    if (i > 450) closest_late = std::min(closest_late, d);
    max_view_change = std::max(
        max_view_change, std::abs(std::remainder(heading_of(b) - heading_of(start), 2.0 * kPi)));
  }
  EXPECT_GT(farthest, 1.0) << "it must go somewhere";
  EXPECT_GT(max_view_change * 180.0 / kPi, 150.0) << "views round the whole room";
  EXPECT_GT(turned * 180.0 / kPi, 300.0);
  EXPECT_LT(closest_late, 0.10) << "passes back through its start";
}

TEST(SyntheticCamera, RoomRotationIsRotationDominantFromTheFirstFrame) {
  SyntheticOptions o = procedural_options();
  o.num_frames = 300;
  SyntheticCamera cam("room_rotation", o, false);
  ASSERT_TRUE(cam.open(2).is_ok());
  const SE3d start = cam.sample_at(0.0).T_w_c;
  double yaw_min = 0.0;
  double yaw_max = 0.0;
  double max_translation = 0.0;
  for (int i = 0; i <= 300; ++i) {
    const SE3d T = cam.sample_at(i / 30.0).T_w_c;
    max_translation = std::max(max_translation, (T.translation() - start.translation()).norm());
    const double yaw = std::remainder(heading_of(T) - heading_of(start), 2.0 * kPi);
    yaw_min = std::min(yaw_min, yaw);
    yaw_max = std::max(yaw_max, yaw);
  }
  EXPECT_LT(max_translation, 0.10) << "a few cm of translation";
  EXPECT_GT((yaw_max - yaw_min) * 180.0 / kPi, 70.0) << "sweeps of +-30-45 degrees";
  // The first frames already rotate at a hand-held rate: over 1 deg per frame at 30 Hz,
  // while moving under 3 mm.
  const SE3d f1 = cam.sample_at(1.0 / 30.0).T_w_c;
  const double rot_deg =
      Eigen::Quaterniond(start.linear()).angularDistance(Eigen::Quaterniond(f1.linear())) * 180.0 /
      kPi;
  EXPECT_GT(rot_deg, 1.0);
  EXPECT_LT((f1.translation() - start.translation()).norm(), 0.003);
}

TEST(SyntheticCamera, CorridorIsLongNarrowAndMostlyWhite) {
  SyntheticOptions o = procedural_options();
  o.fps = 10.0;
  o.num_frames = 200;
  SyntheticCamera cam("corridor", o, false);
  ASSERT_TRUE(cam.open(2).is_ok());
  EXPECT_DOUBLE_EQ(cam.room_hi().x() - cam.room_lo().x(), o.corridor_length);
  EXPECT_DOUBLE_EQ(cam.room_hi().y() - cam.room_lo().y(), o.corridor_width);
  EXPECT_TRUE(cam.boxes().empty());
  double length = 0.0;
  for (int i = 1; i <= 200; ++i) {
    const SE3d a = cam.sample_at((i - 1) / 10.0).T_w_c;
    const SE3d b = cam.sample_at(i / 10.0).T_w_c;
    length += (b.translation() - a.translation()).head<2>().norm();
    EXPECT_LT(std::abs(b.translation().y()), 0.5 * o.corridor_width - 0.5) << "frame " << i;
  }
  EXPECT_GT(length, 18.0) << "~1 m/s for 20 s";
  // Low texture: bright and flat next to room_orbit's walls.
  SyntheticOptions ro = small_options();
  ro.num_frames = 40;
  SyntheticCamera room("room_orbit", ro, false);
  ASSERT_TRUE(room.open(2).is_ok());
  const cv::Mat c = frame_at(cam, 30);
  const cv::Mat r = frame_at(room, 30);
  EXPECT_GT(cv::mean(c)[0], 150.0);
  EXPECT_LT(gradient_energy(c), 0.5 * gradient_energy(r));
}

TEST(SyntheticCamera, KidnapUnknownReappearsWhereNothingWasSeen) {
  SyntheticOptions o = procedural_options();
  o.room_size_x = 10.0;
  o.room_size_y = 8.0;
  o.num_frames = 600;
  SyntheticCamera cam("room_kidnap_unknown", o, false);
  ASSERT_TRUE(cam.open(2).is_ok());
  ASSERT_TRUE(cam.start().is_ok());
  const CameraIntrinsics& K = cam.intrinsics();
  std::vector<SE3d> poses;
  std::vector<cv::Mat> depths;
  int first_back = -1;  // the first frame after the blackout (t = 9 s)
  cv::Mat reappear_depth;
  SE3d reappear = SE3d::Identity();
  for (int i = 0; i < 600; ++i) {
    FrameHandle f;
    ASSERT_EQ(cam.acquire(f, 0), AcquireStatus::kFrame);
    const double t = static_cast<double>(f->t_ns) * 1e-9;
    const bool black = t >= o.kidnap_start_s && t < o.kidnap_start_s + o.kidnap_black_s;
    EXPECT_EQ(f->has_ground_truth, !black) << "frame " << i;
    if (black) continue;
    if (t < o.kidnap_start_s && i % 3 == 0) {
      poses.push_back(f->T_w_c_gt);
      depths.push_back(f->depth.clone());
    }
    if (t > o.kidnap_start_s && first_back < 0) {
      first_back = i;
      reappear = f->T_w_c_gt;
      reappear_depth = f->depth.clone();
    }
    if (i == 599) {
      // Back home: looking at the mapped half again.
      EXPECT_GT(f->T_w_c_gt.linear().col(2).dot(poses.front().linear().col(2)), 0.9);
    }
  }
  // Its view direction differs by more than 90 degrees from every earlier one ...
  for (const SE3d& T : poses) {
    EXPECT_LT(reappear.linear().col(2).dot(T.linear().col(2)), 0.0);
  }
  EXPECT_GT((reappear.translation() - poses.back().translation()).norm(), 2.0);
  // ... and almost none of the surface it sees was seen before: a back-projected pixel counts
  // as seen when an earlier frame saw that point (in its image, at its depth).
  int seen = 0;
  int total = 0;
  for (int v = 0; v < o.height; v += 6) {
    for (int u = 0; u < o.width; u += 6) {
      const double z = reappear_depth.at<float>(v, u);
      const Eigen::Vector3d p_w =
          reappear * Eigen::Vector3d((u - K.cx) / K.fx * z, (v - K.cy) / K.fy * z, z);
      ++total;
      for (std::size_t k = 0; k < poses.size(); ++k) {
        const Eigen::Vector3d p_c = poses[k].inverse() * p_w;
        if (p_c.z() <= 0.05) continue;
        const double pu = K.fx * p_c.x() / p_c.z() + K.cx;
        const double pv = K.fy * p_c.y() / p_c.z() + K.cy;
        if (pu < 0 || pv < 0 || pu > o.width - 1 || pv > o.height - 1) continue;
        const double zk = depths[k].at<float>(static_cast<int>(pv), static_cast<int>(pu));
        if (std::abs(zk - p_c.z()) < 0.05 * p_c.z()) {
          ++seen;
          break;
        }
      }
    }
  }
  EXPECT_LT(seen, total / 50) << seen << " of " << total << " points were seen before";
}

TEST(SyntheticCamera, MotionBlurBlursAMovingCameraOnly) {
  // Moving: room_rotation's sweep; static: the same with every amplitude zero.
  auto energy = [](double exposure, bool moving, cv::Mat* out) {
    SyntheticOptions o = procedural_options();
    o.width = 320;
    o.height = 240;
    o.noise_sigma = 0.0;
    o.exposure_time_s = exposure;
    if (!moving) {
      o.sweep_yaw_deg = 0.0;
      o.sweep_pitch_deg = 0.0;
      o.sweep_translation_m = 0.0;
    }
    SyntheticCamera cam("room_rotation", o, false);
    EXPECT_TRUE(cam.open(2).is_ok());
    const cv::Mat img = frame_at(cam, 3);
    if (out != nullptr) *out = img;
    return gradient_energy(img);
  };
  const double e0 = energy(0.0, true, nullptr);
  const double e1 = energy(0.01, true, nullptr);
  const double e2 = energy(0.03, true, nullptr);
  EXPECT_LT(e1, 0.9 * e0);
  EXPECT_LT(e2, 0.8 * e1);
  cv::Mat still0;
  cv::Mat still1;
  energy(0.0, false, &still0);
  energy(0.03, false, &still1);
  EXPECT_EQ(cv::norm(still0, still1, cv::NORM_L1), 0.0) << "a static camera is not blurred";
}

TEST(SyntheticCamera, MotionBlurKeepsNoiseAndDepthOfTheFrameTime) {
  SyntheticOptions o = procedural_options();
  o.exposure_time_s = 0.02;
  for (int samples : {4, 5}) {
    o.blur_samples = samples;
    SyntheticCamera cam("room_rotation", o, false);
    ASSERT_TRUE(cam.open(2).is_ok());
    ASSERT_TRUE(cam.start().is_ok());
    FrameHandle f;
    ASSERT_EQ(cam.acquire(f, 0), AcquireStatus::kFrame);
    cv::Mat depth(o.height, o.width, CV_32FC1);
    cv::Mat gray(o.height, o.width, CV_8UC1);
    cam.render(f->T_w_c_gt, gray, &depth, 0);
    EXPECT_EQ(cv::norm(depth, f->depth, cv::NORM_INF), 0.0) << samples << " samples";
  }
}

TEST(SyntheticCamera, ExposureStepsJumpTheGain) {
  SyntheticOptions o = procedural_options();
  o.exposure_step_every_s = 1.0;
  o.exposure_step_size = 0.3;
  SyntheticCamera cam("room_rotation", o, false);
  ASSERT_TRUE(cam.open(2).is_ok());
  EXPECT_DOUBLE_EQ(cam.gain_at(0.5), 1.0);
  for (int k = 1; k <= 8; ++k) {
    const double before = cam.gain_at(k - 0.01);
    const double after = cam.gain_at(k + 0.01);
    EXPECT_DOUBLE_EQ(cam.gain_at(k + 0.5), after) << "constant between steps";
    const double ratio = after / before;
    EXPECT_TRUE(std::abs(ratio - 1.3) < 1e-9 || std::abs(ratio - 1.0 / 1.3) < 1e-9) << ratio;
    EXPECT_LE(std::abs(std::log(after) / std::log(1.3)), 2.0 + 1e-9) << "within two notches";
  }
  // Off by default.
  SyntheticCamera plain("room_rotation", procedural_options(), false);
  ASSERT_TRUE(plain.open(2).is_ok());
  EXPECT_DOUBLE_EQ(plain.gain_at(3.5), 1.0);
}

TEST(SyntheticCamera, NewScenariosAreDeterministicAndAllocationFree) {
  SyntheticOptions o = procedural_options();
  o.exposure_time_s = 0.01;
  o.exposure_step_every_s = 0.2;
  for (const char* scenario : kNewScenarios) {
    auto run = [&](int seed) {
      SyntheticOptions so = o;
      so.seed = seed;
      SyntheticCamera cam(scenario, so, false);
      EXPECT_TRUE(cam.open(2).is_ok());
      EXPECT_TRUE(cam.start().is_ok());
      cv::Mat last;
      for (int i = 0; i < 4; ++i) {
        FrameHandle f;
        const auto before = platform::alloc::thread_allocations();
        EXPECT_EQ(cam.acquire(f, 0), AcquireStatus::kFrame);
        last = f->gray;  // shares the pool buffer: no allocation
        if (i > 0) {
          EXPECT_EQ(platform::alloc::thread_allocations() - before, 0U)
              << scenario << " frame " << i;
        }
        last = last.clone();
      }
      return last;
    };
    const cv::Mat a = run(1);
    const cv::Mat b = run(1);
    const cv::Mat c = run(2);
    EXPECT_EQ(cv::norm(a, b, cv::NORM_L1), 0.0) << scenario;
    EXPECT_GT(cv::norm(a, c, cv::NORM_L1), 1000.0) << scenario;
  }
}

TEST(SyntheticCamera, MissingPhotoFolderIsAClearError) {
  SyntheticOptions o = small_options();
  o.texture = "photo";
  o.photo_dir = "/nonexistent/photos";
  SyntheticCamera cam("room_orbit", o, false);
  const Status s = cam.open(2);
  ASSERT_FALSE(s.is_ok());
  EXPECT_NE(s.message().find("/nonexistent/photos"), std::string::npos) << s.message();
  EXPECT_NE(s.message().find("mate-backgrounds"), std::string::npos) << s.message();
  // texture: auto means photo for the reproduction scenarios: no silent fallback either.
  o.texture = "auto";
  SyntheticCamera turn("hall_turn", o, false);
  EXPECT_FALSE(turn.open(2).is_ok());
}

TEST(SyntheticCamera, PhotoTexturesLoadOnePhotoPerWallBySeed) {
  SKIP_WITHOUT_PHOTOS();
  SyntheticOptions o = small_options();
  o.texture = "photo";
  std::set<std::string> first;
  std::vector<std::string> seeds_1;
  for (int seed : {1, 2}) {
    o.seed = seed;
    SyntheticCamera cam("room_orbit", o, false);
    ASSERT_TRUE(cam.open(2).is_ok());
    ASSERT_EQ(cam.photo_files().size(), 6U);
    const std::set<std::string> distinct(cam.photo_files().begin(), cam.photo_files().end());
    EXPECT_EQ(distinct.size(), 6U) << "a different photo on each wall";
    if (seed == 1) {
      seeds_1 = cam.photo_files();
    } else {
      EXPECT_NE(cam.photo_files(), seeds_1) << "seeds pick different photos";
    }
    const cv::Mat img = frame_at(cam, 0);
    cv::Scalar mean;
    cv::Scalar stddev;
    cv::meanStdDev(img, mean, stddev);
    EXPECT_GT(stddev[0], 10.0);
  }
}

TEST(SyntheticCamera, PhotoSetsSplitTheListInTwoDisjointHalves) {
  SKIP_WITHOUT_PHOTOS();
  SyntheticOptions o;
  std::vector<std::string> all;
  std::vector<std::string> dev;
  std::vector<std::string> heldout;
  o.photo_set = "all";
  ASSERT_TRUE(SyntheticCamera::list_photos(o, all).is_ok());
  o.photo_set = "dev";
  ASSERT_TRUE(SyntheticCamera::list_photos(o, dev).is_ok());
  o.photo_set = "heldout";
  ASSERT_TRUE(SyntheticCamera::list_photos(o, heldout).is_ok());
  EXPECT_GE(all.size(), 12U);
  EXPECT_EQ(dev.size() + heldout.size(), all.size());
  EXPECT_LE(std::abs(static_cast<int>(dev.size()) - static_cast<int>(heldout.size())), 1);
  for (const std::string& p : dev) {
    EXPECT_EQ(std::count(heldout.begin(), heldout.end(), p), 0) << p;
    EXPECT_EQ(p.find("_3840x2160"), std::string::npos) << "resolution variants are left out";
  }
  // A wall photo comes from the chosen half.
  o.texture = "photo";
  o.width = 64;
  o.height = 48;
  SyntheticCamera cam("room_explore", o, false);
  ASSERT_TRUE(cam.open(2).is_ok());
  for (const std::string& p : cam.photo_files()) {
    EXPECT_EQ(std::count(heldout.begin(), heldout.end(), p), 1) << p;
  }
}

TEST(SyntheticCamera, ScenarioConfigsOpenWithPhotosAndBlur) {
  SKIP_WITHOUT_PHOTOS();
  // The reproduction scenarios' defaults (texture: auto -> photo) with their configs' effects.
  for (const char* scenario : kNewScenarios) {
    SyntheticOptions o = small_options();
    o.exposure_time_s = 0.01;
    o.exposure_step_every_s = 5.0;
    SyntheticCamera cam(scenario, o, false);
    ASSERT_TRUE(cam.open(2).is_ok()) << scenario;
    EXPECT_EQ(cam.photo_files().size(), 6U) << scenario;
    const cv::Mat img = frame_at(cam, 5);
    cv::Scalar mean;
    cv::Scalar stddev;
    cv::meanStdDev(img, mean, stddev);
    EXPECT_GT(stddev[0], 2.0) << scenario;
  }
}

// ---- Look-alike places: repeat_texture, room_repeated, hall_repeated ----

// room_repeated as in configs/scenarios/room_repeated.yaml, small and procedural.
SyntheticOptions room_repeated_options() {
  SyntheticOptions o = procedural_options();
  o.num_frames = 960;
  o.room_size_x = 8.0;
  o.room_size_y = 6.0;
  o.room_height = 2.7;
  o.num_boxes = 8;
  o.repeat_texture = 3;
  o.kidnap_start_s = 19.0;
  o.kidnap_black_s = 0.15;
  return o;
}

// hall_repeated as in configs/scenarios/hall_repeated.yaml, small and procedural.
SyntheticOptions hall_repeated_options() {
  SyntheticOptions o = procedural_options();
  o.fps = 10.0;
  o.num_frames = 400;
  o.hall_size_x = 40.0;
  o.hall_size_y = 20.0;
  o.hall_height = 6.0;
  o.drive_speed_mps = 2.2;
  o.num_boxes = 6;
  o.repeat_texture = 16;
  return o;
}

// A camera `dist` m in front of the centre of `panel`, `right` m to its right as seen from
// the room, looking straight at the wall.
SE3d facing_panel(const SyntheticCamera& cam, const WallPanel& panel, double dist, double right) {
  const auto a = static_cast<std::size_t>(panel.wall / 2);
  const std::size_t pa = a == 0 ? 1 : 0;
  Eigen::Vector3d centre;
  centre[a] = panel.wall % 2 == 0 ? cam.room_lo()[a] : cam.room_hi()[a];
  centre[pa] = 0.5 * (panel.u0 + panel.u1);
  centre[2] = 0.5 * (panel.v0 + panel.v1);
  Eigen::Vector3d inward = Eigen::Vector3d::Zero();
  inward[a] = panel.wall % 2 == 0 ? 1.0 : -1.0;
  const Eigen::Vector3d to_right = (-inward).cross(Eigen::Vector3d::UnitZ());
  const Eigen::Vector3d eye = centre + dist * inward + right * to_right;
  return look_at(eye, eye - inward, Eigen::Vector3d::UnitZ());
}

// Renders, without noise, the views `dist` m in front of panels i and j (slightly off-centre)
// and returns their mean absolute difference and, in `max_diff`, the largest.
double panel_view_difference(const SyntheticCamera& cam, std::size_t i, std::size_t j, double dist,
                             double* max_diff) {
  const CameraIntrinsics& K = cam.intrinsics();
  cv::Mat a(K.height, K.width, CV_8UC1);
  cv::Mat b(K.height, K.width, CV_8UC1);
  cv::Mat depth_a(K.height, K.width, CV_32FC1);
  cv::Mat depth_b(K.height, K.width, CV_32FC1);
  cam.render(facing_panel(cam, cam.panels()[i], dist, 0.13), a, &depth_a, 0);
  cam.render(facing_panel(cam, cam.panels()[j], dist, 0.13), b, &depth_b, 0);
  EXPECT_LT(cv::norm(depth_a, depth_b, cv::NORM_INF), 1e-3) << "the same view of a flat wall";
  if (max_diff != nullptr) *max_diff = cv::norm(a, b, cv::NORM_INF);
  return cv::norm(a, b, cv::NORM_L1) / static_cast<double>(a.total());
}

// Every copy of the panel renders the same image from the same place in front of it (the
// views see nothing but the panel: 25 degrees wide, 2 m away), and the panel has texture.
void expect_identical_copies(const char* scenario, SyntheticOptions o, std::size_t copies) {
  o.width = 160;
  o.height = 120;
  o.fov_x_deg = 25.0;
  o.noise_sigma = 0.0;
  o.num_boxes = 0;
  SyntheticCamera cam(scenario, o, false);
  ASSERT_TRUE(cam.open(2).is_ok()) << scenario;
  ASSERT_EQ(cam.panels().size(), copies) << scenario;
  std::set<int> walls;
  for (std::size_t k = 1; k < cam.panels().size(); ++k) {
    walls.insert(cam.panels()[k].wall);
    double max_diff = 0.0;
    const double mean_diff = panel_view_difference(cam, 0, k, 2.0, &max_diff);
    EXPECT_LT(mean_diff, 0.1) << scenario << " copy " << k << " on wall " << cam.panels()[k].wall;
    EXPECT_LE(max_diff, 2.0) << scenario << " copy " << k;
  }
  EXPECT_GE(walls.size(), 2U) << scenario << ": copies on two walls at least";
  cv::Mat view(o.height, o.width, CV_8UC1);
  cam.render(facing_panel(cam, cam.panels()[0], 2.0, 0.13), view, nullptr, 0);
  cv::Scalar mean;
  cv::Scalar stddev;
  cv::meanStdDev(view, mean, stddev);
  EXPECT_GT(stddev[0], 5.0) << scenario << ": the panel carries a picture";
  // Without the option the same views differ: the walls differ.
  o.repeat_texture = 0;
  SyntheticCamera plain(scenario, o, false);
  ASSERT_TRUE(plain.open(2).is_ok());
  EXPECT_TRUE(plain.panels().empty());
  cv::Mat a(o.height, o.width, CV_8UC1);
  cv::Mat b(o.height, o.width, CV_8UC1);
  plain.render(facing_panel(cam, cam.panels()[0], 2.0, 0.13), a, nullptr, 0);
  plain.render(facing_panel(cam, cam.panels().back(), 2.0, 0.13), b, nullptr, 0);
  EXPECT_GT(cv::norm(a, b, cv::NORM_L1) / static_cast<double>(a.total()), 5.0) << scenario;
}

// The reproduction scenarios before room_repeated render exactly as before repeat_texture
// was added (procedural textures, motion blur and exposure steps on; hashes of frames 10 and
// 100 taken before).
TEST(SyntheticCamera, ReproductionScenariosUnchangedByDefault) {
  struct Expected {
    const char* scenario;
    std::array<std::uint64_t, 4> hashes;  // gray, depth at frames 10, 100
  };
  const std::array<Expected, 5> expected{{
      {"hall_turn",
       {0xc3263d3b783f2bfbULL, 0x18f4dc96bff8765dULL, 0xf7d97d54b0505724ULL,
        0x308df7e4144e861cULL}},
      {"room_explore",
       {0xb44c882a13306c2aULL, 0x9b68033a5d844679ULL, 0xc7d32d2a430c047dULL,
        0x1b49c077131d1aedULL}},
      {"room_rotation",
       {0x28a04501e176fd8eULL, 0x529f04592e61ec40ULL, 0xe9130f2550b414c1ULL,
        0x3339358611176e39ULL}},
      {"corridor",
       {0x1bed4b2d59161b10ULL, 0xa7337cc10e083b18ULL, 0xa8052115556325a3ULL,
        0x39025af0c2e9bf79ULL}},
      {"room_kidnap_unknown",
       {0x5083f08cfcaabd65ULL, 0x02320dc43d2f60b8ULL, 0x6ea9ce2818bcfb02ULL,
        0xdba78fc6ea855d4eULL}},
  }};
  for (const Expected& e : expected) {
    SyntheticOptions o = procedural_options();
    o.num_frames = 300;
    o.exposure_time_s = 0.01;
    o.exposure_step_every_s = 0.5;
    SyntheticCamera cam(e.scenario, o, false);
    ASSERT_TRUE(cam.open(2).is_ok());
    ASSERT_TRUE(cam.start().is_ok());
    std::size_t k = 0;
    for (int i = 0; i <= 100; ++i) {
      FrameHandle f;
      ASSERT_EQ(cam.acquire(f, 0), AcquireStatus::kFrame);
      if (i != 10 && i != 100) continue;
      EXPECT_EQ(fnv1a(f->gray), e.hashes[k]) << e.scenario << " frame " << i << " gray";
      EXPECT_EQ(fnv1a(f->depth), e.hashes[k + 1]) << e.scenario << " frame " << i << " depth";
      k += 2;
    }
  }
}

TEST(SyntheticCamera, RepeatedPanelIsTheSameOnEveryCopy) {
  expect_identical_copies("room_repeated", room_repeated_options(), 3);
  expect_identical_copies("hall_repeated", hall_repeated_options(), 16);
  // The option works in the other scenes too: four copies, one on each wall of room_orbit.
  SyntheticOptions o = small_options();
  o.repeat_texture = 4;
  expect_identical_copies("room_orbit", o, 4);
}

TEST(SyntheticCamera, RepeatedPanelIsTheSameOnEveryCopyWithPhotos) {
  SKIP_WITHOUT_PHOTOS();
  SyntheticOptions room = room_repeated_options();
  room.texture = "auto";
  expect_identical_copies("room_repeated", room, 3);
  SyntheticOptions hall = hall_repeated_options();
  hall.texture = "auto";
  expect_identical_copies("hall_repeated", hall, 16);
}

TEST(SyntheticCamera, RepeatedPanelsHangWhereTheScenariosSay) {
  // room_repeated: A on the -x wall, B on the +x wall (8 m apart), C on the -y wall, centred;
  // every other box wears the panel, and no box stands in front of a copy.
  SyntheticCamera room("room_repeated", room_repeated_options(), false);
  ASSERT_TRUE(room.open(2).is_ok());
  ASSERT_EQ(room.panels().size(), 3U);
  EXPECT_EQ(room.panels()[0].wall, 0);
  EXPECT_EQ(room.panels()[1].wall, 1);
  EXPECT_EQ(room.panels()[2].wall, 2);
  for (const WallPanel& p : room.panels()) {
    EXPECT_NEAR(0.5 * (p.u0 + p.u1), 0.0, 1e-6);
    EXPECT_NEAR(p.u1 - p.u0, 2.0, 1e-6);
    EXPECT_GT(p.v0, 0.5);
    EXPECT_LT(p.v1, 2.6);
  }
  ASSERT_GE(room.boxes().size(), 4U);
  int wearing = 0;
  for (std::size_t b = 0; b < room.boxes().size(); ++b) {
    const SceneBox& box = room.boxes()[b];
    wearing += box.texture == kPanelTexture ? 1 : 0;
    EXPECT_EQ(box.texture == kPanelTexture, b % 2 == 1) << "box " << b;
    // Not between a copy and the room's centre line.
    EXPECT_FALSE(box.lo.y() < 1.3 && box.hi.y() > -1.3 && (box.lo.x() < -0.5 || box.hi.x() > 0.5))
        << "box " << b << " stands in front of A or B";
    EXPECT_FALSE(box.lo.x() < 1.3 && box.hi.x() > -1.3 && box.lo.y() < 0.0)
        << "box " << b << " stands in front of C";
  }
  EXPECT_GE(wearing, 2);
  // hall_repeated: 8 copies on each long wall, every 5 m.
  SyntheticCamera hall("hall_repeated", hall_repeated_options(), false);
  ASSERT_TRUE(hall.open(2).is_ok());
  ASSERT_EQ(hall.panels().size(), 16U);
  for (std::size_t k = 0; k < 16; ++k) {
    const WallPanel& p = hall.panels()[k];
    EXPECT_EQ(p.wall, k < 8 ? 2 : 3);
    EXPECT_NEAR(0.5 * (p.u0 + p.u1), -17.5 + 5.0 * static_cast<double>(k % 8), 1e-5);
    EXPECT_NEAR(p.u1 - p.u0, 3.0, 1e-6);
  }
  // Off by default: no copies, no box wears the panel.
  SyntheticCamera plain("room_repeated", procedural_options(), false);
  ASSERT_TRUE(plain.open(2).is_ok());
  EXPECT_TRUE(plain.panels().empty());
  for (const SceneBox& box : plain.boxes()) EXPECT_NE(box.texture, kPanelTexture);
}

TEST(SyntheticCamera, RoomRepeatedMapsBothCopiesThenBlacksOutFacingAWithoutAJump) {
  const SyntheticOptions o = room_repeated_options();
  SyntheticCamera cam("room_repeated", o, false);
  ASSERT_TRUE(cam.open(2).is_ok());
  ASSERT_TRUE(cam.start().is_ok());
  const Eigen::Vector3d a_centre(cam.room_lo().x(), 0.0, 1.4);
  const Eigen::Vector3d b_centre(cam.room_hi().x(), 0.0, 1.4);
  std::vector<SE3d> poses;
  std::vector<int> black;
  bool saw_a = false;
  bool saw_b = false;
  for (int i = 0; i < o.num_frames; ++i) {
    FrameHandle f;
    ASSERT_EQ(cam.acquire(f, 0), AcquireStatus::kFrame);
    poses.push_back(f->T_w_c_gt);
    const Eigen::Vector3d axis = f->T_w_c_gt.linear().col(2);
    if (!f->has_ground_truth) {
      black.push_back(i);
      EXPECT_EQ(cv::countNonZero(f->gray), 0) << "frame " << i;
    } else if (static_cast<double>(f->t_ns) * 1e-9 < o.kidnap_start_s) {
      saw_a = saw_a || axis.x() < -0.97;
      saw_b = saw_b || axis.x() > 0.97;
    }
  }
  // Both copies mapped before; black for 4 frames (3-5), at 19 s.
  EXPECT_TRUE(saw_a);
  EXPECT_TRUE(saw_b);
  ASSERT_EQ(black.size(), 4U);
  EXPECT_EQ(black.front(), 571);
  EXPECT_EQ(black.back(), 574);
  // The ground truth moves on through the blackout like a slow walk: no step larger than a
  // walking frame's (3 cm, 2 degrees), none at the blackout larger than twice the largest of
  // the second before it.
  double before_t = 0.0;
  double before_r = 0.0;
  for (int i = 1; i < o.num_frames; ++i) {
    const double dt = (poses[i].translation() - poses[i - 1].translation()).norm();
    const double dr = Eigen::Quaterniond(poses[i].linear())
                          .angularDistance(Eigen::Quaterniond(poses[i - 1].linear()));
    EXPECT_LT(dt, 0.03) << "frame " << i;
    EXPECT_LT(dr * 180.0 / kPi, 2.0) << "frame " << i;
    if (i >= 541 && i < 571) {
      before_t = std::max(before_t, dt);
      before_r = std::max(before_r, dr);
    }
    if (i >= 571 && i <= 575) {
      EXPECT_LT(dt, 2.0 * before_t) << "frame " << i;
      EXPECT_LT(dr, 2.0 * before_r) << "frame " << i;
      EXPECT_GT(dt, 0.0) << "frame " << i << ": the camera keeps moving";
    }
  }
  // Facing A from the lap's end through the blackout and 3 s after it; B is metres behind.
  for (int i = 545; i < 660; ++i) {
    const SE3d& T = poses[static_cast<std::size_t>(i)];
    EXPECT_LT(T.linear().col(2).x(), -0.9) << "frame " << i;
    EXPECT_GT((b_centre - T.translation()).norm(), 4.0);
    EXPECT_LT((a_centre - T.translation()).norm(), 3.5);
  }
  // Then it walks elsewhere: the +y half, facing the +y wall.
  const SE3d& last = poses.back();
  EXPECT_GT(last.translation().y(), 1.0);
  EXPECT_GT(last.linear().col(2).y(), 0.8);
  // A kidnap_start_s too early for the lap is refused, naming the option.
  SyntheticOptions early = o;
  early.kidnap_start_s = 4.0;
  SyntheticCamera bad("room_repeated", early, false);
  const Status s = bad.open(2);
  EXPECT_FALSE(s.is_ok());
  EXPECT_NE(s.message().find("kidnap_start_s"), std::string::npos) << s.message();
}

TEST(SyntheticCamera, HallRepeatedDrivesALoopBackThroughItsStart) {
  const SyntheticOptions o = hall_repeated_options();
  SyntheticCamera cam("hall_repeated", o, false);
  ASSERT_TRUE(cam.open(2).is_ok());
  const double lap = 2.0 * 20.0 + 2.0 * kPi * 6.0;  // straights of 20 m, turns of 6 m radius
  const double lap_s = lap / o.drive_speed_mps;
  double length = 0.0;
  double turned = 0.0;
  const SE3d start = cam.sample_at(0.0).T_w_c;
  for (int i = 1; i < o.num_frames; ++i) {
    const SE3d a = cam.sample_at((i - 1) / o.fps).T_w_c;
    const SE3d b = cam.sample_at(i / o.fps).T_w_c;
    const Eigen::Vector3d c = b.translation();
    EXPECT_NEAR(c.z(), 1.65, 0.03);
    EXPECT_NEAR((c - a.translation()).head<2>().norm() * o.fps, o.drive_speed_mps, 0.05);
    EXPECT_TRUE((c.head<2>().array() > cam.room_lo().head<2>().array() + 3.9).all() &&
                (c.head<2>().array() < cam.room_hi().head<2>().array() - 3.9).all())
        << "frame " << i;
    for (const auto& box : cam.boxes()) {
      const double gx = std::max({0.0, box.lo.x() - c.x(), c.x() - box.hi.x()});
      const double gy = std::max({0.0, box.lo.y() - c.y(), c.y() - box.hi.y()});
      EXPECT_GE(std::hypot(gx, gy), 2.9);
    }
    if (i / o.fps <= lap_s) {
      turned += std::remainder(heading_of(b) - heading_of(a), 2.0 * kPi);
      length += (c - a.translation()).head<2>().norm();
    }
  }
  EXPECT_NEAR(length, lap, 0.03 * lap);
  EXPECT_NEAR(turned, 2.0 * kPi, 0.05) << "one full turn to the left";
  // Looks 35 degrees right of its travel: at the near long wall, from 4 m.
  EXPECT_NEAR(heading_of(start), -35.0 * kPi / 180.0, 0.03);
  EXPECT_NEAR(start.translation().y(), cam.room_lo().y() + 4.0, 0.01);
  // A true loop: after the lap it passes the start again, looking the same way, and drives
  // on over the first metres (the sequence ends 40 s in).
  const SE3d again = cam.sample_at(lap_s).T_w_c;
  EXPECT_LT((again.translation() - start.translation()).head<2>().norm(), 1e-6);
  EXPECT_LT(std::abs(std::remainder(heading_of(again) - heading_of(start), 2.0 * kPi)), 0.03);
  EXPECT_GT(o.num_frames / o.fps - lap_s, 3.0);
  // The far end is a 180 degree turn: half-way round the lap it heads -x on the +y side.
  const SE3d half = cam.sample_at(0.5 * lap_s).T_w_c;
  EXPECT_NEAR(half.translation().y(), cam.room_hi().y() - 4.0, 0.01);
  // A hall wider than long is refused, naming the options.
  SyntheticOptions square = o;
  square.hall_size_x = 30.0;
  square.hall_size_y = 30.0;
  SyntheticCamera bad("hall_repeated", square, false);
  const Status s = bad.open(2);
  EXPECT_FALSE(s.is_ok());
  EXPECT_NE(s.message().find("hall_size_x"), std::string::npos) << s.message();
}

TEST(SyntheticCamera, RepeatedScenariosAreDeterministicAndAllocationFree) {
  for (const bool hall : {false, true}) {
    const char* scenario = hall ? "hall_repeated" : "room_repeated";
    auto run = [&](int seed, std::vector<std::uint64_t>& hashes) {
      SyntheticOptions o = hall ? hall_repeated_options() : room_repeated_options();
      o.width = 160;
      o.height = 120;
      o.seed = seed;
      o.exposure_time_s = 0.01;
      o.exposure_step_every_s = 0.2;
      SyntheticCamera cam(scenario, o, false);
      ASSERT_TRUE(cam.open(2).is_ok());
      ASSERT_TRUE(cam.start().is_ok());
      for (int i = 0; i < 6; ++i) {
        FrameHandle f;
        const auto before = platform::alloc::thread_allocations();
        ASSERT_EQ(cam.acquire(f, 0), AcquireStatus::kFrame);
        const std::uint64_t h = fnv1a(f->gray);  // reads the pool buffer: no allocation
        const std::uint64_t d = fnv1a(f->depth);
        f.reset();
        if (i > 0) {
          EXPECT_EQ(platform::alloc::thread_allocations() - before, 0U)
              << scenario << " frame " << i;
        }
        hashes.push_back(h);
        hashes.push_back(d);
      }
    };
    std::vector<std::uint64_t> a;
    std::vector<std::uint64_t> b;
    std::vector<std::uint64_t> c;
    run(1, a);
    run(1, b);
    run(2, c);
    EXPECT_EQ(a, b) << scenario << ": same seed, same images";
    EXPECT_NE(a[10], c[10]) << scenario << ": another seed, other images";
  }
}

}  // namespace
}  // namespace mer::hal
