// The threaded pipeline under load: capture never blocks, drop-oldest keeps the newest
// frames, every frame is accounted for, and every buffer returns to the pool. Runs under
// TSan in CI (label 'concurrency').
#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "hal/synthetic/synthetic_camera.h"
#include "pipeline/pipeline.h"

namespace mer::pipeline {
namespace {

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

RunResult run_threaded(const std::string& name, int frames, double fps, int busy_us) {
  const auto dir = std::filesystem::temp_directory_path() / name;
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
  ASSERT_EQ(r.stats.threads.size(), 4U);  // capture, tracking, output, depth
}

}  // namespace
}  // namespace mer::pipeline
