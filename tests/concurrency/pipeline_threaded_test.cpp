// The threaded pipeline under load: capture never blocks, drop-oldest keeps the newest
// frames, every frame is accounted for, and every buffer returns to the pool; and the map
// written by the depth thread (keyframe builder), the back-end thread (local BA, culling
// with slot reuse) and the loop thread while the tracker reads it. Runs under TSan in CI (label
// 'concurrency').
#include <unistd.h>

#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "hal/synthetic/synthetic_camera.h"
#include "pipeline/pipeline.h"

#if defined(__SANITIZE_THREAD__)
#define MER_TEST_TSAN 1
#elif defined(__has_feature)
#if __has_feature(thread_sanitizer)
#define MER_TEST_TSAN 1
#endif
#endif

namespace mer::pipeline {
namespace {

#ifdef MER_TEST_TSAN
constexpr bool kTsan = true;
#else
constexpr bool kTsan = false;
#endif

std::vector<std::uint64_t> read_seqs(const std::filesystem::path& frames_csv) {
  std::ifstream f(frames_csv);
  std::vector<std::uint64_t> seqs;
  std::string line;
  std::getline(f, line);  // header
  while (std::getline(f, line)) seqs.push_back(std::stoull(line.substr(0, line.find(','))));
  return seqs;
}

struct RunResult {
  PipelineStats stats;
  std::vector<std::uint64_t> seqs;
  std::size_t pool_available = 0;
  std::size_t pool_capacity = 0;
};

RunResult run_threaded(const std::string& name, int frames, double fps, int busy_us,
                       void (*configure)(PipelineConfig&) = nullptr) {
  // Per process: two instances of this binary may run at once (ctest -j, stress loops).
  const auto dir =
      std::filesystem::temp_directory_path() / (name + "_" + std::to_string(::getpid()));
  std::filesystem::remove_all(dir);
  std::filesystem::create_directories(dir);
  hal::SyntheticOptions so;
  so.width = 160;
  so.height = 120;
  so.num_frames = frames;
  so.fps = fps;
  hal::SyntheticCamera cam("room_orbit", so, /*paced=*/true);
  EXPECT_TRUE(cam.open(8).is_ok());
  PipelineConfig pc;
  pc.tracking.busy_work_us = busy_us;
  pc.tracking.extractor.num_levels = 3;  // 160x120: a small pyramid
  pc.tracking.extractor.num_features = 300;
  pc.map.max_keyframes = 64;
  pc.map.max_points = 20000;
  // A busy-waiting tracker must not monopolize a core of a shared 2-core test machine.
  if (busy_us > 0) pc.board.tracking_priority = 0;
  // Under TSan every stage thread runs with normal scheduling: the TSan runtime guards its
  // allocator with spin locks that wait with sched_yield, which never lets a lower-priority
  // SCHED_FIFO thread run. With three FIFO threads on two cores (capture, tracking, back end)
  // the capture and tracking threads spun forever on a lock the allocating back end held.
  // Races do not depend on the priorities; the real-time placement is tested without TSan.
  if (kTsan) {
    pc.board.capture_priority = 0;
    pc.board.tracking_priority = 0;
    pc.board.backend_priority = 0;
  }
  if (configure != nullptr) configure(pc);
  std::atomic<bool> stop{false};
  RunResult run;
  {
    Pipeline p(pc, cam, stop);
    EXPECT_TRUE(p.init(dir.string()).is_ok());
    const Status s = p.run();
    EXPECT_TRUE(s.is_ok()) << s.message();
    run.stats = p.stats();
  }
  run.seqs = read_seqs(dir / "frames.csv");
  run.pool_available = cam.pool().available_approx();
  run.pool_capacity = cam.pool().capacity();
  std::filesystem::remove_all(dir);
  return run;
}

TEST(PipelineThreaded, SlowTrackingDropsOldestAndAccountsForEveryFrame) {
  // Camera at 200 fps (5 ms), tracking >= 20 ms per frame: most frames must be dropped.
  const RunResult r = run_threaded("mer_threaded_drop", 120, 200.0, 20'000);
  const PipelineStats& s = r.stats;
  EXPECT_EQ(s.frames_in, 120U);
  EXPECT_GT(s.frames_dropped, 30U);
  EXPECT_EQ(s.frames_processed + s.frames_dropped, s.frames_in);
  EXPECT_EQ(s.output_overflows, 0U);
  ASSERT_EQ(r.seqs.size(), s.frames_processed);
  for (std::size_t i = 1; i < r.seqs.size(); ++i) {
    EXPECT_LT(r.seqs[i - 1], r.seqs[i]) << "frames must reach tracking in order";
  }
  // Drop-oldest: the last frame of the stream is never the one dropped.
  EXPECT_EQ(r.seqs.back(), 119U);
  EXPECT_EQ(r.pool_available, r.pool_capacity) << "every frame buffer returns to the pool";
}

TEST(PipelineThreaded, CameraRateRunAccountsForEveryFrame) {
  const RunResult r = run_threaded("mer_threaded_nodrop", 60, 60.0, 0);
  EXPECT_EQ(r.stats.frames_in, 60U);
  EXPECT_EQ(r.stats.frames_processed + r.stats.frames_dropped, 60U);
  EXPECT_EQ(r.seqs.size(), r.stats.frames_processed);
  EXPECT_EQ(r.pool_available, r.pool_capacity);
  ASSERT_EQ(r.stats.threads.size(), 6U);  // capture, tracking, output, depth, backend, loop
  EXPECT_EQ(r.stats.threads[4].thread, "mer_backend");
  EXPECT_EQ(r.stats.threads.back().thread, "mer_loop");
  // CPU: each stage thread's own clock; together no more than the process's, and the capture
  // thread's holds the source's rendering.
  const CpuStats& c = r.stats.cpu;
  EXPECT_EQ(c.process.count, r.stats.frames_processed);
  double threads_s = 0.0;
  for (const ThreadPlacement& t : r.stats.threads) {
    EXPECT_GE(t.cpu_s, 0.0) << t.thread;
    threads_s += t.cpu_s;
  }
  EXPECT_GT(r.stats.threads[0].cpu_s, 0.0) << "capture";
  EXPECT_GT(r.stats.threads[1].cpu_s, 0.0) << "tracking";
  EXPECT_GE(r.stats.threads[0].cpu_s * 1.0001, c.source_s);
  EXPECT_GT(c.source_s, 0.0);
  EXPECT_LE(threads_s, c.process_s * 1.0001 + 0.01);
}

// Keyframes, local BA and culling on their own threads: RGB-D mode maps from the first frame;
// a map of 12 keyframe slots fills after ~11 keyframes, so culling removes keyframes and
// the builder reuses their slots while the tracker reads the map and the back end optimizes.
// (~40 keyframes when the machine keeps up; fewer under TSan on a loaded machine.)
TEST(PipelineThreaded, KeyframesLocalBaAndCullingOnTheirThreads) {
  const RunResult r = run_threaded("mer_threaded_backend", 150, 30.0, 0, [](PipelineConfig& pc) {
    pc.pipeline.mode = SensorMode::kRgbd;
    pc.map.max_keyframes = 12;
    pc.culling.point_min_observations = 2;  // culls young points seen once
    // A keyframe every ~3 frames and long BA runs: the builder inserts while a BA solves
    // (pre-emption, write-back after concurrent insertions, queued keyframes coalesced).
    pc.tracking.keyframe.min_spacing_s = 0.05;
    pc.tracking.keyframe.max_spacing_s = 0.1;
    pc.backend.max_iterations = 50;
    pc.backend.window_keyframes = 10;
    // Keypoint alignment moves keypoints of published keyframes (writer-side data read by
    // the BA and culling under the writer lock, while the tracker reads keypoint counts).
    pc.depth.align_keypoints = true;
  });
  const PipelineStats& s = r.stats;
  std::printf(
      "frames %llu processed, %llu lost; keyframes %llu; local BA %llu runs (%llu aborted, %llu "
      "coalesced, %llu stale writes); culling %llu runs, %llu keyframes; %llu slots reused\n",
      static_cast<unsigned long long>(s.frames_processed),
      static_cast<unsigned long long>(s.frames_lost),
      static_cast<unsigned long long>(s.mapping.keyframes),
      static_cast<unsigned long long>(s.backend.runs),
      static_cast<unsigned long long>(s.backend.aborted),
      static_cast<unsigned long long>(s.backend_coalesced),
      static_cast<unsigned long long>(s.backend.stale_writes),
      static_cast<unsigned long long>(s.culling.runs),
      static_cast<unsigned long long>(s.culling.culled_keyframes),
      static_cast<unsigned long long>(s.map.reused_keyframe_slots));
  EXPECT_EQ(s.frames_processed + s.frames_dropped, s.frames_in);
  EXPECT_EQ(r.pool_available, r.pool_capacity);
  EXPECT_GE(s.mapping.keyframes, 14U) << "keyframes created";
  EXPECT_GT(s.backend.runs, 0U) << "local BA ran on the back-end thread";
  EXPECT_GT(s.mapping.aligned_keypoints, 0U) << "keypoints aligned while the BA ran";
  // One run per inserted keyframe at most (older ones queued behind a newer are coalesced).
  EXPECT_LE(s.backend.runs + s.backend_coalesced, s.mapping.keyframes);
  EXPECT_GT(s.culling.runs, 0U);
  EXPECT_GT(s.culling.culled_keyframes, 0U) << "capacity rule";
  EXPECT_GT(s.map.reused_keyframe_slots, 0U) << "slots freed by the back end reused by the builder";
  EXPECT_LE(s.map.live_keyframes, 12U);
  // RGB-D maps from the first frame and the camera orbits a textured room: nearly every frame
  // is tracked (0 lost when measured, threaded and under TSan on a loaded machine); culling
  // or slot reuse that broke the tracker's map would lose many.
  EXPECT_GT(s.frames_processed, 0U);
  EXPECT_LE(s.frames_lost * 10, s.frames_processed) << "at most 10 % of the frames lost";
  ASSERT_EQ(s.threads.size(), 6U);
}

// Loop closure on the back-end thread while tracking reads the map: a whole orbit in RGB-D,
// so the camera comes back to its start; the loop closer searches at every keyframe, and
// when it closes the loop it moves keyframes and points under the writer lock and publishes
// the correction the tracker follows at its next frame.
TEST(PipelineThreaded, LoopClosureRunsBesideTracking) {
  const RunResult r = run_threaded("mer_threaded_loop", 400, 20.0, 0, [](PipelineConfig& pc) {
    pc.pipeline.mode = SensorMode::kRgbd;
    pc.loop.min_keyframe_gap = 10;
  });
  const PipelineStats& s = r.stats;
  std::printf(
      "frames %llu processed, %llu dropped, %llu lost; keyframes %llu; loop: %llu "
      "searches, %llu candidates, %llu closed\n",
      static_cast<unsigned long long>(s.frames_processed),
      static_cast<unsigned long long>(s.frames_dropped),
      static_cast<unsigned long long>(s.frames_lost),
      static_cast<unsigned long long>(s.mapping.keyframes),
      static_cast<unsigned long long>(s.loop.keyframes_checked),
      static_cast<unsigned long long>(s.loop.candidates_checked),
      static_cast<unsigned long long>(s.loop.loops_closed));
  EXPECT_EQ(s.frames_processed + s.frames_dropped, s.frames_in);
  EXPECT_EQ(r.pool_available, r.pool_capacity);
  EXPECT_GT(s.loop.keyframes_checked, 0U) << "the loop closer ran";
  // On its own thread, beside the back end's local BA (which it must not hold up).
  const bool loop_thread =
      std::any_of(s.threads.begin(), s.threads.end(),
                  [](const ThreadPlacement& t) { return t.thread == "mer_loop"; });
  EXPECT_TRUE(loop_thread) << "no mer_loop thread was started";
  std::printf("loop queue full: %llu keyframes not searched\n",
              static_cast<unsigned long long>(s.loop_queue_full));
  // The orbit comes back to its start: the loop is found and closed (7-9 closures when
  // measured), and the tracker keeps following the corrected map. Lost frames measured: 0 of
  // 400 threaded, 28 of 223 under TSan on a loaded machine (177 frames dropped, so larger
  // steps between the frames tracked); a tracker that stopped following the corrections
  // would lose every frame after the first closure, about half of the run.
  EXPECT_GE(s.loop.loops_closed, 1U) << "the revisit closes a loop";
  EXPECT_GT(s.frames_processed, 0U);
  EXPECT_LE(s.frames_lost * 4, s.frames_processed) << "at most 25 % of the frames lost";
}

}  // namespace
}  // namespace mer::pipeline
