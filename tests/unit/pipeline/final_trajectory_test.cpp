#include "pipeline/final_trajectory.h"

#include <vector>

#include <gtest/gtest.h>

namespace mer::pipeline {
namespace {

SE3d pose(double yaw, double x, double y, double z) {
  return make_se3(Eigen::Quaterniond(Eigen::AngleAxisd(yaw, Eigen::Vector3d::UnitZ())),
                  Eigen::Vector3d(x, y, z));
}

void expect_near(const SE3d& a, const SE3d& b) {
  EXPECT_LT((a.matrix() - b.matrix()).norm(), 1e-12) << a.matrix() << "\nvs\n" << b.matrix();
}

// Removed keyframes reach the final map through their parents, even when the parent was
// removed later too; a record whose chain ends at a keyframe that is not known is dropped.
TEST(FinalTrajectory, LineageChainsResolveToLiveKeyframes) {
  const SE3d T_w_a = pose(0.3, 1.0, 2.0, 0.5);
  const std::vector<StampedPose> live{{400, pose(0.0, 4.0, 0.0, 0.0)}, {100, T_w_a}};
  const SE3d T_a_b = pose(0.1, 0.2, 0.0, 0.0);
  const SE3d T_b_c = pose(-0.2, 0.0, 0.3, 0.0);
  const std::vector<backend::CulledKeyframe> lineage{
      {300, 200, T_b_c},                      // c's parent b was removed after c
      {200, 100, T_a_b},                      // b's parent a is live
      {500, 999, pose(0.0, 1.0, 1.0, 1.0)}};  // parent 999 forgotten
  const std::vector<FinalKeyframePose> kfs = resolve_keyframe_poses(live, lineage);
  ASSERT_EQ(kfs.size(), 4U);
  EXPECT_EQ(kfs[0].t_ns, 100);
  EXPECT_EQ(kfs[1].t_ns, 200);
  EXPECT_EQ(kfs[2].t_ns, 300);
  EXPECT_EQ(kfs[3].t_ns, 400);
  EXPECT_FALSE(kfs[0].from_lineage);
  EXPECT_TRUE(kfs[1].from_lineage);
  EXPECT_TRUE(kfs[2].from_lineage);
  EXPECT_FALSE(kfs[3].from_lineage);
  expect_near(kfs[1].T_w_c, T_w_a * T_a_b);
  expect_near(kfs[2].T_w_c, T_w_a * T_a_b * T_b_c);
}

// A record made in a segment that later merged into the main one at scale 0.5 has its offset
// halved; a record of a segment that never joined it is not followed.
TEST(FinalTrajectory, LineageOffsetsTakeTheirSegmentsMergeScale) {
  const SE3d T_w_a = pose(0.3, 1.0, 2.0, 0.5);
  const std::vector<StampedPose> live{{100, T_w_a}};
  const SE3d T_a_b = pose(0.1, 0.4, -0.2, 0.0);
  std::vector<backend::CulledKeyframe> lineage{{200, 100, T_a_b, 1}, {300, 100, T_a_b, 2}};
  const std::vector<double> scale{1.0, 0.5, 0.0};
  const std::vector<FinalKeyframePose> kfs = resolve_keyframe_poses(live, lineage, scale);
  ASSERT_EQ(kfs.size(), 2U);
  EXPECT_EQ(kfs[1].t_ns, 200);
  SE3d T_a_b_half = T_a_b;
  T_a_b_half.translation() *= 0.5;
  expect_near(kfs[1].T_w_c, T_w_a * T_a_b_half);
  // Without scales every record is taken as in the main segment's units.
  EXPECT_EQ(resolve_keyframe_poses(live, lineage).size(), 3U);
}

// A frame lands where its keyframe's final pose puts it; a frame without a resolvable
// keyframe moves with the previous frame's correction, and a frame before any anchored one
// stays as tracked.
TEST(FinalTrajectory, FramesFollowTheirKeyframeOrThePreviousCorrection) {
  const SE3d T_w_kf_final = pose(0.5, 3.0, -1.0, 0.2);
  const std::vector<FinalKeyframePose> kfs{{100, T_w_kf_final, false}};
  const SE3d T_kf_c = pose(0.05, 0.1, 0.0, 0.02);
  const SE3d T_w_kf_tracked = pose(0.4, 2.9, -1.1, 0.2);
  std::vector<AnchoredFrame> frames(4);
  frames[0] = {50, pose(0.0, 0.1, 0.2, 0.3), false, 0, SE3d::Identity()};
  frames[1] = {150, T_w_kf_tracked * T_kf_c, true, 100, T_kf_c};
  frames[2] = {160, pose(0.45, 3.0, -1.0, 0.2), true, 777, SE3d::Identity()};  // unknown kf
  frames[3] = {170, pose(0.46, 3.1, -1.0, 0.2), false, 0, SE3d::Identity()};
  FinalTrajectoryStats st;
  const std::vector<StampedPose> out = reanchor_frames(frames, kfs, st);
  ASSERT_EQ(out.size(), 4U);
  EXPECT_EQ(st.frames, 4U);
  EXPECT_EQ(st.reanchored, 1U);
  EXPECT_EQ(st.unresolved, 3U);
  EXPECT_EQ(st.via_lineage, 0U);
  expect_near(out[0].T_w_c, frames[0].T_w_c);
  expect_near(out[1].T_w_c, T_w_kf_final * T_kf_c);
  const SE3d correction = out[1].T_w_c * frames[1].T_w_c.inverse();
  expect_near(out[2].T_w_c, correction * frames[2].T_w_c);
  expect_near(out[3].T_w_c, correction * frames[3].T_w_c);
  for (std::size_t i = 0; i < out.size(); ++i) EXPECT_EQ(out[i].t_ns, frames[i].t_ns);
}

// The back end moved keyframe B relative to its predecessor A after B's frame was tracked: the
// frame that became B lands on B's final pose, and a frame half-way in time between them gets
// half of that correction (rotation angle and translation).
TEST(FinalTrajectory, FramesBetweenKeyframesShareTheNextKeyframesCorrection) {
  const SE3d T_w_a = pose(0.2, 1.0, 0.0, 0.0);
  const SE3d T_w_b = pose(0.3, 1.5, 0.1, 0.0);
  const std::vector<FinalKeyframePose> kfs{{100, T_w_a, false}, {200, T_w_b, false}};
  const SE3d T_a_b_tracked = pose(0.08, 0.45, 0.05, 0.0);  // tracking's view of B from A
  const SE3d T_a_f = pose(0.04, 0.2, 0.02, 0.0);
  std::vector<AnchoredFrame> frames(3);
  frames[0] = {150, T_w_a * T_a_f, true, 100, T_a_f};
  frames[1] = {200, T_w_a * T_a_b_tracked, true, 100, T_a_b_tracked};
  frames[2] = {210, T_w_b * T_a_f, true, 200, T_a_f};  // anchored to B, which has no next
  FinalTrajectoryStats st;
  const std::vector<StampedPose> out = reanchor_frames(frames, kfs, st);
  ASSERT_EQ(out.size(), 3U);
  EXPECT_EQ(st.reanchored, 3U);
  EXPECT_EQ(st.interpolated, 2U);
  expect_near(out[1].T_w_c, T_w_b);
  const SE3d D = T_w_a.inverse() * T_w_b * T_a_b_tracked.inverse();
  const Eigen::AngleAxisd aa(D.linear());
  SE3d half = SE3d::Identity();
  half.linear() = Eigen::AngleAxisd(0.5 * aa.angle(), aa.axis()).toRotationMatrix();
  half.translation() = 0.5 * D.translation();
  expect_near(out[0].T_w_c, T_w_a * half * T_a_f);
  expect_near(out[2].T_w_c, T_w_b * T_a_f);
}

}  // namespace
}  // namespace mer::pipeline
