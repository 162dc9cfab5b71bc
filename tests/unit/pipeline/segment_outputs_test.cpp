#include "pipeline/segment_outputs.h"

#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "hal/ground_truth.h"
#include "pipeline/output_stage.h"

namespace mer::pipeline {
namespace {

namespace fs = std::filesystem;

SE3d pose(double yaw, double x, double y, double z) {
  return make_se3(Eigen::Quaterniond(Eigen::AngleAxisd(yaw, Eigen::Vector3d::UnitZ())),
                  Eigen::Vector3d(x, y, z));
}

SegmentOutput seg(std::uint16_t id, std::uint64_t frames) {
  SegmentOutput g;
  g.id = id;
  g.frames = frames;
  return g;
}

/// A fresh directory per test, removed afterwards.
class SegmentOutputs : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = fs::temp_directory_path() /
           ("mer_segment_outputs_" +
            std::string(::testing::UnitTest::GetInstance()->current_test_info()->name()));
    fs::remove_all(dir_);
    fs::create_directories(dir_);
  }
  void TearDown() override { fs::remove_all(dir_); }

  /// Writes `poses` as the output stage does (one TUM line per pose).
  void write(const std::string& name, const std::vector<StampedPose>& poses) const {
    std::ofstream f(dir_ / name);
    char buf[256];
    for (const StampedPose& p : poses) {
      const int n = format_tum_line(buf, sizeof buf, p.t_ns, p.T_w_c);
      f.write(buf, n);
    }
  }
  std::vector<StampedPose> read(const std::string& name) const {
    auto t = hal::load_tum_trajectory((dir_ / name).string());
    EXPECT_TRUE(t.is_ok()) << name << ": " << t.status().message();
    return t.is_ok() ? t.value().poses : std::vector<StampedPose>{};
  }

  fs::path dir_;
};

constexpr std::int64_t kS = 1'000'000'000;

// Segment 2 merges into 1, then 1 into 0: every frame of 1 and 2 lands in 0's world frame
// (2's through both similarities), in time order, in trajectory.txt; the never-merged
// segment 3 keeps its file; the merged segments' files are gone.
TEST_F(SegmentOutputs, MergedSegmentsMoveIntoTheOlderFrameAndJoinItsFile) {
  const SE3d a0 = pose(0.0, 0.0, 0.0, 0.0);
  const SE3d a1 = pose(0.1, 1.0, 0.0, 0.0);
  const SE3d b0 = pose(0.2, 0.0, 1.0, 0.0);
  const SE3d c0 = pose(-0.3, 0.5, 0.5, 2.0);
  const SE3d d0 = pose(0.4, 9.0, 9.0, 9.0);
  write("trajectory.txt", {{1 * kS, a0}, {2 * kS, a1}, {7 * kS, a1}});
  write("keyframes.txt", {{1 * kS, a0}});
  write("trajectory_segment_1.txt", {{3 * kS, b0}, {4 * kS + 5, b0}});
  write("keyframes_segment_1.txt", {{3 * kS, b0}});
  write("trajectory_segment_2.txt", {{5 * kS, c0}, {6 * kS, c0}});
  write("trajectory_segment_3.txt", {{8 * kS, d0}, {9 * kS, d0}, {10 * kS, d0}});
  write("keyframes_segment_3.txt", {{8 * kS, d0}});

  geometry::Sim3d S_1_2{Eigen::Matrix3d(Eigen::AngleAxisd(0.5, Eigen::Vector3d::UnitY())),
                        Eigen::Vector3d(0.1, 0.2, 0.3), 2.0};
  geometry::Sim3d S_0_1{Eigen::Matrix3d(Eigen::AngleAxisd(-0.7, Eigen::Vector3d::UnitX())),
                        Eigen::Vector3d(-1.0, 0.0, 4.0), 0.5};
  const std::vector<SegmentMergeRecord> merges{{2, 1, 60, S_1_2}, {1, 0, 80, S_0_1}};
  std::vector<SegmentOutput> segs{seg(0, 3), seg(1, 2), seg(2, 2), seg(3, 3)};
  std::uint16_t main = 99;
  const Status s = join_segment_files(dir_.string(), merges, segs, main);
  ASSERT_TRUE(s.is_ok()) << s.message();
  EXPECT_EQ(main, 0);

  const std::vector<StampedPose> t = read("trajectory.txt");
  ASSERT_EQ(t.size(), 7U);
  const std::int64_t want_t[] = {1 * kS, 2 * kS, 3 * kS, 4 * kS + 5, 5 * kS, 6 * kS, 7 * kS};
  for (std::size_t i = 0; i < t.size(); ++i) EXPECT_EQ(t[i].t_ns, want_t[i]) << i;
  const SE3d want_b0 = geometry::apply_to_pose(S_0_1, b0);
  const SE3d want_c0 = geometry::apply_to_pose(S_0_1 * S_1_2, c0);
  EXPECT_LT((t[0].T_w_c.matrix() - a0.matrix()).norm(), 1e-8);
  EXPECT_LT((t[2].T_w_c.matrix() - want_b0.matrix()).norm(), 1e-8);
  EXPECT_LT((t[4].T_w_c.matrix() - want_c0.matrix()).norm(), 1e-8);
  EXPECT_LT((t[6].T_w_c.matrix() - a1.matrix()).norm(), 1e-8);
  EXPECT_EQ(read("keyframes.txt").size(), 2U);

  EXPECT_FALSE(fs::exists(dir_ / "trajectory_segment_1.txt"));
  EXPECT_FALSE(fs::exists(dir_ / "keyframes_segment_1.txt"));
  EXPECT_FALSE(fs::exists(dir_ / "trajectory_segment_2.txt"));
  EXPECT_EQ(read("trajectory_segment_3.txt").size(), 3U);

  EXPECT_EQ(segs[0].merged_into, -1);
  EXPECT_EQ(segs[1].merged_into, 0);
  EXPECT_EQ(segs[1].merged_at_seq, 80U);
  EXPECT_EQ(segs[2].merged_into, 0);  // followed 1 into 0
  EXPECT_EQ(segs[2].merged_at_seq, 60U);
  EXPECT_EQ(segs[3].merged_into, -1);
  EXPECT_EQ(segs[1].trajectory, "trajectory.txt");
  EXPECT_EQ(segs[2].trajectory, "trajectory.txt");
  EXPECT_EQ(segs[3].trajectory, "trajectory_segment_3.txt");
}

