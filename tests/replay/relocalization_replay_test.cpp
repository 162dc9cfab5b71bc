// mer_slam end to end through a kidnap: synthetic:room_kidnap goes black for 1 s (frames
// 421-450 with kidnap_start_s 14) and reappears where it was 6 s earlier. The relocalizer must
// find the camera in the map within 30 frames of it reappearing, in lockstep and threaded; with
// relocalization off the camera stays lost (the mechanism, not chance, brings it back), unless
// a new map segment is allowed: then it tracks again in segment 1, with its own trajectory
// file. The blackout outlasts tracking.new_segment_after_s (0.5 s): the tracker starts a new
// segment while black, and the relocalizer brings it back to segment 0.
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
  int segment = -1;           // map segment
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
    if (cols.size() < 16) continue;
    rows.push_back({std::stoi(cols[0]), cols[2], cols[11], cols[14], std::stoi(cols[15])});
  }
  return rows;
}

std::filesystem::path run_kidnap(const std::string& name, bool reloc, bool lockstep,
                                 bool new_segments = true) {
  const auto dir = std::filesystem::temp_directory_path() / name;
  std::filesystem::remove_all(dir);
  const auto cfg = std::filesystem::temp_directory_path() / (name + ".yaml");
  {
    std::ofstream f(cfg);
    f << "camera:\n  synthetic:\n    seed: 2\n    kidnap_start_s: 14\n"
      << "relocalization:\n  enabled: " << (reloc ? "true" : "false") << "\n"
      << "tracking:\n  new_segments: " << (new_segments ? "true" : "false") << "\n";
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

// First frame at or after `from` that was tracked (-1: none).
int first_tracked_from(const std::vector<FrameRow>& rows, int from) {
  for (const FrameRow& f : rows) {
    if (f.seq >= from && f.state == "tracked") return f.seq;
  }
  return -1;
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
  // The state machine: lost, relocalizing, then (0.5 s after the last tracked frame) a new
  // segment is being initialized while black; relocalization is still asked for.
  EXPECT_EQ(rows[kBlackFirst].tracker_state, "lost");
  EXPECT_EQ(rows[kBlackFirst + 5].tracker_state, "relocalizing");
  EXPECT_EQ(rows[kBackAt - 1].tracker_state, "new_segment");
  EXPECT_EQ(rows[kBackAt - 1].segment, 1);
  // Back within kWithin frames of reappearing, and tracked from there on.
  const int first_back = first_tracked_from(rows, kBackAt);
  ASSERT_GE(first_back, kBackAt);
  EXPECT_LT(first_back, kBackAt + kWithin) << "measured: the second frame after reappearing";
  EXPECT_EQ(rows[static_cast<std::size_t>(first_back)].reason, "relocalization");
  EXPECT_EQ(rows[static_cast<std::size_t>(first_back)].tracker_state, "tracking");
  EXPECT_EQ(rows[static_cast<std::size_t>(first_back)].segment, 0) << "back in the first map";
  EXPECT_EQ(tracked_in(rows, first_back, kFrames), kFrames - first_back);
  EXPECT_FALSE(std::filesystem::exists(dir / "trajectory_segment_1.txt"))
      << "segment 1 never tracked a frame";
  cv::FileStorage s = open_summary(dir);
  ASSERT_TRUE(s.isOpened());
  const cv::FileNode rl = s["relocalization"];
  EXPECT_EQ(static_cast<int>(rl["lost_spells"]), 1);
  EXPECT_GE(static_cast<int>(rl["successes"]), 1);
  EXPECT_EQ(static_cast<int>(rl["resumed"]), 1);
  EXPECT_EQ(static_cast<int>(rl["new_segments"]), 1);
  EXPECT_EQ(static_cast<int>(rl["segment_returns"]), 1);
  ASSERT_EQ(s["segments"].size(), 1U);
  EXPECT_EQ(static_cast<int>(s["segments"][0]["frames"]), tracked_in(rows, 0, kFrames));
  EXPECT_LE(static_cast<int>(rl["max_lost_frames"]), kBackAt - kBlackFirst + kWithin);
  // Relocalized into the map's frame, not a new one: the whole trajectory aligns to the truth
  // with one similarity (a wrong relocalization would show as metres of error).
  EXPECT_LT(static_cast<double>(s["accuracy"]["ate_rmse_m"]), 0.03) << "measured 0.007 m";
}

TEST(Relocalization, WithoutItOrNewSegmentsTheKidnappedCameraStaysLost) {
  const auto dir = run_kidnap("mer_e2e_reloc_off", false, true, false);
  const std::vector<FrameRow> rows = read_frames(dir);
  ASSERT_EQ(rows.size(), static_cast<std::size_t>(kFrames));
  EXPECT_EQ(tracked_in(rows, kBackAt, kFrames), 0);
  EXPECT_EQ(rows.back().tracker_state, "lost") << "no relocalizer: never 'relocalizing'";
  cv::FileStorage s = open_summary(dir);
  ASSERT_TRUE(s.isOpened());
  EXPECT_EQ(static_cast<int>(s["relocalization"]["attempts"]), 0);
  EXPECT_EQ(static_cast<int>(s["relocalization"]["new_segments"]), 0);
}

// Without a relocalizer, a new map segment is initialized where the camera reappears (as at an
// unknown place) and tracks again; the place is a mapped one, so the new segment's keyframes
// find the old map (loop.merge_segments): segment 1 merges into segment 0, tracking follows
// into it, and trajectory.txt holds every tracked frame in one frame that aligns to the truth.
TEST(Relocalization, WithoutItANewSegmentTracksTheKidnappedCameraAndMergesBack) {
  const auto dir = run_kidnap("mer_e2e_reloc_off_segment", false, true, true);
  const std::vector<FrameRow> rows = read_frames(dir);
  ASSERT_EQ(rows.size(), static_cast<std::size_t>(kFrames));
  EXPECT_EQ(rows[kBackAt - 1].tracker_state, "new_segment");
  const int first_back = first_tracked_from(rows, kBackAt);
  ASSERT_GE(first_back, kBackAt);
  // Measured: frame 485, 34 frames after reappearing (the two-view start waits for parallax
  // on this slow orbit); 30 frames is the aim, twice that the bound.
  EXPECT_LT(first_back, kBackAt + 2 * kWithin) << "new segment initialized";
  int in_segment_1 = 0;
  int back_in_0 = 0;
  int tracked = 0;
  for (const FrameRow& f : rows) {
    if (f.state != "tracked") continue;
    ++tracked;
    if (f.seq < kBlackFirst) {
      EXPECT_EQ(f.segment, 0) << "frame " << f.seq;
    } else {
      in_segment_1 += f.segment == 1;
      back_in_0 += f.segment == 0;
    }
  }
  EXPECT_GT(in_segment_1, 0);
  // Measured: merged at frame 496, 11 frames after the new segment's start.
  EXPECT_GT(back_in_0 + in_segment_1, (kFrames - kBackAt - 2 * kWithin) * 9 / 10);
  EXPECT_GT(back_in_0, in_segment_1) << "merged early";
  auto lines = [](const std::filesystem::path& p) {
    std::ifstream in(p);
    int n = 0;
    for (std::string l; std::getline(in, l);) n += !l.empty();
    return n;
  };
  EXPECT_FALSE(std::filesystem::exists(dir / "trajectory_segment_1.txt"));
  EXPECT_EQ(lines(dir / "trajectory.txt"), tracked);
  cv::FileStorage s = open_summary(dir);
  ASSERT_TRUE(s.isOpened());
  EXPECT_EQ(static_cast<int>(s["relocalization"]["new_segments"]), 1);
  EXPECT_EQ(static_cast<int>(s["loop"]["segments_merged"]), 1);
  const cv::FileNode segs = s["segments"];
  ASSERT_EQ(segs.size(), 2U);
  EXPECT_EQ(static_cast<int>(segs[0]["merged_into"]), -1);
  EXPECT_EQ(static_cast<int>(segs[1]["id"]), 1);
  EXPECT_EQ(static_cast<int>(segs[1]["merged_into"]), 0);
  EXPECT_EQ(static_cast<int>(segs[1]["frames"]), in_segment_1);
  EXPECT_EQ(static_cast<std::string>(segs[1]["trajectory"]), "trajectory.txt");
  // One consistent frame for the whole run (measured 7.7 mm rmse, 0.13 % of the path).
  EXPECT_LT(static_cast<double>(s["accuracy"]["ate_rmse_m"]), 0.03);
  EXPECT_GT(static_cast<double>(s["accuracy"]["tracked_after_init_pct"]), 85.0);
  // trajectory_final.txt re-anchors every frame of trajectory.txt to the final map, the
  // merged segment's too (their anchors scaled by the merge).
  const cv::FileNode fin = s["final_trajectory"];
  ASSERT_FALSE(fin.empty());
  EXPECT_EQ(static_cast<int>(fin["frames"]), tracked);
  EXPECT_EQ(static_cast<int>(fin["unresolved"]), 0);
  EXPECT_EQ(lines(dir / "trajectory_final.txt"), tracked);
  EXPECT_LT(static_cast<double>(s["accuracy_final"]["ate_rmse_m"]), 0.03);
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
