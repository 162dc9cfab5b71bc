// ReplayCamera: the real KITTI clips end to end, pacing, lockstep without drops, skips and
// errors, zero allocations in acquire(), prompt stop().
#include "hal/replay/replay_camera.h"

#include <chrono>
#include <fstream>
#include <thread>

#include <gtest/gtest.h>

#include "hal/replay/kitti_loader.h"
#include "platform/alloc_counter.h"
#include "platform/clock.h"
#include "replay_fixtures.h"
#include "support/required_data.h"

namespace mer::hal {
namespace {

constexpr std::int64_t kSecond = 1'000'000'000;
constexpr std::int64_t kMs = 1'000'000;

bool has(const std::string& text, const std::string& part) {
  return text.find(part) != std::string::npos;
}

std::unique_ptr<CameraSource> make_kitti_camera(const std::string& dir, bool paced,
                                                ReplayOptions opts = {}) {
  auto cam = make_replay_camera("kitti", dir, opts, CalibrationOptions{}, false, paced);
  EXPECT_TRUE(cam.is_ok()) << cam.status().message();
  return cam.is_ok() ? std::move(cam.value()) : nullptr;
}

// Writes a KITTI fixture whose times.txt runs at `hz`.
void make_kitti_at(const std::string& dir, int n, double hz) {
  test::make_kitti(dir, n, 32, 24, 0);
  std::string times;
  for (int i = 0; i < n; ++i) times += std::to_string(i / hz) + "\n";
  test::write_file(dir + "/times.txt", times);
}

struct Clip {
  const char* name;
  int width;
  int height;
  double fx;
  double cx;
  double cy;
  std::size_t poses;
};

TEST(ReplayCamera, ReplaysTheSharedKittiClips) {
  const std::string data = test::shared_data_dir();
  MER_REQUIRE_DATA(!data.empty()) << "../shared/data not found (set MER_SHARED_DIR)";
  // Note: kitti_clip1/poses.txt holds 51 poses, not 50 as its README says: its last line
  // has no trailing newline (so `wc -l` counts 50), and groundtruth.txt has the same 51st
  // pose (t = 5.0). Dropping an unterminated last line would be a silent wrong answer.
  // The "fewer poses than images" case is ClipWithFewerPosesThanImages below.
  const Clip clips[] = {{"kitti_clip1", 1226, 370, 707.0912, 601.8873, 183.1104, 51},
                        {"kitti_clip2", 1241, 376, 718.856, 607.1928, 185.2157, 51}};
  for (const Clip& c : clips) {
    SCOPED_TRACE(c.name);
    auto cam = make_kitti_camera(data + "/" + c.name, false);
    ASSERT_TRUE(cam);
    ASSERT_TRUE(cam->open(8).is_ok());
    const CameraIntrinsics& k = cam->intrinsics();
    EXPECT_EQ(k.width, c.width);
    EXPECT_EQ(k.height, c.height);
    EXPECT_DOUBLE_EQ(k.fx, c.fx);
    EXPECT_DOUBLE_EQ(k.fy, c.fx);
    EXPECT_DOUBLE_EQ(k.cx, c.cx);
    EXPECT_DOUBLE_EQ(k.cy, c.cy);
    const CameraCapabilities caps = cam->capabilities();
    EXPECT_FALSE(caps.live);
    EXPECT_FALSE(caps.has_depth);
    EXPECT_TRUE(caps.has_ground_truth);
    EXPECT_NEAR(caps.nominal_fps, 10.0, 1e-6);
    const auto& replay = dynamic_cast<const ReplayCamera&>(*cam);
    EXPECT_EQ(replay.loader().ground_truth().poses.size(), c.poses);
    ASSERT_TRUE(cam->start().is_ok());
    std::int64_t prev_t = -1;
    std::uint64_t n = 0;
    for (;; ++n) {
      FrameHandle f;
      const AcquireStatus st = cam->acquire(f, 5 * kSecond);
      if (st == AcquireStatus::kEndOfStream) break;
      ASSERT_EQ(st, AcquireStatus::kFrame) << cam->last_error().message();
      EXPECT_EQ(f->seq, n);
      EXPECT_GT(f->t_ns, prev_t) << "timestamps strictly increasing";
      prev_t = f->t_ns;
      EXPECT_EQ(f->gray.cols, c.width);
      EXPECT_EQ(f->gray.rows, c.height);
      EXPECT_EQ(f->has_ground_truth, n < c.poses) << "frame " << n;
      EXPECT_GT(f->produce_ns, 0);
      EXPECT_GT(f->t_ready_ns, 0);
      if (n == 1 && c.width == 1226) {  // clip1 poses.txt line 2: t = (-1.401751e-02, ..)
        EXPECT_NEAR(f->T_w_c_gt.translation().x(), -1.401751e-02, 1e-9);
        EXPECT_NEAR(f->T_w_c_gt.translation().z(), 1.198998, 1e-9);
      }
      if (n == 50 && c.width == 1226) {  // the unterminated last line of clip1 poses.txt
        EXPECT_NEAR(f->T_w_c_gt.translation().x(), -9.814360e-01, 1e-9);
        EXPECT_NEAR(f->T_w_c_gt.translation().z(), 5.983857e+01, 1e-9);
      }
      EXPECT_GT(cv::mean(f->gray)[0], 10.0) << "a real image, not an empty buffer";
    }
    EXPECT_EQ(n, 51U);
    EXPECT_EQ(prev_t, 5 * kSecond);
    EXPECT_EQ(replay.skipped(), 0U);
    FrameHandle f;
    EXPECT_EQ(cam->acquire(f, 0), AcquireStatus::kEndOfStream) << "end of stream is sticky";
    cam->stop();
  }
}

// The real clip with its last pose removed: 51 images, 50 poses; frame 50 has none.
TEST(ReplayCamera, ClipWithFewerPosesThanImages) {
  const std::string data = test::shared_data_dir();
  MER_REQUIRE_DATA(!data.empty()) << "../shared/data not found (set MER_SHARED_DIR)";
  test::TempDir dir;
  const std::string clip = data + "/kitti_clip1";
  std::filesystem::create_symlink(clip + "/image_0", dir / "image_0");
  std::filesystem::copy_file(clip + "/calib.txt", dir / "calib.txt");
  std::filesystem::copy_file(clip + "/times.txt", dir / "times.txt");
  std::ifstream in(clip + "/poses.txt");
  std::string line;
  std::string first50;
  for (int i = 0; i < 50 && std::getline(in, line); ++i) first50 += line + "\n";
  test::write_file(dir / "poses.txt", first50);
  auto cam = make_kitti_camera(dir.path(), false);
  ASSERT_TRUE(cam->open(8).is_ok());
  ASSERT_TRUE(cam->start().is_ok());
  std::uint64_t n = 0;
  for (;; ++n) {
    FrameHandle f;
    const AcquireStatus st = cam->acquire(f, 5 * kSecond);
    if (st == AcquireStatus::kEndOfStream) break;
    ASSERT_EQ(st, AcquireStatus::kFrame);
    EXPECT_EQ(f->has_ground_truth, n < 50) << "frame " << n;
  }
  EXPECT_EQ(n, 51U);
}

TEST(ReplayCamera, PacedReplayFollowsTheRecordedRate) {
  test::TempDir dir;
  make_kitti_at(dir.path(), 10, 20.0);
  auto cam = make_kitti_camera(dir.path(), true);
  ASSERT_TRUE(cam->open(8).is_ok());
  EXPECT_TRUE(cam->capabilities().live);
  const std::int64_t t0 = platform::monotonic_now_ns();
  ASSERT_TRUE(cam->start().is_ok());
  int frames = 0;
  int timeouts = 0;
  for (;;) {
    FrameHandle f;
    const AcquireStatus st = cam->acquire(f, 20 * kMs);  // shorter than the 50 ms period
    if (st == AcquireStatus::kEndOfStream) break;
    if (st == AcquireStatus::kTimeout) {
      ++timeouts;
      continue;
    }
    ASSERT_EQ(st, AcquireStatus::kFrame);
    // Frame i is released no earlier than start() + i * 50 ms (t_first = 0).
    EXPECT_GE(f->t_ready_ns - t0, f->t_ns) << "frame " << f->seq;
    ++frames;
  }
  const std::int64_t elapsed = platform::monotonic_now_ns() - t0;
  EXPECT_EQ(frames, 10);
  EXPECT_GE(elapsed, 400 * kMs) << "10 frames at 20 Hz span 450 ms";
  EXPECT_LT(elapsed, 2 * kSecond);
  EXPECT_GT(timeouts, 0) << "frames not due within the timeout give kTimeout";
}

TEST(ReplayCamera, LockstepNeverDropsEvenWithASlowConsumer) {
  test::TempDir dir;
  make_kitti_at(dir.path(), 30, 1000.0);
  ReplayOptions opts;
  opts.prefetch = 2;
  auto cam = make_kitti_camera(dir.path(), false, opts);
  ASSERT_TRUE(cam->open(3).is_ok());
  ASSERT_TRUE(cam->start().is_ok());
  std::uint64_t expected = 0;
  for (;;) {
    FrameHandle f;
    const AcquireStatus st = cam->acquire(f, 5 * kSecond);
    if (st == AcquireStatus::kEndOfStream) break;
    ASSERT_EQ(st, AcquireStatus::kFrame);
    EXPECT_EQ(f->seq, expected++);
    std::this_thread::sleep_for(std::chrono::milliseconds(3));
  }
  EXPECT_EQ(expected, 30U);
}

TEST(ReplayCamera, AcquireDoesNotAllocateInSteadyState) {
  ASSERT_TRUE(platform::alloc::counter_linked());
  test::TempDir dir;
  make_kitti_at(dir.path(), 40, 1000.0);
  auto cam = make_kitti_camera(dir.path(), false);
  ASSERT_TRUE(cam->open(8).is_ok());
  ASSERT_TRUE(cam->start().is_ok());
  std::uint64_t allocs = 0;
  int frames = 0;
  for (;;) {
    FrameHandle f;
    const std::uint64_t before = platform::alloc::thread_allocations();
    const AcquireStatus st = cam->acquire(f, 5 * kSecond);
    const std::uint64_t delta = platform::alloc::thread_allocations() - before;
    if (st == AcquireStatus::kEndOfStream) break;
    ASSERT_EQ(st, AcquireStatus::kFrame);
    if (++frames > 3) allocs += delta;  // after warm-up
  }
  EXPECT_EQ(frames, 40);
  EXPECT_EQ(allocs, 0U);
}

TEST(ReplayCamera, SkipsAreCountedAndTheStreamGoesOn) {
  test::TempDir dir;
  make_kitti_at(dir.path(), 6, 100.0);
  std::filesystem::remove(dir / "image_0/000002.png");
  test::write_file(dir / "image_0/000004.png", "garbage");
  auto cam = make_kitti_camera(dir.path(), false);
  ASSERT_TRUE(cam->open(8).is_ok());
  ASSERT_TRUE(cam->start().is_ok());
  std::vector<std::uint64_t> seqs;
  for (;;) {
    FrameHandle f;
    const AcquireStatus st = cam->acquire(f, 5 * kSecond);
    if (st == AcquireStatus::kEndOfStream) break;
    ASSERT_EQ(st, AcquireStatus::kFrame);
    seqs.push_back(f->seq);
  }
  EXPECT_EQ(seqs, (std::vector<std::uint64_t>{0, 1, 3, 5}));
  EXPECT_EQ(dynamic_cast<ReplayCamera&>(*cam).skipped(), 2U);
  EXPECT_TRUE(cam->last_error().is_ok());
}

TEST(ReplayCamera, TooManyConsecutiveSkipsIsAnError) {
  test::TempDir dir;
  make_kitti_at(dir.path(), 8, 100.0);
  for (int i = 2; i < 6; ++i) {
    std::filesystem::remove(dir / ("image_0/00000" + std::to_string(i) + ".png"));
  }
  ReplayOptions opts;
  opts.max_consecutive_skips = 3;
  auto cam = make_kitti_camera(dir.path(), false, opts);
  ASSERT_TRUE(cam->open(8).is_ok());
  ASSERT_TRUE(cam->start().is_ok());
  FrameHandle f;
  ASSERT_EQ(cam->acquire(f, 5 * kSecond), AcquireStatus::kFrame);
  ASSERT_EQ(cam->acquire(f, 5 * kSecond), AcquireStatus::kFrame);
  EXPECT_TRUE(cam->last_error().is_ok());
  EXPECT_EQ(cam->acquire(f, 5 * kSecond), AcquireStatus::kError);
  const std::string msg = cam->last_error().message();
  EXPECT_TRUE(has(msg, "4 unusable frames in a row")) << msg;
  EXPECT_TRUE(has(msg, "max_consecutive_skips")) << msg;
  EXPECT_TRUE(has(msg, dir / "image_0/000005.png")) << msg;
  EXPECT_EQ(cam->acquire(f, 0), AcquireStatus::kError) << "the error is sticky";
}

TEST(ReplayCamera, StopIsPromptWhileThePrefetcherWaits) {
  test::TempDir dir;
  make_kitti_at(dir.path(), 50, 1000.0);
  auto cam = make_kitti_camera(dir.path(), false);
  ASSERT_TRUE(cam->open(6).is_ok());
  ASSERT_TRUE(cam->start().is_ok());
  // Hold two frames; the prefetcher fills the rest of the pool and waits.
  FrameHandle a;
  FrameHandle b;
  ASSERT_EQ(cam->acquire(a, 5 * kSecond), AcquireStatus::kFrame);
  ASSERT_EQ(cam->acquire(b, 5 * kSecond), AcquireStatus::kFrame);
  std::this_thread::sleep_for(std::chrono::milliseconds(50));
  const std::int64_t t0 = platform::monotonic_now_ns();
  cam->stop();
  EXPECT_LT(platform::monotonic_now_ns() - t0, 500 * kMs);
  FrameHandle c;
  EXPECT_EQ(cam->acquire(c, 0), AcquireStatus::kEndOfStream);
  a.reset();
  b.reset();
  EXPECT_EQ(cam->pool().available_approx(), 6U) << "undelivered frames went back to the pool";
}

TEST(ReplayCamera, ConsumerHoldingEveryBufferGetsTimeoutsNotAHang) {
  test::TempDir dir;
  make_kitti_at(dir.path(), 10, 1000.0);
  ReplayOptions opts;
  opts.prefetch = 1;
  auto cam = make_kitti_camera(dir.path(), false, opts);
  ASSERT_TRUE(cam->open(2).is_ok());
  ASSERT_TRUE(cam->start().is_ok());
  FrameHandle a;
  FrameHandle b;
  ASSERT_EQ(cam->acquire(a, 5 * kSecond), AcquireStatus::kFrame);
  ASSERT_EQ(cam->acquire(b, 5 * kSecond), AcquireStatus::kFrame);
  FrameHandle c;
  EXPECT_EQ(cam->acquire(c, 20 * kMs), AcquireStatus::kTimeout);
  a.reset();
  ASSERT_EQ(cam->acquire(c, 5 * kSecond), AcquireStatus::kFrame);
  EXPECT_EQ(c->seq, 2U);
}

TEST(ReplayCamera, OptionsAndOpenErrors) {
  test::TempDir dir;
  make_kitti_at(dir.path(), 3, 10.0);
  {
    auto cam = make_kitti_camera(dir.path(), false);  // prefetch 4
    const Status s = cam->open(4);
    ASSERT_EQ(s.code(), StatusCode::kInvalidArgument);
    EXPECT_TRUE(has(s.message(), "camera.replay.prefetch")) << s.message();
  }
  {
    ReplayOptions opts;
    opts.prefetch = 0;
    auto cam = make_kitti_camera(dir.path(), false, opts);
    const Status s = cam->open(8);
    ASSERT_EQ(s.code(), StatusCode::kInvalidArgument);
    EXPECT_TRUE(has(s.message(), "camera.replay.prefetch")) << s.message();
  }
  {
    auto cam = make_kitti_camera(dir / "nope", false);
    const Status s = cam->open(8);
    EXPECT_EQ(s.code(), StatusCode::kInputError);
    EXPECT_EQ(cam->start().code(), StatusCode::kRuntimeError) << "start() after a failed open()";
    FrameHandle f;
    EXPECT_EQ(cam->acquire(f, 0), AcquireStatus::kEndOfStream);
  }
}

TEST(MakeReplayCamera, SchemesAndModes) {
  EXPECT_TRUE(make_replay_camera("tum", "/x", {}, {}, true, false).is_ok());
  EXPECT_TRUE(make_replay_camera("euroc", "/x", {}, {}, false, false).is_ok());
  auto rgbd = make_replay_camera("kitti", "/x", {}, {}, true, false);
  ASSERT_FALSE(rgbd.is_ok());
  EXPECT_EQ(rgbd.status().code(), StatusCode::kInvalidArgument);
  EXPECT_TRUE(has(rgbd.status().message(), "rgbd")) << rgbd.status().message();
  auto unknown = make_replay_camera("bag", "/x", {}, {}, false, false);
  ASSERT_FALSE(unknown.is_ok());
  EXPECT_TRUE(has(unknown.status().message(), "'bag'"));
}

TEST(ReplayOptions, ValidateAndPrint) {
  ReplayOptions o;
  EXPECT_TRUE(options::validate(o).is_ok());
  o.depth_scale = 0.0;
  EXPECT_FALSE(options::validate(o).is_ok());
  std::ostringstream os;
  ReplayOptions d;
  options::print(d, os);
  EXPECT_TRUE(has(os.str(), "prefetch: 4"));
  EXPECT_TRUE(has(os.str(), "max_consecutive_skips: 10"));
  EXPECT_TRUE(has(os.str(), "depth_scale: 5000.0"));
}

}  // namespace
}  // namespace mer::hal
