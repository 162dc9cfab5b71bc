// Map culling on constructed maps: the redundant-keyframe rule (with its scale condition,
// the anchor and the newest keyframes kept), the recent-point rules (found ratio,
// observations by age), removal at capacity (most redundant keyframes, least observed
// points), and the options' doc lines and ranges.
#include "backend/map_culling.h"

#include <vector>

#include <gtest/gtest.h>

#include "support/doc_check.h"

namespace mer::backend {
namespace {

constexpr int kKeypoints = 32;

map::MapOptions map_options(int max_keyframes, int max_points) {
  map::MapOptions o;
  o.max_keyframes = max_keyframes;
  o.max_points = max_points;
  o.max_keypoints_per_keyframe = kKeypoints;
  o.max_observations_per_point = 8;
  o.max_covisible_per_keyframe = 16;
  o.cell_table_size = 256;
  o.points_per_cell = 64;
  return o;
}

/// Options with only the rule under test switched on.
CullingOptions rules_off() {
  CullingOptions c;
  c.keyframe_redundancy = 1.0;  // a fraction never exceeds 1
  c.point_recent_keyframes = 0;
  c.point_min_observations = 1;
  c.capacity_fraction = 1.0;
  c.keep_newest_keyframes = 1;
  return c;
}

/// Adds a keyframe of kKeypoints keypoints, all on pyramid `level`.
map::KeyframeId add_kf(map::Map& m, int level = 0, std::uint16_t segment = 0) {
  std::vector<features::Keypoint> kps(kKeypoints);
  std::vector<features::Descriptor> descs(kKeypoints);
  for (int i = 0; i < kKeypoints; ++i) {
    kps[static_cast<std::size_t>(i)].x = static_cast<float>(10 * i);
    kps[static_cast<std::size_t>(i)].y = 100.0F;
    kps[static_cast<std::size_t>(i)].level = static_cast<std::int8_t>(level);
    kps[static_cast<std::size_t>(i)].scale = 1.0F;
    descs[static_cast<std::size_t>(i)] = {static_cast<std::uint64_t>(i), 1, 2, 3};
  }
  map::KeyframeInput in;
  in.seq = m.keyframes_added();
  in.t_ns = static_cast<std::int64_t>(in.seq) * 1000;
  in.T_w_c.translation() = Eigen::Vector3d(0.1 * static_cast<double>(in.seq), 0.0, 0.0);
  in.keypoints = kps;
  in.descriptors = descs;
  in.segment = segment;
  const Result<map::KeyframeId> r = m.add_keyframe(in);
  EXPECT_TRUE(r.is_ok()) << r.status().message();
  return r.is_ok() ? r.value() : map::kNoId;
}

/// A point created at keypoint `kp` of views[0] and observed at the same keypoint by the rest.
map::PointId add_point(map::Map& m, const std::vector<map::KeyframeId>& views, std::uint32_t kp) {
  const Result<map::PointId> r =
      m.add_point(Eigen::Vector3d(0.01 * kp, 0.0, 3.0), views.front(), kp);
  EXPECT_TRUE(r.is_ok()) << r.status().message();
  if (!r.is_ok()) return map::kNoId;
  for (std::size_t v = 1; v < views.size(); ++v)
    EXPECT_TRUE(m.add_observation(r.value(), views[v], kp));
  return r.value();
}

// Eight keyframes: points 0-9 seen by k0..k4 and k7 (returned), points 10-19 by k2 and k6
// only. With redundancy_options(), one pass removes k1, k3 and k4.
std::vector<map::PointId> redundant_map(map::Map& m, std::vector<map::KeyframeId>& k,
                                        std::uint16_t segment = 0) {
  for (int i = 0; i < 8; ++i) k.push_back(add_kf(m, 0, segment));
  std::vector<map::PointId> shared;
  for (std::uint32_t i = 0; i < 10; ++i)
    shared.push_back(add_point(m, {k[0], k[1], k[2], k[3], k[4], k[7]}, i));
  for (std::uint32_t i = 10; i < 20; ++i) add_point(m, {k[2], k[6]}, i);
  for (const map::KeyframeId kf : k) m.update_covisibility(kf);
  return shared;
}

CullingOptions redundancy_options() {
  CullingOptions o = rules_off();
  o.keyframe_redundancy = 0.9;
  o.keep_newest_keyframes = 3;  // serials 5, 6, 7
  o.point_min_observations = 2;
  return o;
}

TEST(MapCulling, RedundantKeyframesAreRemovedButNotTheAnchorNorTheNewest) {
  map::Map m(map_options(16, 200));
  std::vector<map::KeyframeId> k;
  const std::vector<map::PointId> shared = redundant_map(m, k);
  MapCuller c(redundancy_options(), m);
  EXPECT_DOUBLE_EQ(c.redundancy(k[1]), 1.0);
  EXPECT_DOUBLE_EQ(c.redundancy(k[2]), 0.5);
  const CullingReport rep = c.spin_once(k[7]);
  // Candidates in covisibility order k0 (anchor), k1, k2, k3, k4: removing k1 and k3 leaves
  // the shared points 4 observers, still enough for k4 (3 others); k2 is half its own.
  EXPECT_EQ(rep.culled_keyframes, 3);
  for (const int i : {1, 3, 4})
    EXPECT_FALSE(m.keyframe_is_live(k[static_cast<std::size_t>(i)])) << i;
  for (const int i : {0, 2, 5, 6, 7})
    EXPECT_TRUE(m.keyframe_is_live(k[static_cast<std::size_t>(i)])) << i;
  EXPECT_EQ(rep.checked_keyframes, 4);
  EXPECT_EQ(rep.orphaned_points, 0);
  for (const map::PointId p : shared) EXPECT_EQ(m.point_num_observations(p), 3u);
  EXPECT_EQ(c.totals().culled_keyframes, 3u);
  // Each removed keyframe keeps its pose relative to a keyframe that was live then (keyframe
  // i sits at x = 0.1 i, stamped 1000 i ns), for the re-anchored trajectory.
  ASSERT_EQ(c.lineage().size(), 3U);
  for (const CulledKeyframe& rec : c.lineage()) {
    EXPECT_TRUE(rec.t_ns == 1000 || rec.t_ns == 3000 || rec.t_ns == 4000) << rec.t_ns;
    EXPECT_NE(rec.parent_t_ns, rec.t_ns);
    const double x_parent = 0.1 * static_cast<double>(rec.parent_t_ns / 1000);
    EXPECT_NEAR(x_parent + rec.T_parent_kf.translation().x(),
                0.1 * static_cast<double>(rec.t_ns / 1000), 1e-12);
    EXPECT_TRUE(rec.T_parent_kf.linear().isIdentity(1e-12));
  }
  // A second pass finds nothing more to remove.
  EXPECT_EQ(c.spin_once(k[7]).culled_keyframes, 0);
  EXPECT_EQ(c.lineage().size(), 3U);
}

// A lineage record says the segment its offset was measured in (a later merge rescales it),
// and its parent is of that segment: the newest keyframe, another segment's, is not taken
// when the removed keyframe has no live covisible one.
TEST(MapCulling, LineageStaysInTheRemovedKeyframesSegment) {
  map::Map m(map_options(16, 200));
  std::vector<map::KeyframeId> k;
  (void)redundant_map(m, k, 1);
  MapCuller c(redundancy_options(), m);
  EXPECT_EQ(c.spin_once(k[7]).culled_keyframes, 3);
  ASSERT_EQ(c.lineage().size(), 3U);
  for (const CulledKeyframe& rec : c.lineage()) EXPECT_EQ(rec.segment, 1U) << rec.t_ns;

  // Two keyframes of segment 0 (the first the anchor), then two of segment 1, no points:
  // at capacity the middle two go. Each has no covisible keyframe, so the newest keyframe
  // would carry it on; it is of segment 1, so only segment 1's removed keyframe gets a record.
  map::Map m2(map_options(4, 200));
  CullingOptions o = rules_off();
  o.capacity_fraction = 0.5;  // 2 of 4 keyframes
  o.keep_newest_keyframes = 1;
  const map::KeyframeId a0 = add_kf(m2, 0, 0);
  const map::KeyframeId a1 = add_kf(m2, 0, 0);
  const map::KeyframeId b0 = add_kf(m2, 0, 1);
  const map::KeyframeId b1 = add_kf(m2, 0, 1);
  MapCuller c2(o, m2);
  EXPECT_EQ(c2.spin_once(b1).capacity_keyframes, 2);
  EXPECT_TRUE(m2.keyframe_is_live(a0));
  EXPECT_FALSE(m2.keyframe_is_live(a1));
  EXPECT_FALSE(m2.keyframe_is_live(b0));
  ASSERT_EQ(c2.lineage().size(), 1U);
  EXPECT_EQ(c2.lineage()[0].t_ns, 2000);         // b0
  EXPECT_EQ(c2.lineage()[0].parent_t_ns, 3000);  // b1
  EXPECT_EQ(c2.lineage()[0].segment, 1U);
}

TEST(MapCulling, LineageIsABoundedRing) {
  map::Map m(map_options(16, 200));
  std::vector<map::KeyframeId> k;
  (void)redundant_map(m, k);
  CullingOptions o = redundancy_options();
  o.lineage_capacity = 2;
  MapCuller c(o, m);
  EXPECT_EQ(c.spin_once(k[7]).culled_keyframes, 3);
  EXPECT_EQ(c.lineage().size(), 2U) << "the oldest record is forgotten";
  o.lineage_capacity = 0;
  map::Map m2(map_options(16, 200));
  MapCuller off(o, m2);
  EXPECT_TRUE(off.lineage().empty());
}

TEST(MapCulling, RedundancyCountsOnlyObservationsAtTheSameOrAFinerScale) {
  map::Map m(map_options(8, 64));
  const map::KeyframeId fine = add_kf(m, 0);
  std::vector<map::KeyframeId> coarse;
  for (int i = 0; i < 3; ++i) coarse.push_back(add_kf(m, 2));
  for (std::uint32_t i = 0; i < 8; ++i) add_point(m, {fine, coarse[0], coarse[1], coarse[2]}, i);
  CullingOptions o = rules_off();
  o.redundant_level_slack = 1;
  MapCuller strict(o, m);
  EXPECT_DOUBLE_EQ(strict.redundancy(fine), 0.0);       // the others see it two levels coarser
  EXPECT_DOUBLE_EQ(strict.redundancy(coarse[0]), 1.0);  // finer and equal levels count
  o.redundant_level_slack = 2;
  MapCuller loose(o, m);
  EXPECT_DOUBLE_EQ(loose.redundancy(fine), 1.0);
}

TEST(MapCulling, RecentPointsAreCulledByFoundRatioAndObservations) {
  map::Map m(map_options(16, 64));
  std::vector<map::KeyframeId> k;
  k.push_back(add_kf(m));
  const map::PointId old_single = add_point(m, {k[0]}, 0);
  for (int i = 0; i < 4; ++i) k.push_back(add_kf(m));
  // Created with the fifth keyframe (age 0 now).
  const map::PointId rarely_found = add_point(m, {k[4], k[3]}, 1);
  const map::PointId often_found = add_point(m, {k[4], k[3]}, 2);
  const map::PointId single = add_point(m, {k[4]}, 3);
  for (int i = 0; i < 10; ++i) m.note_visible(rarely_found);
  m.note_found(rarely_found);  // (1 + 1) / (1 + 10) < 0.25
  for (int i = 0; i < 3; ++i) {
    m.note_visible(often_found);
    m.note_found(often_found);
  }

  CullingOptions o = rules_off();
  o.point_recent_keyframes = 3;
  o.point_min_found_ratio = 0.25;
  o.point_check_after_keyframes = 2;
  o.point_min_observations = 2;
  MapCuller c(o, m);
  // Age 0: the tracker has not looked for them yet.
  EXPECT_EQ(c.spin_once(map::kNoId).culled_points, 0);
  k.push_back(add_kf(m));  // age 1: the ratio rule applies
  EXPECT_EQ(c.spin_once(map::kNoId).culled_points, 1);
  EXPECT_TRUE(m.point_is_bad(rarely_found));
  EXPECT_FALSE(m.point_is_bad(single));  // too young for the observation rule
  k.push_back(add_kf(m));                // age 2: the observation rule applies
  EXPECT_EQ(c.spin_once(map::kNoId).culled_points, 1);
  EXPECT_TRUE(m.point_is_bad(single));
  EXPECT_FALSE(m.point_is_bad(often_found));
  EXPECT_FALSE(m.point_is_bad(old_single));  // older than point_recent_keyframes: not checked
  EXPECT_EQ(c.totals().culled_points, 2u);
}

TEST(MapCulling, AtCapacityTheMostRedundantKeyframesGo) {
  map::Map m(map_options(10, 400));
  std::vector<map::KeyframeId> k;
  for (int i = 0; i < 10; ++i) k.push_back(add_kf(m));
  // A chain of points seen by consecutive keyframes (never redundant); a group seen by
  // k3, k4, k5 and k7 (redundant in each of them).
  for (std::size_t i = 0; i + 1 < k.size(); ++i) {
    for (std::uint32_t p = 0; p < 4; ++p) add_point(m, {k[i], k[i + 1]}, (i % 2 == 0 ? 0 : 4) + p);
  }
  for (std::uint32_t p = 0; p < 8; ++p) add_point(m, {k[3], k[4], k[5], k[7]}, 16 + p);
  CullingOptions o = rules_off();
  o.capacity_fraction = 0.8;  // 8 live keyframes
  o.keep_newest_keyframes = 2;
  o.max_capacity_removals = 1;
  MapCuller c(o, m);
  // Each pass removes the removable keyframe (not k0, not the 2 newest) of largest
  // redundancy, the oldest on a tie.
  for (int pass = 0; pass < 2; ++pass) {
    map::KeyframeId expected = map::kNoId;
    double best = -1.0;
    for (std::size_t i = 1; i + 2 < k.size(); ++i) {
      if (!m.keyframe_is_live(k[i])) continue;
      const double r = c.redundancy(k[i]);
      if (r > best) {
        best = r;
        expected = k[i];
      }
    }
    if (pass == 0) {
      EXPECT_EQ(expected, k[3]);  // its whole group is redundant, its chain points are not
    } else {
      EXPECT_EQ(expected, k[1]);  // nothing redundant left: the oldest removable goes
    }
    const CullingReport rep = c.spin_once(k[9]);
    EXPECT_EQ(rep.capacity_keyframes, 1) << pass;
    EXPECT_FALSE(m.keyframe_is_live(expected)) << pass;
  }
  EXPECT_EQ(m.live_keyframes(), 8u);
  EXPECT_EQ(c.spin_once(k[9]).capacity_keyframes, 0);  // at the limit: nothing more
  for (const std::size_t i : {0U, 8U, 9U}) EXPECT_TRUE(m.keyframe_is_live(k[i])) << i;
  // The slots are reused by the next keyframes (no reader registered: at once).
  EXPECT_NE(add_kf(m), map::kNoId);
  EXPECT_EQ(m.counters().reused_keyframe_slots, 1u);
}

TEST(MapCulling, AtCapacityTheLeastObservedPointsGo) {
  map::Map m(map_options(16, 50));
  std::vector<map::KeyframeId> k;
  for (int i = 0; i < 5; ++i) k.push_back(add_kf(m));
  // Point i has 1 + i % 4 observations.
  std::vector<map::PointId> pts;
  for (std::uint32_t i = 0; i < 32; ++i) {
    std::vector<map::KeyframeId> views{k[0]};
    for (std::uint32_t v = 1; v <= i % 4; ++v) views.push_back(k[v]);
    pts.push_back(add_point(m, views, i));
  }
  for (std::uint32_t i = 0; i < 18; ++i) pts.push_back(add_point(m, {k[4]}, i));  // 50 in all
  ASSERT_EQ(m.live_points(), 50u);
  for (int i = 0; i < 4; ++i) k.push_back(add_kf(m));  // all points older than recent (3)
  CullingOptions o = rules_off();
  o.point_recent_keyframes = 3;
  o.point_min_observations = 1;
  o.capacity_fraction = 0.5;  // 25 live points
  MapCuller c(o, m);
  const CullingReport rep = c.spin_once(map::kNoId);
  EXPECT_EQ(rep.capacity_points, 25);
  EXPECT_EQ(m.live_points(), 25u);
  // The 26 single-observation points (8 + 18) were the candidates: 25 go, lowest ids first.
  int single_left = 0;
  for (const map::PointId p : pts) {
    if (!m.point_is_bad(p)) single_left += m.point_num_observations(p) == 1 ? 1 : 0;
  }
  EXPECT_EQ(single_left, 1);
  for (std::uint32_t i = 0; i < 32; ++i) {
    if (i % 4 != 0) {
      EXPECT_FALSE(m.point_is_bad(pts[i])) << i;
    }
  }
}

TEST(MapCulling, DisabledDoesNothingAndAutoResolvesByDepth) {
  map::Map m(map_options(8, 64));
  const map::KeyframeId a = add_kf(m);
  add_kf(m);
  CullingOptions o;
  o.enabled = false;
  MapCuller off(o, m);
  EXPECT_FALSE(off.spin_once(a).ran);
  CullingOptions autos;
  EXPECT_EQ(autos.point_min_observations, 0);
  EXPECT_EQ(MapCuller(autos, m, false).options().point_min_observations, 3);
  EXPECT_EQ(MapCuller(autos, m, true).options().point_min_observations, 1);
}

// The keyframes of a discarded segment (a failed start) go on the next pass, culling on or
// off, without a lineage (their frames are lost, not re-anchored); points only they saw go
// with them. The map's newest keyframe waits for a later pass.
TEST(MapCulling, DiscardedSegmentsKeyframesAreRemoved) {
  map::Map m(map_options(16, 200));
  const map::KeyframeId a = add_kf(m);
  const map::KeyframeId b = add_kf(m);
  const map::KeyframeId d1 = add_kf(m, 0, 1);
  const map::KeyframeId d2 = add_kf(m, 0, 1);
  const map::PointId own = add_point(m, {d1, d2}, 0);
  const map::PointId kept = add_point(m, {a, b}, 1);
  CullingOptions o = rules_off();
  o.enabled = false;
  MapCuller c(o, m);
  EXPECT_FALSE(c.spin_once(b).ran);  // nothing discarded: culling off does nothing
  ASSERT_TRUE(m.discard_segment(1));
  CullingReport rep = c.spin_once(b);
  // d2 is the map's newest keyframe: kept for now.
  EXPECT_EQ(rep.discarded_keyframes, 1);
  EXPECT_FALSE(m.keyframe_is_live(d1));
  EXPECT_TRUE(m.keyframe_is_live(d2));
  const map::KeyframeId e = add_kf(m);
  rep = c.spin_once(e);
  EXPECT_EQ(rep.discarded_keyframes, 1);
  EXPECT_EQ(rep.culled_keyframes, 0);
  EXPECT_FALSE(m.keyframe_is_live(d2));
  map::PointView v;
  EXPECT_FALSE(m.read_point(own, v));
  EXPECT_TRUE(m.read_point(kept, v));
  for (const map::KeyframeId k : {a, b, e}) EXPECT_TRUE(m.keyframe_is_live(k)) << k;
  EXPECT_EQ(c.totals().discarded_keyframes, 2U);
  EXPECT_EQ(c.totals().culled_keyframes, 0U);
  EXPECT_TRUE(c.lineage().empty());
}

TEST(MapCulling, EveryOptionHasADocLineAndRange) {
  testing::DocCheck v;
  CullingOptions o;
  o.visit(v);
  EXPECT_EQ(v.fields, 12);
}

}  // namespace
}  // namespace mer::backend
