// Ground truth in common form: interpolation, TUM/KITTI files, save/load round trip, and
// the reference trajectories in ../shared/data/trajectories.
#include "hal/ground_truth.h"

#include <cmath>
#include <filesystem>

#include <gtest/gtest.h>

#include "replay_fixtures.h"
#include "support/required_data.h"

namespace mer::hal {
namespace {

using test::pose_z;

Trajectory two_samples() {
  Trajectory t;
  t.poses.push_back({1'000'000'000, pose_z(0.0, 0.0, 0.0, 0.0)});
  t.poses.push_back({1'020'000'000, pose_z(0.2, 2.0, -4.0, 6.0)});
  return t;
}

double yaw(const SE3d& T) {
  return std::atan2(T.linear()(1, 0), T.linear()(0, 0));
}

TEST(InterpolatePose, LerpsTranslationAndSlerpsRotation) {
  const Trajectory t = two_samples();
  const auto mid = interpolate_pose(t, 1'010'000'000, 20'000'000);
  ASSERT_TRUE(mid.has_value());
  EXPECT_NEAR(yaw(*mid), 0.1, 1e-12);
  EXPECT_NEAR((mid->translation() - Eigen::Vector3d(1.0, -2.0, 3.0)).norm(), 0.0, 1e-12);
  const auto quarter = interpolate_pose(t, 1'005'000'000, 20'000'000);
  ASSERT_TRUE(quarter.has_value());
  EXPECT_NEAR(yaw(*quarter), 0.05, 1e-12);
  EXPECT_NEAR(quarter->translation().x(), 0.5, 1e-12);
}

TEST(InterpolatePose, ExactSampleOutsideAndGaps) {
  const Trajectory t = two_samples();
  const auto exact = interpolate_pose(t, 1'020'000'000, 0);
  ASSERT_TRUE(exact.has_value());
  EXPECT_NEAR(yaw(*exact), 0.2, 1e-12);
  EXPECT_FALSE(interpolate_pose(t, 999'999'999, 20'000'000).has_value()) << "before the first";
  EXPECT_FALSE(interpolate_pose(t, 1'020'000'001, 20'000'000).has_value()) << "after the last";
  EXPECT_FALSE(interpolate_pose(t, 1'010'000'000, 9'999'999).has_value()) << "gap too wide";
  EXPECT_FALSE(interpolate_pose(Trajectory{}, 0, 20'000'000).has_value());
}

TEST(GroundTruthFiles, SaveThenLoadTumRoundTrips) {
  test::TempDir dir;
  Trajectory t;
  t.poses.push_back({1305031102175304000LL, pose_z(0.3, 1.25, -2.5, 0.125)});
  t.poses.push_back({1305031102211214123LL, pose_z(-1.0, 0.0, 3.0, -7.0)});
  ASSERT_TRUE(save_tum_trajectory(dir / "traj.txt", t).is_ok());
  auto back = load_tum_trajectory(dir / "traj.txt");
  ASSERT_TRUE(back.is_ok()) << back.status().message();
  ASSERT_EQ(back.value().poses.size(), 2U);
  EXPECT_EQ(back.value().source, dir / "traj.txt");
  for (std::size_t i = 0; i < 2; ++i) {
    EXPECT_EQ(back.value().poses[i].t_ns, t.poses[i].t_ns) << "ns exact through the text";
    EXPECT_NEAR((back.value().poses[i].T_w_c.matrix() - t.poses[i].T_w_c.matrix()).norm(), 0.0,
                1e-8);
  }
  EXPECT_FALSE(std::filesystem::exists(dir / "traj.txt.tmp"));
  EXPECT_FALSE(save_tum_trajectory(dir / "no/such/dir/t.txt", t).is_ok());
}

TEST(GroundTruthFiles, KittiWithAndWithoutTimes) {
  test::TempDir dir;
  test::make_kitti(dir.path(), 3, 8, 8, 2);
  auto by_index = load_kitti_trajectory(dir / "poses.txt");
  ASSERT_TRUE(by_index.is_ok()) << by_index.status().message();
  ASSERT_EQ(by_index.value().poses.size(), 2U);
  EXPECT_EQ(by_index.value().poses[1].t_ns, 1'000'000'000);
  auto timed = load_kitti_trajectory(dir / "poses.txt", dir / "times.txt");
  ASSERT_TRUE(timed.is_ok()) << timed.status().message();
  EXPECT_EQ(timed.value().poses[1].t_ns, 100'000'000);
  EXPECT_NEAR(timed.value().poses[1].T_w_c.translation().z(), 2.0, 1e-6);
  test::write_file(dir / "short_times.txt", "0.0\n");
  auto too_few = load_kitti_trajectory(dir / "poses.txt", dir / "short_times.txt");
  ASSERT_FALSE(too_few.is_ok());
  EXPECT_NE(too_few.status().message().find("short_times.txt"), std::string::npos);
}

TEST(GroundTruthFiles, MissingFileIsAnErrorNamingIt) {
  auto r = load_tum_trajectory("/no/such/groundtruth.txt");
  ASSERT_FALSE(r.is_ok());
  EXPECT_EQ(r.status().code(), StatusCode::kInputError);
  EXPECT_NE(r.status().message().find("/no/such/groundtruth.txt"), std::string::npos);
}

TEST(GroundTruthFiles, ReadsTheSharedReferenceTrajectories) {
  const std::string data = test::shared_data_dir();
  MER_REQUIRE_DATA(!data.empty()) << "../shared/data not found (set MER_SHARED_DIR)";
  const std::string dir = data + "/trajectories";
  const std::pair<const char*, std::size_t> tum[] = {
      {"fr2_desk_groundtruth.txt", 0},      {"fr2_desk_ORB.txt", 2893},
      {"freiburg1_xyz-groundtruth.txt", 0}, {"freiburg1_xyz-rgbdslam.txt", 0},
      {"freiburg1_xyz-ORB_kf_mono.txt", 0}, {"fr2_desk_ORB_kf_mono.txt", 0}};
  for (const auto& [name, expected] : tum) {
    auto r = load_tum_trajectory(dir + "/" + name);
    ASSERT_TRUE(r.is_ok()) << r.status().message();
    EXPECT_GT(r.value().poses.size(), 10U) << name;
    if (expected != 0) {
      EXPECT_EQ(r.value().poses.size(), expected) << name;
    }
  }
  // Real ground truth repeats a timestamp once (1311868229.5760, lines 10862-10863).
  auto desk = load_tum_trajectory(dir + "/fr2_desk_groundtruth.txt");
  ASSERT_TRUE(desk.is_ok());
  EXPECT_EQ(desk.value().duplicates_dropped, 1U);
  EXPECT_EQ(desk.value().first_duplicate_line, 10863);
  auto kitti = load_kitti_trajectory(dir + "/KITTI_00_gt.txt", dir + "/KITTI_00_gt_times.txt");
  ASSERT_TRUE(kitti.is_ok()) << kitti.status().message();
  EXPECT_EQ(kitti.value().poses.size(), 4541U);
  EXPECT_EQ(kitti.value().poses[1].t_ns, 103'735'900);
  // The clip's groundtruth.txt is the same poses as its poses.txt, in TUM form.
  auto a = load_tum_trajectory(data + "/kitti_clip1/groundtruth.txt");
  auto b = load_kitti_trajectory(data + "/kitti_clip1/poses.txt", data + "/kitti_clip1/times.txt");
  ASSERT_TRUE(a.is_ok()) << a.status().message();
  ASSERT_TRUE(b.is_ok()) << b.status().message();
  ASSERT_EQ(a.value().poses.size(), b.value().poses.size());
  for (std::size_t i = 0; i < a.value().poses.size(); ++i) {
    EXPECT_EQ(a.value().poses[i].t_ns, b.value().poses[i].t_ns);
    EXPECT_NEAR(
        (a.value().poses[i].T_w_c.translation() - b.value().poses[i].T_w_c.translation()).norm(),
        0.0, 1e-5);
  }
}

}  // namespace
}  // namespace mer::hal