// Segment 1's keyframes sit, in the final map, where similarity S puts them; the merge's
// own similarity (the loop point's) is off by 10 % in scale and a few degrees. Its frames
// move by the similarity fitted to the keyframes (S), not by the merge's; without the final
// keyframes, or with fewer than kMinFitKeyframes of them, by the merge's.
TEST_F(SegmentOutputs, MergedFramesMoveByTheSimilarityFittedToTheirKeyframes) {
  const SE3d a0 = pose(0.0, 0.0, 0.0, 0.0);
  std::vector<StampedPose> kf1;
  for (int i = 0; i < 5; ++i) {
    kf1.push_back({(3 + i) * kS, pose(0.1 * i, 0.5 * i, 0.2 * i * i, 0.1)});
  }
  const SE3d frame1 = pose(0.35, 1.1, 0.6, 0.15);
  const geometry::Sim3d S{Eigen::Matrix3d(Eigen::AngleAxisd(0.4, Eigen::Vector3d::UnitZ())),
                          Eigen::Vector3d(1.0, -2.0, 0.5), 0.6};
  geometry::Sim3d S_merge = S;
  S_merge.s *= 1.1;
  S_merge.R = Eigen::AngleAxisd(0.05, Eigen::Vector3d::UnitX()).toRotationMatrix() * S.R;
  const std::vector<SegmentMergeRecord> merges{{1, 0, 80, S_merge}};
  std::vector<FinalKeyframePose> finals{{1 * kS, a0, false}};
  for (const StampedPose& k : kf1) finals.push_back({k.t_ns, geometry::apply_to_pose(S, k.T_w_c)});
  auto prepare = [&] {
    write("trajectory.txt", {{1 * kS, a0}, {2 * kS, a0}, {9 * kS, a0}});
    write("keyframes.txt", {{1 * kS, a0}});
    write("trajectory_segment_1.txt", {{3 * kS, kf1[0].T_w_c}, {5 * kS + 7, frame1}});
    write("keyframes_segment_1.txt", kf1);
  };
  auto frame1_after = [&](const FinalKeyframesOf& of, int& fitted) {
    prepare();
    std::vector<SegmentOutput> segs{seg(0, 3), seg(1, 2)};
    std::uint16_t main = 99;
    const Status st = join_segment_files(dir_.string(), merges, segs, main, of);
    EXPECT_TRUE(st.is_ok()) << st.message();
    EXPECT_EQ(main, 0);
    fitted = segs[1].fit_keyframes;
    const std::vector<StampedPose> t = read("trajectory.txt");
    EXPECT_EQ(t.size(), 5U);
    return t.size() == 5U ? t[3].T_w_c : SE3d::Identity();
  };
  int fitted = -1;
  const SE3d by_fit =
      frame1_after([&](std::uint16_t m) { return m == 0 ? finals : decltype(finals){}; }, fitted);
  EXPECT_EQ(fitted, 5);
  EXPECT_LT((by_fit.matrix() - geometry::apply_to_pose(S, frame1).matrix()).norm(), 1e-8);
  const SE3d by_merge = frame1_after({}, fitted);
  EXPECT_EQ(fitted, 0);
  EXPECT_LT((by_merge.matrix() - geometry::apply_to_pose(S_merge, frame1).matrix()).norm(), 1e-8);
  const std::vector<FinalKeyframePose> few(finals.begin(), finals.begin() + 3);
  const SE3d by_few = frame1_after([&](std::uint16_t) { return few; }, fitted);
  EXPECT_EQ(fitted, 0);
  EXPECT_LT((by_few.matrix() - by_merge.matrix()).norm(), 1e-8);
}

