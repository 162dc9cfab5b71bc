// mer_slam end to end through a kidnap: synthetic:room_kidnap goes black for 1 s (frames
// 421-450 with kidnap_start_s 14) and reappears where it was 6 s earlier. The relocalizer must
// find the camera in the map within 30 frames of it reappearing, in lockstep and threaded; with
// relocalization off the camera stays lost (the mechanism, not chance, brings it back).
// Frame k is at t = k / 30 s; black while 14 < t <= 15.
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#include <gtest/gtest.h>
#include <opencv2/core.hpp>

#include "support/run_command.h"

namespace mer {
namespace {

using testing::quote;
using testing::run_command;

const std::string kExe = MER_SLAM_EXE;
constexpr int kBlackFirst = 421;  // first black frame
constexpr int kBackAt = 451;      // first frame after the 1 s blackout
constexpr int kWithin = 30;       // frames the relocalizer may take
constexpr int kFrames = 540;

struct FrameRow {
  int seq = 0;
  std::string state;          // tracked / lost / not_initialized
  std::string reason;         // keyframe_reason
  std::string tracker_state;  // the state machine
};

std::vector<FrameRow> read_frames(const std::filesystem::path& dir) {
  std::vector<FrameRow> rows;
  std::ifstream in(dir / "frames.csv");
  std::string line;
  std::getline(in, line);  // header
  while (std::getline(in, line)) {
    std::vector<std::string> cols;
    std::stringstream ss(line);
    std::string c;
    while (std::getline(ss, c, ',')) cols.push_back(c);
    if (cols.size() < 15) continue;
    rows.push_back({std::stoi(cols[0]), cols[2], cols[11], cols[14]});
  }
  return rows;
}

std::filesystem::path run_kidnap(const std::string& name, bool reloc, bool lockstep) {
  const auto dir = std::filesystem::temp_directory_path() / name;
  std::filesystem::remove_all(dir);
  const auto cfg = std::filesystem::temp_directory_path() / (name + ".yaml");
  {
    std::ofstream f(cfg);
    f << "camera:\n  synthetic:\n    seed: 2\n    kidnap_start_s: 14\n"
      << "relocalization:\n  enabled: " << (reloc ? "true" : "false") << "\n";
  }
  const auto r =
      run_command(quote(kExe) + (lockstep ? " --lockstep" : "") +
                  " --input synthetic:room_kidnap --quiet --max-frames " + std::to_string(kFrames) +
                  " --config " + quote(cfg.string()) + " --output " + quote(dir.string()));
  EXPECT_EQ(r.exit_code, 0) << r.output;
  return dir;
}

int tracked_in(const std::vector<FrameRow>& rows, int from, int to) {
  int n = 0;
  for (const FrameRow& f : rows) n += (f.seq >= from && f.seq < to && f.state == "tracked");
  return n;
}

cv::FileStorage open_summary(const std::filesystem::path& dir) {
  return cv::FileStorage((dir / "summary.json").string(),
                         cv::FileStorage::READ | cv::FileStorage::FORMAT_JSON);
}

TEST(Relocalization, LockstepKidnapToAKnownPlaceIsRelocalizedWithin30Frames) {
  const auto dir = run_kidnap("mer_e2e_reloc_lockstep", true, true);
  const std::vector<FrameRow> rows = read_frames(dir);
  ASSERT_EQ(rows.size(), static_cast<std::size_t>(kFrames));
  EXPECT_EQ(tracked_in(rows, kBlackFirst - 60, kBlackFirst), 60) << "tracked before the blackout";
  EXPECT_EQ(tracked_in(rows, kBlackFirst, kBackAt), 0) << "nothing to track while black";
  // The state machine: lost, then relocalizing while black.
  EXPECT_EQ(rows[kBlackFirst].tracker_state, "lost");
  EXPECT_EQ(rows[kBackAt - 1].tracker_state, "relocalizing");
  // Back within kWithin frames of reappearing, and tracked from there on.
  int first_back = -1;
  for (const FrameRow& f : rows) {
    if (f.seq >= kBackAt && f.state == "tracked") {
      first_back = f.seq;
      break;
    }
  }
  ASSERT_GE(first_back, kBackAt);
  EXPECT_LT(first_back, kBackAt + kWithin) << "measured: the second frame after reappearing";
  EXPECT_EQ(rows[static_cast<std::size_t>(first_back)].reason, "relocalization");
  EXPECT_EQ(rows[static_cast<std::size_t>(first_back)].tracker_state, "tracking");
  EXPECT_EQ(tracked_in(rows, first_back, kFrames), kFrames - first_back);
  cv::FileStorage s = open_summary(dir);
  ASSERT_TRUE(s.isOpened());
  const cv::FileNode rl = s["relocalization"];
  EXPECT_EQ(static_cast<int>(rl["lost_spells"]), 1);
  EXPECT_GE(static_cast<int>(rl["successes"]), 1);
  EXPECT_EQ(static_cast<int>(rl["resumed"]), 1);
  EXPECT_LE(static_cast<int>(rl["max_lost_frames"]), kBackAt - kBlackFirst + kWithin);
  // Relocalized into the map's frame, not a new one: the whole trajectory aligns to the truth
  // with one similarity (a wrong relocalization would show as metres of error).
  EXPECT_LT(static_cast<double>(s["accuracy"]["ate_rmse_m"]), 0.03) << "measured 0.007 m";
}

TEST(Relocalization, WithoutItTheKidnappedCameraStaysLost) {
  const auto dir = run_kidnap("mer_e2e_reloc_off", false, true);
  const std::vector<FrameRow> rows = read_frames(dir);
  ASSERT_EQ(rows.size(), static_cast<std::size_t>(kFrames));
  EXPECT_EQ(tracked_in(rows, kBackAt, kFrames), 0);
  EXPECT_EQ(rows.back().tracker_state, "lost") << "no relocalizer: never 'relocalizing'";
  cv::FileStorage s = open_summary(dir);
  ASSERT_TRUE(s.isOpened());
  EXPECT_EQ(static_cast<int>(s["relocalization"]["attempts"]), 0);
}

// Threaded: the relocalizer runs on the depth thread while tracking goes on at camera rate.
TEST(Relocalization, ThreadedKidnapIsRelocalizedOffTheTrackingThread) {
  const auto dir = run_kidnap("mer_e2e_reloc_threaded", true, false);
  const std::vector<FrameRow> rows = read_frames(dir);
  ASSERT_GT(rows.size(), static_cast<std::size_t>(kBackAt + 2 * kWithin));
  cv::FileStorage s = open_summary(dir);
  ASSERT_TRUE(s.isOpened());
  EXPECT_GE(static_cast<int>(s["relocalization"]["successes"]), 1);
  EXPECT_GE(static_cast<int>(s["relocalization"]["resumed"]), 1);
  // Frames may be dropped in threaded mode: count the tracked share of those processed.
  int n = 0;
  int tracked = 0;
  for (const FrameRow& f : rows) {
    if (f.seq < kBackAt + kWithin) continue;
    ++n;
    tracked += f.state == "tracked";
  }
  ASSERT_GT(n, 0);
  EXPECT_GE(tracked, n * 95 / 100) << tracked << " of " << n << " frames after the return";
  // The tracking thread allocates nothing on lost, relocalizing or tracked frames
  // (initialization, which does, is counted apart).
  const cv::FileNode by_state = s["tracking_allocs_by_state"];
  for (const char* state : {"tracking", "lost", "relocalizing"}) {
    EXPECT_GT(static_cast<int>(by_state[state]["frames"]), 0) << state;
    EXPECT_EQ(static_cast<int>(by_state[state]["allocations"]), 0) << state;
  }
}

}  // namespace
}  // namespace mer
