// A merge measured from keyframes (LoopOptions::merge_by_relocalization): a segment that was
// being lost keeps keyframes with keypoints but few map-points, too few for the 3D similarity
// of a loop. Its keyframes are relocalized against the other segment's local map and the
// similarity between the two world frames is fitted to their poses.
#include <cmath>
#include <cstdio>
#include <random>
#include <vector>

#include <gtest/gtest.h>

#include "loop/loop_closer.h"
#include "map/map.h"
#include "synthetic_map.h"

namespace mer::loop {
namespace {

constexpr double kDegPerRad = 180.0 / M_PI;

/// Segment 0: a camera turning on the spot maps headings 0-90 degrees (10 keyframes with
/// points). Segment 1 (later, its own world frame and scale 0.3 of the metre): 6 keyframes
/// walked sideways through headings 40-50, 0.6 m in all, with keypoints and descriptors but no
/// map-point, as the last keyframes of a segment being lost.
struct TwoSegments {
  scene::OrbitWorld world;
  map::Map map{scene::OrbitWorld::map_options()};
  std::vector<map::KeyframeId> seg0;
  std::vector<map::KeyframeId> seg1;
  std::vector<SE3d> seg1_true;
  geometry::Sim3d sim_1_0;  ///< the truth (segment 0's world, metres) -> segment 1's world

  /// `step_m`: segment 1's keyframes are this far apart (sideways; 0: all at the room's middle,
  /// turning on the spot); `with_points`: its first
  /// keyframe holds a map-point for every keypoint of the world (at its true place, moved into
  /// segment 1's world), as a segment whose keyframes still see their own points.
  explicit TwoSegments(double step_m = 0.12, bool with_points = false) {
    std::mt19937_64 rng(11);
    seg0 = world.build(map, 0.0, 10.0, 10, rng);
    sim_1_0.R = Eigen::AngleAxisd(20.0 / kDegPerRad, Eigen::Vector3d(0.3, 1.0, 0.2).normalized())
                    .toRotationMatrix();
    sim_1_0.t = Eigen::Vector3d(0.4, -0.1, 0.7);
    sim_1_0.s = 0.3;
    for (int k = 0; k < 6; ++k) {
      const double offset = step_m > 0.0 ? -0.3 + step_m * k : 0.0;
      const SE3d T_true = scene::OrbitWorld::pose(40.0 + 2.0 * k, offset);
      const scene::View v = world.observe(T_true, rng);
      map::KeyframeInput in;
      in.seq = 500 + static_cast<std::uint64_t>(k) * 5;
      in.t_ns = 20'000'000'000 + static_cast<std::int64_t>(k) * 166'000'000;
      in.T_w_c = geometry::apply_to_pose(sim_1_0, T_true);
      in.segment = 1;
      in.keypoints = v.keypoints;
      in.descriptors = v.descriptors;
      const Result<map::KeyframeId> r = map.add_keyframe(in);
      EXPECT_TRUE(r.is_ok()) << r.status().message();
      if (!r.is_ok()) return;
      seg1.push_back(r.value());
      seg1_true.push_back(T_true);
      if (with_points && k == 0) {
        for (std::size_t j = 0; j < v.point.size(); ++j) {
          if (v.point[j] < 0) continue;
          const Eigen::Vector3d p = world.points[static_cast<std::size_t>(v.point[j])];
          EXPECT_TRUE(map.add_point(sim_1_0 * p, r.value(), static_cast<std::uint32_t>(j)).is_ok());
        }
      }
    }
  }
};

LoopReport merge(TwoSegments& s, bool by_relocalization) {
  LoopOptions o;
  o.merge_by_relocalization = by_relocalization;
  // Retrieval is not what is checked here: with segment 1's keyframes the only scored ones,
  // the bar (a multiple of their median score) would leave out most of them.
  o.min_key_score_ratio = 0.0;
  LoopCloser closer(o, s.map, {1.0F}, false, nullptr);
  // The keyframe of segment 0 at heading 50 looks for a loop: segment 1's keyframes are
  // candidates (another segment: no time or keyframe gap).
  return closer.spin_once(s.seg0[5], s.world.K);
}

TEST(LoopMergeRelocalized, ASegmentWithoutMapPointsMergesOntoTheTruth) {
  TwoSegments s;
  ASSERT_EQ(s.seg1.size(), 6U);
  const LoopReport rep = merge(s, true);
  ASSERT_TRUE(rep.closed);
  EXPECT_EQ(rep.merged_from, 1);
  EXPECT_EQ(rep.merged_into, 0);
  EXPECT_GE(rep.merge_relocalized, 3);
  // Segment 1's keyframes where the truth has them, in segment 0's frame (metres).
  double worst_m = 0.0;
  double worst_deg = 0.0;
  for (std::size_t k = 0; k < s.seg1.size(); ++k) {
    EXPECT_EQ(s.map.keyframe_segment(s.seg1[k]), 0);
    SE3d T;
    ASSERT_TRUE(s.map.keyframe_pose(s.seg1[k], T));
    worst_m = std::max(worst_m, (T.translation() - s.seg1_true[k].translation()).norm());
    worst_deg = std::max(
        worst_deg,
        kDegPerRad * Eigen::AngleAxisd(T.linear().transpose() * s.seg1_true[k].linear()).angle());
  }
  std::printf(
      "merge from %d keyframes placed: scale %.4f (truth %.4f), worst keyframe %.4f m, "
      "%.3f deg\n",
      rep.merge_relocalized, rep.merge_similarity.s, 1.0 / s.sim_1_0.s, worst_m, worst_deg);
  EXPECT_NEAR(rep.merge_similarity.s * s.sim_1_0.s, 1.0, 0.03);
  EXPECT_LT(worst_m, 0.03);
  EXPECT_LT(worst_deg, 0.5);
  // Welded: the placed keyframes observe the points their relocalization matched, so the
  // joined map's optimizations hold the two sides together.
  EXPECT_GT(rep.fused_observations, 100);
  int observed = 0;
  for (const map::KeyframeId kf : s.seg1) {
    for (std::uint32_t k = 0; k < s.map.keyframe_num_keypoints(kf); ++k) {
      observed += s.map.keyframe_point(kf, k) != map::kNoId ? 1 : 0;
    }
  }
  EXPECT_EQ(observed, rep.fused_observations);
}

// Keyframes at one place (they only turn): their centres cannot measure the scale, the depths
// of the points both segments hold for the same keypoints can.
TEST(LoopMergeRelocalized, DepthRatiosMeasureTheScaleWhereTheCentresCannot) {
  TwoSegments s(0.0, true);
  ASSERT_EQ(s.seg1.size(), 6U);
  const LoopReport rep = merge(s, true);
  ASSERT_TRUE(rep.closed);
  EXPECT_EQ(rep.merged_from, 1);
  std::printf("merge from %d keyframes at one place: scale %.4f (truth %.4f)\n",
              rep.merge_relocalized, rep.merge_similarity.s, 1.0 / s.sim_1_0.s);
  EXPECT_NEAR(rep.merge_similarity.s * s.sim_1_0.s, 1.0, 0.01);
  // Without the points, the same keyframes are refused: nothing measures the scale.
  TwoSegments thin(0.0, false);
  EXPECT_FALSE(merge(thin, true).closed);
}

TEST(LoopMergeRelocalized, WithoutItTheThinSegmentStaysApart) {
  TwoSegments s;
  const LoopReport rep = merge(s, false);
  EXPECT_FALSE(rep.closed);
  EXPECT_EQ(s.map.keyframe_segment(s.seg1[0]), 1);
}

}  // namespace
}  // namespace mer::loop