// Without a merge the segment with the most frames is the main one (the corridor case: a
// one-frame segment 0, then a long one): trajectory.txt holds it, segment 0 moves aside.
TEST_F(SegmentOutputs, WithoutMergeTheLargestSegmentIsTrajectoryTxt) {
  const SE3d a = pose(0.0, 1.0, 2.0, 3.0);
  const SE3d b = pose(1.0, -1.0, 0.0, 0.5);
  write("trajectory.txt", {{1 * kS, a}});
  write("keyframes.txt", {{1 * kS, a}});
  write("trajectory_segment_1.txt", {{2 * kS, b}, {3 * kS, b}, {4 * kS, b}});
  write("keyframes_segment_1.txt", {{2 * kS, b}});
  std::vector<SegmentOutput> segs{seg(0, 1), seg(1, 3)};
  std::uint16_t main = 99;
  ASSERT_TRUE(join_segment_files(dir_.string(), {}, segs, main).is_ok());
  EXPECT_EQ(main, 1);
  const std::vector<StampedPose> t = read("trajectory.txt");
  ASSERT_EQ(t.size(), 3U);
  EXPECT_EQ(t[0].t_ns, 2 * kS);
  EXPECT_LT((t[0].T_w_c.matrix() - b.matrix()).norm(), 1e-8);  // not moved
  EXPECT_EQ(read("trajectory_segment_0.txt").size(), 1U);
  EXPECT_EQ(read("keyframes_segment_0.txt").size(), 1U);
  EXPECT_FALSE(fs::exists(dir_ / "trajectory_segment_1.txt"));
  EXPECT_EQ(segs[0].trajectory, "trajectory_segment_0.txt");
  EXPECT_EQ(segs[1].trajectory, "trajectory.txt");
}

// With segment 0 the largest and no merge, nothing is rewritten.
TEST_F(SegmentOutputs, SegmentZeroLargestAndNoMergeLeavesTheFiles) {
  write("trajectory.txt", {{1 * kS, pose(0, 0, 0, 0)}, {2 * kS, pose(0, 1, 0, 0)}});
  write("trajectory_segment_1.txt", {{3 * kS, pose(0, 5, 0, 0)}});
  const auto before = fs::last_write_time(dir_ / "trajectory.txt");
  std::vector<SegmentOutput> segs{seg(0, 2), seg(1, 1)};
  std::uint16_t main = 99;
  ASSERT_TRUE(join_segment_files(dir_.string(), {}, segs, main).is_ok());
  EXPECT_EQ(main, 0);
  EXPECT_EQ(fs::last_write_time(dir_ / "trajectory.txt"), before);
  EXPECT_TRUE(fs::exists(dir_ / "trajectory_segment_1.txt"));
  EXPECT_EQ(segs[1].trajectory, "trajectory_segment_1.txt");
}

SegmentOutput discarded(std::uint16_t id, std::uint64_t frames) {
  SegmentOutput g = seg(id, frames);
  g.discarded = true;
  return g;
}

// Discarded segments (failed starts) are never the main one, however many frames they had,
// and their files go: trajectory.txt holds the kept segment.
TEST_F(SegmentOutputs, DiscardedSegmentsLeaveTheirFilesAndAreNeverMain) {
  const SE3d a = pose(0.0, 1.0, 2.0, 3.0);
  const SE3d b = pose(1.0, -1.0, 0.0, 0.5);
  write("trajectory.txt", {{1 * kS, a}, {2 * kS, a}, {3 * kS, a}, {4 * kS, a}, {5 * kS, a}});
  write("keyframes.txt", {{1 * kS, a}});
  write("trajectory_segment_1.txt", {{6 * kS, b}, {7 * kS, b}});
  write("keyframes_segment_1.txt", {{6 * kS, b}});
  write("trajectory_segment_2.txt", {{8 * kS, a}, {9 * kS, a}, {10 * kS, a}, {11 * kS, a}});
  write("keyframes_segment_2.txt", {{8 * kS, a}});
  std::vector<SegmentOutput> segs{discarded(0, 5), seg(1, 2), discarded(2, 4)};
  std::uint16_t main = 99;
  ASSERT_TRUE(join_segment_files(dir_.string(), {}, segs, main).is_ok());
  EXPECT_EQ(main, 1);
  const std::vector<StampedPose> t = read("trajectory.txt");
  ASSERT_EQ(t.size(), 2U);
  EXPECT_EQ(t[0].t_ns, 6 * kS);
  EXPECT_EQ(read("keyframes.txt").size(), 1U);
  for (const char* gone :
       {"trajectory_segment_0.txt", "keyframes_segment_0.txt", "trajectory_segment_1.txt",
        "keyframes_segment_1.txt", "trajectory_segment_2.txt", "keyframes_segment_2.txt"}) {
    EXPECT_FALSE(fs::exists(dir_ / gone)) << gone;
  }
  EXPECT_EQ(segs[0].trajectory, "");
  EXPECT_EQ(segs[1].trajectory, "trajectory.txt");
  EXPECT_EQ(segs[2].trajectory, "");
}

// No segment kept: trajectory.txt and keyframes.txt stay, empty.
TEST_F(SegmentOutputs, NoKeptSegmentLeavesEmptyTrajectoryFiles) {
  write("trajectory.txt", {{1 * kS, pose(0, 0, 0, 0)}, {2 * kS, pose(0, 1, 0, 0)}});
  write("keyframes.txt", {{1 * kS, pose(0, 0, 0, 0)}});
  std::vector<SegmentOutput> segs{discarded(0, 2)};
  std::uint16_t main = 99;
  ASSERT_TRUE(join_segment_files(dir_.string(), {}, segs, main).is_ok());
  ASSERT_TRUE(fs::exists(dir_ / "trajectory.txt"));
  EXPECT_EQ(fs::file_size(dir_ / "trajectory.txt"), 0U);
  EXPECT_EQ(fs::file_size(dir_ / "keyframes.txt"), 0U);
  EXPECT_EQ(segs[0].trajectory, "");
}

// A damaged segment file is an error naming it and its line; the files written by the run
// are left as they were.
TEST_F(SegmentOutputs, DamagedFileIsNamedAndNothingIsLost) {
  write("trajectory.txt", {{1 * kS, pose(0, 0, 0, 0)}});
  {
    std::ofstream f(dir_ / "trajectory_segment_1.txt");
    f << "3.0 1 2 3 0 0 0 1\n4.0 not a pose\n";
  }
  std::vector<SegmentOutput> segs{seg(0, 1), seg(1, 2)};
  std::uint16_t main = 99;
  const Status s = join_segment_files(
      dir_.string(), std::vector<SegmentMergeRecord>{{1, 0, 5, geometry::Sim3d{}}}, segs, main);
  ASSERT_FALSE(s.is_ok());
  EXPECT_NE(s.message().find("trajectory_segment_1.txt"), std::string::npos) << s.message();
  EXPECT_NE(s.message().find("line 2"), std::string::npos) << s.message();
  EXPECT_EQ(read("trajectory.txt").size(), 1U);
  EXPECT_TRUE(fs::exists(dir_ / "trajectory_segment_1.txt"));
}

// Scales into the main segment's units follow the merges in order: 2 joined 1 (scale 2),
// then 1 joined 0 (scale 0.25), so 2's units are 0.5 of 0's; 3 never merged; 4 joined 3.
TEST(SegmentScales, FollowTheMergesIntoTheMainSegment) {
  const auto merge = [](std::uint16_t from, std::uint16_t into, double s) {
    SegmentMergeRecord m;
    m.from = from;
    m.into = into;
    m.sim_into_from.s = s;
    return m;
  };
  const std::vector<SegmentMergeRecord> merges{merge(2, 1, 2.0), merge(1, 0, 0.25),
                                               merge(4, 3, 3.0)};
  const std::vector<double> to0 = segment_scales_into(merges, 0, 5);
  ASSERT_EQ(to0.size(), 5U);
  EXPECT_DOUBLE_EQ(to0[0], 1.0);
  EXPECT_DOUBLE_EQ(to0[1], 0.25);
  EXPECT_DOUBLE_EQ(to0[2], 0.5);
  EXPECT_DOUBLE_EQ(to0[3], 0.0);
  EXPECT_DOUBLE_EQ(to0[4], 0.0);
  const std::vector<double> to3 = segment_scales_into(merges, 3, 5);
  EXPECT_DOUBLE_EQ(to3[3], 1.0);
  EXPECT_DOUBLE_EQ(to3[4], 3.0);
  EXPECT_DOUBLE_EQ(to3[0], 0.0);
}

}  // namespace
}  // namespace mer::pipeline
