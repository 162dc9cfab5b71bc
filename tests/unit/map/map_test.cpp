// Map: options, keyframes and points, associations, descriptors, covisibility, cell moves,
// keyframe removal, slot reuse gated by registered readers and stale-id detection by
// generation, zero allocations after construction and how tight query_visible's superset is (its
// time: tests/bench/map_bench.cpp).
#include "map/map.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <mutex>
#include <random>
#include <set>
#include <vector>

#include <gtest/gtest.h>

#include "platform/alloc_counter.h"
#include "support/doc_check.h"

namespace mer::map {
namespace {

MapOptions small_options() {
  MapOptions o;
  o.max_keyframes = 8;
  o.max_points = 64;
  o.max_keypoints_per_keyframe = 32;
  o.max_observations_per_point = 6;
  o.max_covisible_per_keyframe = 4;
  o.cell_table_size = 256;
  o.points_per_cell = 8;
  return o;
}

features::Descriptor descriptor_of(std::uint64_t seed) {
  std::mt19937_64 rng(seed);
  return {rng(), rng(), rng(), rng()};
}

/// A keyframe with n keypoints at (i, 2i) px, descriptors from (kf_seed, i), depth i + 1.
struct KfData {
  std::vector<features::Keypoint> kps;
  std::vector<features::Descriptor> desc;
  std::vector<float> depth;
  KeyframeInput input(const SE3d& T, std::uint64_t seq) const {
    KeyframeInput in;
    in.seq = seq;
    in.t_ns = static_cast<std::int64_t>(seq) * 1000;
    in.T_w_c = T;
    in.keypoints = kps;
    in.descriptors = desc;
    in.depth = depth;
    return in;
  }
};

KfData make_kf(int n, std::uint64_t seed) {
  KfData d;
  for (int i = 0; i < n; ++i) {
    features::Keypoint k;
    k.x = static_cast<float>(i);
    k.y = static_cast<float>(2 * i);
    k.level = static_cast<std::int8_t>(i % 3);
    k.scale = i % 3 == 0 ? 1.0F : (i % 3 == 1 ? 1.2F : 1.44F);
    d.kps.push_back(k);
    d.desc.push_back(descriptor_of(seed * 1000 + static_cast<std::uint64_t>(i)));
    d.depth.push_back(static_cast<float>(i + 1));
  }
  return d;
}

SE3d pose_at(double x, double yaw) {
  return make_se3(Eigen::Quaterniond(Eigen::AngleAxisd(yaw, Eigen::Vector3d::UnitY())),
                  Eigen::Vector3d(x, 0.1 * x, 0.0));
}

KeyframeId add_kf(Map& m, const KfData& d, const SE3d& T, std::uint64_t seq) {
  Result<KeyframeId> r = m.add_keyframe(d.input(T, seq));
  EXPECT_TRUE(r.is_ok()) << r.status().message();
  return r.is_ok() ? r.value() : kNoId;
}

PointId add_pt(Map& m, const Eigen::Vector3d& p, KeyframeId kf, std::uint32_t kp) {
  Result<PointId> r = m.add_point(p, kf, kp);
  EXPECT_TRUE(r.is_ok()) << r.status().message();
  return r.is_ok() ? r.value() : kNoId;
}

// ---- options ----------------------------------------------------------------------------

TEST(MapOptions, ValidationNamesTheKey) {
  EXPECT_TRUE(validate(MapOptions{}).is_ok());
  MapOptions o;
  o.max_points = 0;
  Status s = validate(o);
  ASSERT_FALSE(s.is_ok());
  EXPECT_EQ(s.code(), StatusCode::kInvalidArgument);
  EXPECT_NE(s.message().find("map.max_points"), std::string::npos) << s.message();

  o = MapOptions{};
  o.cell_table_size = 50000;
  s = validate(o);
  ASSERT_FALSE(s.is_ok());
  EXPECT_NE(s.message().find("map.cell_table_size"), std::string::npos) << s.message();
  EXPECT_NE(s.message().find("power of two"), std::string::npos) << s.message();
  EXPECT_EQ(effective_options(o).cell_table_size, 65536);

  o = MapOptions{};
  o.cell_size = 0.0;
  s = validate(o);
  EXPECT_NE(s.message().find("map.cell_size"), std::string::npos) << s.message();
  EXPECT_DOUBLE_EQ(effective_options(o).cell_size, 1e-3);
}

TEST(MapOptions, EveryFieldHasADocLineAndRange) {
  testing::DocCheck v;
  MapOptions o;
  o.visit(v);
  EXPECT_EQ(v.fields, 9);
}

// ---- keyframes ---------------------------------------------------------------------------

TEST(Map, AddKeyframeStoresEverything) {
  Map m(small_options());
  EXPECT_EQ(m.num_keyframes(), 0u);
  const KfData d = make_kf(10, 1);
  const SE3d T = pose_at(1.0, 0.3);
  const KeyframeId kf = add_kf(m, d, T, 42);
  ASSERT_EQ(kf, 0u);
  EXPECT_EQ(m.num_keyframes(), 1u);
  EXPECT_EQ(m.keyframe_seq(kf), 42u);
  EXPECT_EQ(m.keyframe_t_ns(kf), 42000);
  ASSERT_EQ(m.keyframe_keypoints(kf).size(), 10u);
  EXPECT_EQ(m.keyframe_keypoints(kf)[3].y, 6.0F);
  EXPECT_EQ(m.keyframe_descriptors(kf)[7], d.desc[7]);
  EXPECT_EQ(m.keyframe_num_keypoints(kf), 10u);
  EXPECT_EQ(m.keyframe_point(kf, 3), kNoId);
  EXPECT_EQ(m.keyframe_depth(kf, 4), 5.0F);
  EXPECT_EQ(m.keyframe_depth_confidence(kf, 4), 0.0F);
  SE3d got;
  double scale = 0.0;
  ASSERT_TRUE(m.keyframe_pose(kf, got, &scale));
  EXPECT_TRUE(got.isApprox(T, 1e-15));
  EXPECT_EQ(scale, 1.0);
  // Unknown ids.
  EXPECT_FALSE(m.keyframe_pose(1, got));
  EXPECT_TRUE(m.keyframe_keypoints(1).empty());
  EXPECT_EQ(m.keyframe_point(kf, 10), kNoId);
  EXPECT_EQ(m.keyframe_depth(kf, 10), 0.0F);

  // 3D-3D: depth * K^-1 [u v 1].
  const geometry::Pinhole K{400, 400, 3, 4};
  Eigen::Vector3d p_c;
  ASSERT_TRUE(m.keyframe_point_3d(kf, 5, K, p_c));  // u = 5, v = 10, depth 6
  EXPECT_TRUE(p_c.isApprox(Eigen::Vector3d(6.0 * 2 / 400, 6.0 * 6 / 400, 6.0)));
  m.set_keyframe_depth(kf, 5, 0.0F, 0.0F);
  EXPECT_FALSE(m.keyframe_point_3d(kf, 5, K, p_c));
  m.set_keyframe_depth(kf, 5, 2.5F, 0.75F);
  EXPECT_EQ(m.keyframe_depth(kf, 5), 2.5F);
  EXPECT_EQ(m.keyframe_depth_confidence(kf, 5), 0.75F);

  const SE3d T2 = pose_at(-2.0, -0.7);
  m.set_keyframe_pose(kf, T2, 1.5);
  ASSERT_TRUE(m.keyframe_pose(kf, got, &scale));
  EXPECT_TRUE(got.isApprox(T2, 1e-15));
  EXPECT_EQ(scale, 1.5);
}

TEST(Map, KeyframesKeepTheirSegmentAndPosesListByIt) {
  Map m(small_options());
  const KfData d = make_kf(4, 1);
  KeyframeInput a = d.input(pose_at(0.0, 0.0), 10);
  KeyframeInput b = d.input(pose_at(1.0, 0.1), 20);
  b.segment = 1;
  KeyframeInput c = d.input(pose_at(2.0, 0.2), 30);
  const KeyframeId ka = m.add_keyframe(a).value();
  const KeyframeId kb = m.add_keyframe(b).value();
  const KeyframeId kc = m.add_keyframe(c).value();
  EXPECT_EQ(m.keyframe_segment(ka), 0);
  EXPECT_EQ(m.keyframe_segment(kb), 1);
  EXPECT_EQ(m.keyframe_segment(kc), 0);
  EXPECT_EQ(m.keyframe_segment(7), kNoSegment) << "a free slot has no segment";
  EXPECT_EQ(m.keyframe_segment(kNoId), kNoSegment);
  EXPECT_EQ(m.live_keyframe_poses().size(), 3U);
  const std::vector<StampedPose> s0 = m.live_keyframe_poses(0);
  ASSERT_EQ(s0.size(), 2U);
  EXPECT_EQ(s0[0].t_ns, 10000);
  EXPECT_EQ(s0[1].t_ns, 30000);
  const std::vector<StampedPose> s1 = m.live_keyframe_poses(1);
  ASSERT_EQ(s1.size(), 1U);
  EXPECT_EQ(s1[0].t_ns, 20000);
  EXPECT_TRUE(m.live_keyframe_poses(2).empty());
}

TEST(Map, KeypointMoveChangesOnlyThatKeypoint) {
  Map m(small_options());
  const KfData d = make_kf(10, 1);
  const KeyframeId kf = add_kf(m, d, pose_at(1.0, 0.3), 42);
  ASSERT_TRUE(m.set_keypoint_position(kf, 3, 7.25F, -1.5F));
  EXPECT_EQ(m.keyframe_keypoints(kf)[3].x, 7.25F);
  EXPECT_EQ(m.keyframe_keypoints(kf)[3].y, -1.5F);
  EXPECT_EQ(m.keyframe_keypoints(kf)[3].level, d.kps[3].level);
  EXPECT_EQ(m.keyframe_keypoints(kf)[2].x, d.kps[2].x);
  EXPECT_EQ(m.keyframe_keypoints(kf)[4].y, d.kps[4].y);
  EXPECT_FALSE(m.set_keypoint_position(kf, 10, 0.0F, 0.0F));     // no such keypoint
  EXPECT_FALSE(m.set_keypoint_position(kf + 1, 0, 0.0F, 0.0F));  // no such keyframe
  EXPECT_FALSE(m.set_keypoint_position(kf, 0, std::nanf(""), 0.0F));
  EXPECT_EQ(m.keyframe_keypoints(kf)[0].x, d.kps[0].x);
}

TEST(Map, AnchoredMarkIsClearedWithItsPoint) {
  Map m(small_options());
  const KfData d = make_kf(10, 1);
  const KeyframeId kf = add_kf(m, d, pose_at(1.0, 0.3), 42);
  EXPECT_EQ(m.keyframe_keypoints(kf)[3].anchored, 0);  // a detection
  const auto p = m.add_point(Eigen::Vector3d(0.1, 0.2, 3.0), kf, 3);
  ASSERT_TRUE(p.is_ok());
  ASSERT_TRUE(m.set_keypoint_anchored(kf, 3, true));
  ASSERT_TRUE(m.set_keypoint_anchored(kf, 4, true));
  EXPECT_FALSE(m.set_keypoint_anchored(kf, 10, true));  // no such keypoint
  EXPECT_EQ(m.keyframe_keypoints(kf)[3].anchored, 1);
  // Freeing the point clears the mark of its keypoint only: a later association of that
  // keypoint starts as a detection.
  m.set_point_bad(p.value());
  EXPECT_EQ(m.keyframe_keypoints(kf)[3].anchored, 0);
  EXPECT_EQ(m.keyframe_keypoints(kf)[4].anchored, 1);
  ASSERT_TRUE(m.set_keypoint_anchored(kf, 4, false));
  EXPECT_EQ(m.keyframe_keypoints(kf)[4].anchored, 0);
}

TEST(Map, AddKeyframeErrorsNameTheOption) {
  MapOptions o = small_options();
  o.max_keyframes = 2;
  Map m(o);
  const KfData too_many = make_kf(33, 1);
  Result<KeyframeId> r = m.add_keyframe(too_many.input(SE3d::Identity(), 0));
  ASSERT_FALSE(r.is_ok());
  EXPECT_NE(r.status().message().find("map.max_keypoints_per_keyframe"), std::string::npos)
      << r.status().message();

  KfData bad = make_kf(5, 1);
  bad.desc.pop_back();
  r = m.add_keyframe(bad.input(SE3d::Identity(), 0));
  EXPECT_FALSE(r.is_ok());
  EXPECT_EQ(m.num_keyframes(), 0u);

  const KfData d = make_kf(5, 1);
  add_kf(m, d, SE3d::Identity(), 0);
  add_kf(m, d, SE3d::Identity(), 1);
  r = m.add_keyframe(d.input(SE3d::Identity(), 2));
  ASSERT_FALSE(r.is_ok());
  EXPECT_NE(r.status().message().find("map.max_keyframes"), std::string::npos)
      << r.status().message();
  EXPECT_EQ(m.num_keyframes(), 2u);
}

// ---- points ----------------------------------------------------------------------------

TEST(Map, AddPointAssociatesAndReads) {
  Map m(small_options());
  const KfData d = make_kf(10, 1);
  const SE3d T = pose_at(0.0, 0.0);
  const KeyframeId kf = add_kf(m, d, T, 0);
  const Eigen::Vector3d p_w(0.3, -0.2, 2.0);
  const PointId p = add_pt(m, p_w, kf, 4);  // keypoint 4: level 1, scale 1.2
  ASSERT_EQ(p, 0u);
  EXPECT_EQ(m.num_points(), 1u);
  EXPECT_EQ(m.keyframe_point(kf, 4), p);
  PointView v;
  ASSERT_TRUE(m.read_point(p, v));
  EXPECT_EQ(v.p_w, p_w);
  EXPECT_EQ(v.descriptor, d.desc[4]);
  EXPECT_EQ(v.ref_keyframe, kf);
  EXPECT_EQ(v.ref_keypoint, 4u);
  EXPECT_TRUE(v.normal.isApprox(p_w.normalized().cast<float>(), 1e-6F));
  EXPECT_NEAR(v.max_distance, p_w.norm() * 1.2, 1e-5);
  EXPECT_NEAR(v.min_distance, v.max_distance / m.options().distance_scale_range, 1e-5);
  EXPECT_FALSE(m.point_is_bad(p));
  EXPECT_TRUE(m.point_is_bad(1));  // unpublished
  EXPECT_FALSE(m.read_point(1, v));

  std::pair<KeyframeId, std::uint32_t> obs[8];
  ASSERT_EQ(m.point_observations(p, obs), 1u);
  EXPECT_EQ(obs[0], std::make_pair(kf, 4u));

  // The keypoint is taken; bad ids; non-finite position.
  EXPECT_FALSE(m.add_point(p_w, kf, 4).is_ok());
  EXPECT_FALSE(m.add_point(p_w, kf, 10).is_ok());
  EXPECT_FALSE(m.add_point(p_w, 3, 0).is_ok());
  EXPECT_FALSE(m.add_point(Eigen::Vector3d(NAN, 0, 0), kf, 5).is_ok());
  EXPECT_EQ(m.num_points(), 1u);

  PointId buf[8];
  ASSERT_EQ(m.query_radius(p_w, 0.01, 0, buf), 1u);
  EXPECT_EQ(buf[0], p);
}

// Two segments' points at the same coordinates (their world frames overlap): each lands in
// its own segment's cells, a query returns the asked segment's only, and moving a point keeps
// it in its segment.
TEST(Map, CellQueriesKeepSegmentsApart) {
  Map m(small_options());
  const KfData d = make_kf(8, 1);
  KeyframeInput in0 = d.input(SE3d::Identity(), 1);
  KeyframeInput in1 = d.input(SE3d::Identity(), 2);
  in1.segment = 1;
  const Result<KeyframeId> kf0 = m.add_keyframe(in0);
  const Result<KeyframeId> kf1 = m.add_keyframe(in1);
  ASSERT_TRUE(kf0.is_ok() && kf1.is_ok());
  std::vector<PointId> seg0;
  std::vector<PointId> seg1;
  for (std::uint32_t k = 0; k < 4; ++k) {
    const Eigen::Vector3d p_w(0.01 * k, 0.0, 2.0);
    const Result<PointId> a = m.add_point(p_w, kf0.value(), k);
    const Result<PointId> b = m.add_point(p_w, kf1.value(), k);
    ASSERT_TRUE(a.is_ok() && b.is_ok());
    seg0.push_back(a.value());
    seg1.push_back(b.value());
  }
  const geometry::Pinhole K{300.0, 300.0, 320.0, 240.0};
  PointId buf[16];
  for (const std::uint16_t segment : {std::uint16_t{0}, std::uint16_t{1}}) {
    const std::vector<PointId>& want = segment == 0 ? seg0 : seg1;
    std::size_t n = m.query_visible(SE3d::Identity(), K, 640, 480, 0.1, 5.0, segment, buf);
    EXPECT_EQ(std::set<PointId>(buf, buf + n), std::set<PointId>(want.begin(), want.end()));
    n = m.query_radius(Eigen::Vector3d(0.0, 0.0, 2.0), 0.1, segment, buf);
    EXPECT_EQ(std::set<PointId>(buf, buf + n), std::set<PointId>(want.begin(), want.end()));
    // A 4-id output is not taken by the other segment's points.
    n = m.query_visible(SE3d::Identity(), K, 640, 480, 0.1, 5.0, segment, std::span(buf, 4));
    EXPECT_EQ(std::set<PointId>(buf, buf + n), std::set<PointId>(want.begin(), want.end()));
  }
  {
    std::lock_guard<platform::PiMutex> lock(m.writer_lock());
    m.set_point_position(seg1[0], Eigen::Vector3d(3.0, 0.0, 2.0));
  }
  EXPECT_EQ(m.query_radius(Eigen::Vector3d(3.0, 0.0, 2.0), 0.1, 0, buf), 0U);
  ASSERT_EQ(m.query_radius(Eigen::Vector3d(3.0, 0.0, 2.0), 0.1, 1, buf), 1U);
  EXPECT_EQ(buf[0], seg1[0]);
}

TEST(Map, PointsFullNamesTheOption) {
  MapOptions o = small_options();
  o.max_points = 3;
  Map m(o);
  const KeyframeId kf = add_kf(m, make_kf(10, 1), SE3d::Identity(), 0);
  for (std::uint32_t i = 0; i < 3; ++i) add_pt(m, Eigen::Vector3d(0, 0, 1.0 + i), kf, i);
  Result<PointId> r = m.add_point(Eigen::Vector3d(0, 0, 1), kf, 5);
  ASSERT_FALSE(r.is_ok());
  EXPECT_NE(r.status().message().find("map.max_points"), std::string::npos) << r.status().message();
}

TEST(Map, ObservationRules) {
  MapOptions o = small_options();
  o.max_observations_per_point = 3;
  Map m(o);
  const KfData d = make_kf(10, 1);
  std::vector<KeyframeId> kfs;
  for (int i = 0; i < 5; ++i) kfs.push_back(add_kf(m, d, pose_at(i, 0), i));
  const PointId p = add_pt(m, Eigen::Vector3d(0, 0, 3), kfs[0], 0);
  EXPECT_FALSE(m.add_observation(p, kfs[0], 1));  // already observed by kf 0
  EXPECT_TRUE(m.add_observation(p, kfs[1], 2));
  EXPECT_FALSE(m.add_observation(p, kfs[2], 2 + 100));  // bad keypoint
  EXPECT_FALSE(m.add_observation(p + 1, kfs[2], 2));    // unknown point
  const PointId q = add_pt(m, Eigen::Vector3d(0, 0, 4), kfs[2], 2);
  EXPECT_FALSE(m.add_observation(p, kfs[2], 2));  // keypoint taken by q
  EXPECT_TRUE(m.add_observation(p, kfs[2], 3));
  EXPECT_FALSE(m.add_observation(p, kfs[3], 3));  // full (3 observations)
  EXPECT_EQ(m.point_num_observations(p), 3u);
  EXPECT_EQ(m.keyframe_point(kfs[1], 2), p);
  EXPECT_EQ(m.keyframe_point(kfs[2], 2), q);

  m.set_point_bad(p);
  EXPECT_TRUE(m.point_is_bad(p));
  PointView v;
  EXPECT_FALSE(m.read_point(p, v));
  EXPECT_EQ(m.keyframe_point(kfs[0], 0), kNoId);
  EXPECT_EQ(m.keyframe_point(kfs[1], 2), kNoId);
  EXPECT_EQ(m.keyframe_point(kfs[2], 3), kNoId);
  EXPECT_EQ(m.keyframe_point(kfs[2], 2), q);  // untouched
  EXPECT_EQ(m.point_num_observations(p), 0u);
  EXPECT_FALSE(m.add_observation(p, kfs[4], 0));
  PointId buf[8];
  const std::size_t n = m.query_radius(Eigen::Vector3d(0, 0, 3), 0.5, 0, buf);
  EXPECT_EQ(std::count(buf, buf + n, p), 0);
  // The freed keypoint can carry a new point; ids keep increasing.
  EXPECT_EQ(add_pt(m, Eigen::Vector3d(0, 0, 3), kfs[0], 0), q + 1);
}

TEST(Map, MergingDuplicatesMovesObservationsAndFreesTheOther) {
  MapOptions o = small_options();
  o.max_observations_per_point = 3;
  Map m(o);
  const KfData d = make_kf(10, 1);
  std::vector<KeyframeId> kfs;
  for (int i = 0; i < 5; ++i) kfs.push_back(add_kf(m, d, pose_at(i, 0), i));
  // a: kf 0 and 1; b (its duplicate): kf 1 (another keypoint), 2 and 3.
  const PointId a = add_pt(m, Eigen::Vector3d(0, 0, 3), kfs[0], 0);
  ASSERT_TRUE(m.add_observation(a, kfs[1], 0));
  const PointId b = add_pt(m, Eigen::Vector3d(0.01, 0, 3), kfs[1], 1);
  ASSERT_TRUE(m.add_observation(b, kfs[2], 2));
  ASSERT_TRUE(m.add_observation(b, kfs[3], 3));
  EXPECT_EQ(m.merge_points(a, a), -1);

  // kf 1 already sees a: that observation of b is dropped; kf 2 moves; kf 3 would be a's
  // fourth observation (capacity 3) and is dropped.
  EXPECT_EQ(m.merge_points(a, b), 1);
  EXPECT_TRUE(m.point_is_bad(b));
  EXPECT_EQ(m.point_num_observations(a), 3u);
  EXPECT_EQ(m.keyframe_point(kfs[1], 0), a);
  EXPECT_EQ(m.keyframe_point(kfs[1], 1), kNoId);
  EXPECT_EQ(m.keyframe_point(kfs[2], 2), a);
  EXPECT_EQ(m.keyframe_point(kfs[3], 3), kNoId);
  PointView v;
  ASSERT_TRUE(m.read_point(a, v));
  EXPECT_EQ(v.p_w, Eigen::Vector3d(0, 0, 3)) << "the kept point keeps its position";
  EXPECT_EQ(m.counters().merged_points, 1u);
  EXPECT_EQ(m.counters().bad_points, 1u);
  EXPECT_EQ(m.merge_points(a, b), -1) << "b is gone";
  EXPECT_EQ(m.merge_points(b, a), -1);
}

TEST(Map, RepresentativeDescriptorIsTheHammingMedoid) {
  MapOptions o = small_options();
  o.max_observations_per_point = 8;
  Map m(o);
  // Seven keyframes; keypoint 0 of each carries a descriptor near a common base, with
  // different numbers of flipped bits; one of them is the base itself (the medoid).
  const features::Descriptor base = descriptor_of(99);
  const int flips[7] = {40, 9, 0, 30, 5, 60, 12};
  std::vector<features::Descriptor> descs;
  std::mt19937 rng(3);
  for (int k = 0; k < 7; ++k) {
    KfData d = make_kf(4, 10 + static_cast<std::uint64_t>(k));
    features::Descriptor x = base;
    std::vector<int> bits(256);
    for (int b = 0; b < 256; ++b) bits[b] = b;
    std::shuffle(bits.begin(), bits.end(), rng);
    for (int b = 0; b < flips[k]; ++b) {
      x[static_cast<std::size_t>(bits[b] / 64)] ^= 1ULL << (bits[b] % 64);
    }
    d.desc[0] = x;
    descs.push_back(x);
    add_kf(m, d, pose_at(0.2 * k, 0.0), static_cast<std::uint64_t>(k));
  }
  const PointId p = add_pt(m, Eigen::Vector3d(0.5, 0, 3), 0, 0);
  for (KeyframeId k = 1; k < 7; ++k) ASSERT_TRUE(m.add_observation(p, k, 0));
  m.update_point(p);
  PointView v;
  ASSERT_TRUE(m.read_point(p, v));
  // Brute-force medoid (least median distance, median over the row incl. self).
  std::size_t best = 0;
  int best_med = 1 << 30;
  for (std::size_t i = 0; i < descs.size(); ++i) {
    std::vector<int> row;
    for (const auto& dj : descs) row.push_back(features::hamming(descs[i], dj));
    std::sort(row.begin(), row.end());
    const int med = row[(row.size() - 1) / 2];
    if (med < best_med) {
      best_med = med;
      best = i;
    }
  }
  EXPECT_EQ(best, 2u);  // the unflipped base
  EXPECT_EQ(v.descriptor, descs[best]);
  // Normal: mean direction from the 7 camera centres.
  Eigen::Vector3d n = Eigen::Vector3d::Zero();
  for (int k = 0; k < 7; ++k) {
    n += (Eigen::Vector3d(0.5, 0, 3) - pose_at(0.2 * k, 0.0).translation()).normalized();
  }
  EXPECT_TRUE(v.normal.isApprox(n.normalized().cast<float>(), 1e-6F));
}

TEST(Map, MovingPointsAcrossCells) {
  Map m(small_options());
  const KeyframeId kf = add_kf(m, make_kf(20, 1), SE3d::Identity(), 0);
  const PointId a = add_pt(m, Eigen::Vector3d(0.1, 0.1, 1.1), kf, 0);
  const PointId b = add_pt(m, Eigen::Vector3d(0.12, 0.1, 1.1), kf, 1);
  PointId buf[16];
  EXPECT_EQ(m.query_radius(Eigen::Vector3d(0.1, 0.1, 1.1), 0.05, 0, buf), 2u);
  // Within the same cell.
  m.set_point_position(a, Eigen::Vector3d(0.2, 0.2, 1.2));
  EXPECT_EQ(m.query_radius(Eigen::Vector3d(0.1, 0.1, 1.1), 0.05, 0, buf), 2u);
  // To another cell.
  m.set_point_position(a, Eigen::Vector3d(3.0, -1.0, 2.0));
  ASSERT_EQ(m.query_radius(Eigen::Vector3d(0.1, 0.1, 1.1), 0.05, 0, buf), 1u);
  EXPECT_EQ(buf[0], b);
  ASSERT_EQ(m.query_radius(Eigen::Vector3d(3.0, -1.0, 2.0), 0.01, 0, buf), 1u);
  EXPECT_EQ(buf[0], a);
  PointView v;
  ASSERT_TRUE(m.read_point(a, v));
  EXPECT_EQ(v.p_w, Eigen::Vector3d(3.0, -1.0, 2.0));
  const CellGrid& g = m.cell_grid();
  EXPECT_EQ(g.cell_points(g.key_of(Eigen::Vector3d(3.0, -1.0, 2.0), 0), buf), 1u);
  // Out of range: counted, the point still exists, and it comes back when moved in range.
  m.set_point_position(a, Eigen::Vector3d(1e9, 0, 0));
  EXPECT_EQ(m.cell_insert_failures(), 1u);
  EXPECT_EQ(m.query_radius(Eigen::Vector3d(3.0, -1.0, 2.0), 0.01, 0, buf), 0u);
  m.set_point_position(a, Eigen::Vector3d(1.0, 1.0, 1.0));
  ASSERT_EQ(m.query_radius(Eigen::Vector3d(1.0, 1.0, 1.0), 0.01, 0, buf), 1u);
  EXPECT_EQ(buf[0], a);
  EXPECT_EQ(m.cell_insert_failures(), 1u);
}

TEST(Map, FullCellCountedAndPointStillUsable) {
  MapOptions o = small_options();
  o.points_per_cell = 2;
  Map m(o);
  const KeyframeId kf = add_kf(m, make_kf(10, 1), SE3d::Identity(), 0);
  for (std::uint32_t i = 0; i < 4; ++i) add_pt(m, Eigen::Vector3d(0.01 * i, 0, 1.01), kf, i);
  EXPECT_EQ(m.cell_insert_failures(), 2u);
  EXPECT_EQ(m.cell_grid().stats().cell_full, 2u);
  EXPECT_EQ(m.num_points(), 4u);
  PointView v;
  EXPECT_TRUE(m.read_point(3, v));
  PointId buf[8];
  EXPECT_EQ(m.query_radius(Eigen::Vector3d(0, 0, 1.01), 0.1, 0, buf), 2u);
  // Freeing the cell and moving the homeless point in makes it findable again.
  m.set_point_bad(0);
  m.set_point_position(3, Eigen::Vector3d(0.05, 0.0, 1.02));
  EXPECT_EQ(m.query_radius(Eigen::Vector3d(0, 0, 1.01), 0.1, 0, buf), 2u);
  EXPECT_EQ(std::count(buf, buf + 2, PointId{3}), 1);
}

// ---- covisibility ------------------------------------------------------------------------

/// Keyframes 0..4; kf 0 shares 10 points with kf 1, 7 with kf 3, 5 with kf 2, 7 with kf 4;
/// kf 1 and kf 2 share 3 more points that kf 0 does not see.
struct CovisFixture {
  Map m;
  std::vector<PointId> shared01;
  explicit CovisFixture(const MapOptions& o) : m(o) {
    const KfData d = make_kf(40, 1);
    for (int k = 0; k < 5; ++k) add_kf(m, d, pose_at(k, 0.1 * k), static_cast<std::uint64_t>(k));
    std::uint32_t next_kp[5] = {};
    auto share = [&](std::initializer_list<KeyframeId> kfs, int count) {
      for (int i = 0; i < count; ++i) {
        const KeyframeId first = *kfs.begin();
        const PointId p = add_pt(m, Eigen::Vector3d(0.1 * i, 0, 5), first, next_kp[first]++);
        for (auto it = kfs.begin() + 1; it != kfs.end(); ++it) {
          EXPECT_TRUE(m.add_observation(p, *it, next_kp[*it]++));
        }
        if (kfs.size() == 2 && first == 0 && *(kfs.begin() + 1) == 1) shared01.push_back(p);
      }
    };
    share({0, 1}, 10);
    share({0, 3}, 7);
    share({0, 2}, 5);
    share({0, 4}, 7);
    share({1, 2}, 3);
  }
};

MapOptions covis_options(int max_cov) {
  MapOptions o = small_options();
  o.max_points = 200;
  o.max_keypoints_per_keyframe = 64;
  o.max_covisible_per_keyframe = max_cov;
  return o;
}

std::vector<std::pair<KeyframeId, std::uint32_t>> edges(const Map& m, KeyframeId kf) {
  CovisibleKeyframe buf[16];
  const std::size_t n = m.covisible_keyframes(kf, buf);
  std::vector<std::pair<KeyframeId, std::uint32_t>> v;
  for (std::size_t i = 0; i < n; ++i) v.emplace_back(buf[i].id, buf[i].weight);
  return v;
}

using Edges = std::vector<std::pair<KeyframeId, std::uint32_t>>;

TEST(Map, CovisibilityWeightsOrderAndReverseEdges) {
  CovisFixture f(covis_options(8));
  Map& m = f.m;
  m.update_covisibility(0);
  EXPECT_EQ(edges(m, 0), (Edges{{1, 10}, {3, 7}, {4, 7}, {2, 5}}));  // ties: lower id first
  EXPECT_EQ(edges(m, 1), (Edges{{0, 10}}));  // reverse edges only (kf 1 not updated yet)
  EXPECT_EQ(edges(m, 2), (Edges{{0, 5}}));
  EXPECT_EQ(edges(m, 3), (Edges{{0, 7}}));
  EXPECT_EQ(m.covisibility_weight(4, 0), 7u);
  m.update_covisibility(1);
  EXPECT_EQ(edges(m, 1), (Edges{{0, 10}, {2, 3}}));
  EXPECT_EQ(edges(m, 2), (Edges{{0, 5}, {1, 3}}));

  // Points going bad lower the weights; an edge whose weight reaches 0 disappears on both
  // sides.
  for (int i = 0; i < 4; ++i) m.set_point_bad(f.shared01[static_cast<std::size_t>(i)]);
  m.update_covisibility(0);
  EXPECT_EQ(edges(m, 0), (Edges{{3, 7}, {4, 7}, {1, 6}, {2, 5}}));
  EXPECT_EQ(edges(m, 1), (Edges{{0, 6}, {2, 3}}));
  for (std::size_t i = 4; i < f.shared01.size(); ++i) m.set_point_bad(f.shared01[i]);
  m.update_covisibility(0);
  EXPECT_EQ(edges(m, 0), (Edges{{3, 7}, {4, 7}, {2, 5}}));
  EXPECT_EQ(edges(m, 1), (Edges{{2, 3}}));
  EXPECT_EQ(m.covisibility_weight(0, 1), 0u);
}

TEST(Map, CovisibilityKeepsTheStrongest) {
  CovisFixture f(covis_options(2));
  Map& m = f.m;
  m.update_covisibility(0);
  EXPECT_EQ(edges(m, 0), (Edges{{1, 10}, {3, 7}}));
  // Reverse edges exist for every sharing keyframe, each list capped at 2.
  EXPECT_EQ(edges(m, 4), (Edges{{0, 7}}));
  EXPECT_EQ(edges(m, 2), (Edges{{0, 5}}));
  m.update_covisibility(1);
  EXPECT_EQ(edges(m, 2), (Edges{{0, 5}, {1, 3}}));
  CovisibleKeyframe one[1];
  ASSERT_EQ(m.covisible_keyframes(0, one), 1u);  // a short span gets the strongest
  EXPECT_EQ(one[0].id, 1u);
}

TEST(Map, RelativePose) {
  Map m(small_options());
  const KfData d = make_kf(4, 1);
  const SE3d Ta = pose_at(1.0, 0.4);
  const SE3d Tb = pose_at(-0.5, -1.1);
  add_kf(m, d, Ta, 0);
  add_kf(m, d, Tb, 1);
  const SE3d T_a_b = m.relative_pose(0, 1);
  EXPECT_TRUE((Ta * T_a_b).isApprox(Tb, 1e-12));
  const Eigen::Vector3d p_b(0.3, 0.2, 2.0);
  EXPECT_TRUE((T_a_b * p_b).isApprox(Ta.inverse() * (Tb * p_b), 1e-12));
  EXPECT_TRUE(m.relative_pose(0, 0).isApprox(SE3d::Identity(), 1e-12));
  EXPECT_TRUE(m.relative_pose(0, 5).isApprox(SE3d::Identity()));
}

// ---- removal and slot reuse ------------------------------------------------------------------

TEST(Map, FreedPointSlotIsReusedOnlyAfterEveryReaderPassed) {
  MapOptions o = small_options();
  o.max_points = 3;
  Map m(o);
  const Result<int> reader = m.register_reader();
  ASSERT_TRUE(reader.is_ok());
  const KeyframeId kf = add_kf(m, make_kf(10, 1), SE3d::Identity(), 0);
  const PointId a = add_pt(m, Eigen::Vector3d(0, 0, 1), kf, 0);
  const PointId b = add_pt(m, Eigen::Vector3d(0, 0, 2), kf, 1);
  add_pt(m, Eigen::Vector3d(0, 0, 3), kf, 2);
  PointView v;
  ASSERT_TRUE(m.read_point(b, v));
  const Generation gen_b = v.generation;
  EXPECT_EQ(m.point_generation(b), gen_b);
  EXPECT_EQ(m.live_points(), 3u);

  m.set_point_bad(b);
  EXPECT_EQ(m.point_generation(b), kNoGeneration);
  EXPECT_EQ(m.live_points(), 2u);
  EXPECT_EQ(m.counters().point_slots_waiting, 1u);
  // The reader announced before b was freed: it may still read b's slot, so it is not reused.
  Result<PointId> r = m.add_point(Eigen::Vector3d(1, 0, 1), kf, 5);
  ASSERT_FALSE(r.is_ok());
  EXPECT_NE(r.status().message().find("map.max_points"), std::string::npos);
  EXPECT_NE(r.status().message().find("wait for a reader"), std::string::npos);
  // After its quiescent point it is.
  m.reader_quiescent(reader.value());
  r = m.add_point(Eigen::Vector3d(1, 0, 1), kf, 5);
  ASSERT_TRUE(r.is_ok()) << r.status().message();
  EXPECT_EQ(r.value(), b);
  ASSERT_TRUE(m.read_point(b, v));
  EXPECT_NE(v.generation, gen_b);  // a kept (id, generation) no longer names this point
  EXPECT_EQ(v.p_w, Eigen::Vector3d(1, 0, 1));
  EXPECT_EQ(v.ref_keypoint, 5u);
  EXPECT_EQ(m.keyframe_point(kf, 1), kNoId);  // the old association is gone
  EXPECT_EQ(m.keyframe_point(kf, 5), b);
  EXPECT_EQ(m.num_points(), 3u);
  EXPECT_EQ(m.live_points(), 3u);
  EXPECT_EQ(m.counters().reused_point_slots, 1u);
  EXPECT_EQ(m.counters().bad_points, 1u);
  const PointStats st = m.point_stats(b);
  EXPECT_EQ(st.observations, 1u);
  EXPECT_EQ(st.visible, 1u);  // counters restart with the new occupant
  EXPECT_EQ(st.found, 1u);
  m.note_visible(b);
  m.note_visible(b);
  m.note_found(b);
  EXPECT_EQ(m.point_stats(b).visible, 3u);
  EXPECT_EQ(m.point_stats(b).found, 2u);

  // A released reader no longer holds anything back.
  m.set_point_bad(a);
  m.release_reader(reader.value());
  EXPECT_TRUE(m.add_point(Eigen::Vector3d(2, 0, 1), kf, 6).is_ok());
}

TEST(Map, ReaderRegistrationIsBounded) {
  Map m(small_options());
  std::vector<int> readers;
  for (int i = 0; i < kMaxMapReaders; ++i) {
    const Result<int> r = m.register_reader();
    ASSERT_TRUE(r.is_ok());
    readers.push_back(r.value());
  }
  EXPECT_FALSE(m.register_reader().is_ok());
  m.release_reader(readers[1]);
  const Result<int> again = m.register_reader();
  ASSERT_TRUE(again.is_ok());
  EXPECT_EQ(again.value(), readers[1]);
}

TEST(Map, RemovedKeyframeSlotIsReusedAndStaleIdsAreDetected) {
  MapOptions o = small_options();
  o.max_keyframes = 3;
  Map m(o);
  const Result<int> reader = m.register_reader();
  ASSERT_TRUE(reader.is_ok());
  const KfData d = make_kf(10, 1);
  const KeyframeId k0 = add_kf(m, d, pose_at(0, 0), 10);
  const KeyframeId k1 = add_kf(m, d, pose_at(1, 0), 11);
  const KeyframeId k2 = add_kf(m, d, pose_at(2, 0), 12);
  EXPECT_EQ(m.newest_keyframe(), k2);
  const Generation g1 = m.keyframe_generation(k1);
  ASSERT_NE(g1, kNoGeneration);
  EXPECT_EQ(m.keyframe_serial(k1), 1u);
  EXPECT_FALSE(m.remove_keyframe(k2, 1));  // the newest stays
  EXPECT_FALSE(m.remove_keyframe(7, 1));   // unknown id
  ASSERT_TRUE(m.remove_keyframe(k1, 1));
  EXPECT_FALSE(m.remove_keyframe(k1, 1));  // already removed
  EXPECT_FALSE(m.keyframe_is_live(k1));
  EXPECT_EQ(m.keyframe_generation(k1), kNoGeneration);
  EXPECT_TRUE(m.keyframe_keypoints(k1).empty());
  EXPECT_EQ(m.keyframe_seq(k1), 0u);
  SE3d T;
  EXPECT_FALSE(m.keyframe_pose(k1, T));
  EXPECT_EQ(m.keyframe_serial(k1), Map::kNoSerial);
  EXPECT_EQ(m.live_keyframes(), 2u);

  // Full until the registered reader passes a quiescent point.
  KfData d2 = make_kf(4, 2);
  Result<KeyframeId> r = m.add_keyframe(d2.input(pose_at(3, 0), 13));
  ASSERT_FALSE(r.is_ok());
  EXPECT_NE(r.status().message().find("map.max_keyframes"), std::string::npos);
  m.reader_quiescent(reader.value());
  r = m.add_keyframe(d2.input(pose_at(3, 0), 13));
  ASSERT_TRUE(r.is_ok()) << r.status().message();
  EXPECT_EQ(r.value(), k1);  // the slot is reused ...
  EXPECT_EQ(m.newest_keyframe(), k1);
  const Generation g1b = m.keyframe_generation(k1);
  EXPECT_NE(g1b, kNoGeneration);
  EXPECT_NE(g1b, g1);  // ... and the generation tells the stale id from the new keyframe
  EXPECT_EQ(m.keyframe_seq(k1), 13u);
  EXPECT_EQ(m.keyframe_keypoints(k1).size(), 4u);
  EXPECT_EQ(m.keyframe_descriptors(k1)[2], d2.desc[2]);
  EXPECT_EQ(m.keyframe_serial(k1), 3u);
  EXPECT_EQ(m.keyframes_added(), 4u);
  for (std::uint32_t kp = 0; kp < 4; ++kp) EXPECT_EQ(m.keyframe_point(k1, kp), kNoId);
  EXPECT_EQ(m.counters().reused_keyframe_slots, 1u);
  EXPECT_EQ(m.counters().removed_keyframes, 1u);
  EXPECT_TRUE(m.keyframe_is_live(k0));
}

TEST(Map, RemoveKeyframeUpdatesPointsAndEveryCovisibilityEdge) {
  MapOptions o = small_options();
  o.max_keypoints_per_keyframe = 16;
  o.max_covisible_per_keyframe = 8;
  Map m(o);
  const KfData d = make_kf(16, 1);
  std::vector<KeyframeId> kf;
  for (int k = 0; k < 4; ++k) kf.push_back(add_kf(m, d, pose_at(k, 0.0), k));
  // a: seen by 0, 1, 2; b: created by 1 (reference), seen by 2, 3; c: seen by 1 and 3 only.
  const PointId a = add_pt(m, Eigen::Vector3d(0, 0, 4), kf[0], 0);
  ASSERT_TRUE(m.add_observation(a, kf[1], 0));
  ASSERT_TRUE(m.add_observation(a, kf[2], 0));
  const PointId b = add_pt(m, Eigen::Vector3d(0.5, 0, 4), kf[1], 1);
  ASSERT_TRUE(m.add_observation(b, kf[2], 3));
  ASSERT_TRUE(m.add_observation(b, kf[3], 1));
  const PointId c = add_pt(m, Eigen::Vector3d(1, 0, 4), kf[1], 2);
  ASSERT_TRUE(m.add_observation(c, kf[3], 2));
  for (const KeyframeId k : kf) m.update_covisibility(k);
  EXPECT_EQ(m.covisibility_weight(kf[0], kf[1]), 1u);
  EXPECT_EQ(m.covisibility_weight(kf[3], kf[1]), 2u);

  std::uint32_t bad = 0;
  ASSERT_TRUE(m.remove_keyframe(kf[1], 2, &bad));
  EXPECT_EQ(bad, 1u);  // c is left with one observation
  EXPECT_TRUE(m.point_is_bad(c));
  EXPECT_EQ(m.keyframe_point(kf[3], 2), kNoId);
  EXPECT_EQ(m.point_num_observations(a), 2u);
  EXPECT_EQ(m.point_num_observations(b), 2u);
  // b's reference moves to its oldest remaining observation.
  PointView v;
  ASSERT_TRUE(m.read_point(b, v));
  EXPECT_EQ(v.ref_keyframe, kf[2]);
  EXPECT_EQ(v.ref_keypoint, 3u);
  // No list holds an edge to the removed keyframe.
  for (const KeyframeId k : {kf[0], kf[2], kf[3]}) {
    for (const auto& [id, w] : edges(m, k)) EXPECT_NE(id, kf[1]) << "in the list of " << k;
  }
  EXPECT_EQ(m.covisibility_weight(kf[0], kf[2]), 1u);  // untouched edges keep their weight
  m.update_covisibility(kf[2]);
  EXPECT_EQ(m.covisibility_weight(kf[2], kf[3]), 1u);  // b still shared
}

// ---- allocations ---------------------------------------------------------------------------

TEST(Map, NoAllocationAfterConstruction) {
  ASSERT_TRUE(platform::alloc::counter_linked());
  MapOptions o = covis_options(4);
  o.max_keyframes = 6;  // full, so that the slots freed below are reused
  o.max_points = 30;
  Map m(o);
  const std::size_t bytes = m.memory_bytes();
  const KfData d = make_kf(40, 1);  // inputs built before counting
  const geometry::Pinhole K{500, 500, 320, 240};
  std::vector<PointId> ids(256);
  std::vector<CovisibleKeyframe> cov(16);
  std::vector<std::pair<KeyframeId, std::uint32_t>> obs(16);
  PointView v;
  SE3d T;
  double scale = 0.0;
  std::uint64_t sink = 0;

  const std::uint64_t before = platform::alloc::thread_allocations();
  for (int k = 0; k < 6; ++k) {
    const Result<KeyframeId> r =
        m.add_keyframe(d.input(pose_at(0.1 * k, 0.05 * k), static_cast<std::uint64_t>(k)));
    sink += r.is_ok() ? r.value() : 0;
  }
  for (std::uint32_t i = 0; i < 30; ++i) {
    const Result<PointId> r = m.add_point(Eigen::Vector3d(0.1 * i, 0.05 * i, 3.0), 0, i);
    if (!r.is_ok()) continue;
    for (KeyframeId k = 1; k < 6; ++k) sink += m.add_observation(r.value(), k, i) ? 1 : 0;
    m.update_point(r.value());
    m.set_point_position(r.value(), Eigen::Vector3d(0.1 * i - 1.0, 0.5, 2.0));
  }
  m.set_keyframe_pose(2, pose_at(0.3, 0.2), 1.1);
  m.set_keyframe_depth(2, 3, 1.5F, 0.5F);
  m.set_point_bad(7);
  for (KeyframeId k = 0; k < 6; ++k) m.update_covisibility(k);
  std::uint32_t orphaned = 0;
  sink += m.remove_keyframe(4, 2, &orphaned) ? orphaned : 0;
  sink += m.add_keyframe(d.input(pose_at(0.7, 0.1), 7)).is_ok() ? 1 : 0;      // reuses slot 4
  sink += m.add_point(Eigen::Vector3d(0.3, 0.2, 3.0), 4, 0).is_ok() ? 1 : 0;  // reuses 7
  m.note_visible(3);
  m.note_found(3);
  sink += m.point_stats(3).visible + m.point_generation(3) + m.keyframe_generation(4);
  sink += m.newest_keyframe() + m.live_keyframes() + m.live_points() + m.keyframe_serial(4);
  sink += m.counters().reused_keyframe_slots + m.counters().reused_point_slots;
  sink += m.point_observations(3, obs);
  sink += m.point_num_observations(3);
  sink += static_cast<std::uint64_t>(m.relative_pose(0, 3).translation().norm());
  sink += m.num_keyframes() + m.num_points();
  sink += m.keyframe_pose(1, T, &scale) ? 1 : 0;
  sink += m.keyframe_keypoints(1).size() + m.keyframe_descriptors(1).size();
  sink += static_cast<std::uint64_t>(m.keyframe_t_ns(1)) + m.keyframe_seq(1);
  sink += m.keyframe_point(1, 2) + m.keyframe_num_keypoints(1);
  sink += static_cast<std::uint64_t>(m.keyframe_depth(1, 2) + m.keyframe_depth_confidence(1, 2));
  Eigen::Vector3d p_c;
  sink += m.keyframe_point_3d(1, 2, K, p_c) ? 1 : 0;
  sink += m.read_point(3, v) ? 1 : 0;
  sink += m.point_is_bad(7) ? 1 : 0;
  sink += m.covisible_keyframes(0, cov) + m.covisibility_weight(0, 1);
  sink += m.query_visible(SE3d::Identity(), K, 640, 480, 0.1, 5.0, 0, ids);
  sink += m.query_visible(SE3d::Identity(), K, 640, 480, 0.1, 500.0, 0, ids);  // table scan
  sink += m.query_radius(Eigen::Vector3d(0, 0.5, 2.0), 1.0, 0, ids);
  sink += m.cell_insert_failures();
  const std::uint64_t after = platform::alloc::thread_allocations();

  EXPECT_EQ(after - before, 0u) << "sink " << sink;
  EXPECT_EQ(m.num_keyframes(), 6u);
  EXPECT_EQ(m.num_points(), 30u);
  EXPECT_EQ(m.counters().reused_keyframe_slots, 1u);
  EXPECT_EQ(m.counters().reused_point_slots, 1u);
  EXPECT_GT(m.covisible_keyframes(0, cov), 0u);
  EXPECT_EQ(m.memory_bytes(), bytes);
}

// ---- performance ---------------------------------------------------------------------------

TEST(Map, QueryVisibleIsATightSupersetOnAnIndoorScene) {
  // 20k points on the walls, floor and ceiling of an 8 x 3 x 8 room (map units, median
  // depth ~1-3); cameras inside looking around; 640x480, depth range [0.1, 5].
  MapOptions o;
  o.max_keyframes = 2;
  o.max_points = 20000;
  o.max_keypoints_per_keyframe = 16384;
  Map m(o);
  std::printf("map memory with default options: %.1f MiB\n",
              static_cast<double>(Map(MapOptions{}).memory_bytes()) / (1024.0 * 1024.0));
  std::mt19937 rng(5);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  const KfData d = make_kf(16384, 1);
  KeyframeId kfs[2] = {add_kf(m, d, SE3d::Identity(), 0), add_kf(m, d, SE3d::Identity(), 1)};
  std::vector<Eigen::Vector3d> pts;
  for (int i = 0; i < 20000; ++i) {
    Eigen::Vector3d p(4 * u(rng), 1.5 * u(rng), 4 * u(rng));
    const int wall = i % 6;
    p[wall / 2] = (wall % 2 == 0 ? -1.0 : 1.0) * (wall / 2 == 1 ? 1.5 : 4.0);
    pts.push_back(p);
    add_pt(m, p, kfs[i / 16384], static_cast<std::uint32_t>(i % 16384));
  }
  ASSERT_EQ(m.cell_insert_failures(), 0u);
  const geometry::Pinhole K{500, 500, 320, 240};
  std::vector<PointId> out(20000);
  std::vector<SE3d> poses;
  for (int i = 0; i < 200; ++i) {
    const Eigen::Vector3d eye(2.5 * u(rng), 0.8 * u(rng), 2.5 * u(rng));
    const Eigen::Vector3d target(4 * u(rng), 1.5 * u(rng), 4 * u(rng));
    poses.push_back(look_at(eye, target, Eigen::Vector3d(0, -1, 0)));
  }
  std::size_t total = 0;
  std::size_t visible = 0;
  std::vector<double> times;
  for (int rep = 0; rep < 5; ++rep) {
    for (const SE3d& T : poses) {
      const auto t0 = std::chrono::steady_clock::now();
      const std::size_t n = m.query_visible(T, K, 640, 480, 0.1, 5.0, 0, out);
      const auto t1 = std::chrono::steady_clock::now();
      times.push_back(std::chrono::duration<double, std::micro>(t1 - t0).count());
      if (rep == 0) {
        total += n;
        const SE3d T_c_w = T.inverse();
        for (const Eigen::Vector3d& p : pts) {
          const Eigen::Vector3d q = T_c_w * p;
          if (q.z() < 0.1 || q.z() > 5.0) continue;
          const Eigen::Vector2d uv = K.project(q);
          visible += (uv.x() >= 0 && uv.x() < 640 && uv.y() >= 0 && uv.y() < 480) ? 1 : 0;
        }
      }
    }
  }
  std::sort(times.begin(), times.end());
  const double median = times[times.size() / 2];
  const double p95 = times[times.size() * 95 / 100];
  std::printf(
      "query_visible: median %.1f us, p95 %.1f us, max %.1f us; %.0f ids per query, "
      "returned / visible = %.3f\n",
      median, p95, times.back(), static_cast<double>(total) / 200.0,
      static_cast<double>(total) / static_cast<double>(visible));
  // (Its time is measured by tests/bench/map_bench.cpp, bm_query_visible_indoor.)
  EXPECT_LT(static_cast<double>(total) / static_cast<double>(visible), 1.6);
}

}  // namespace
}  // namespace mer::map

namespace mer::map {
namespace {

// Loop corrections compose in the map, per segment: a reader that saw the first one and
// reads its segment's cumulative correction after the second gets S2 * S1, with the count of
// both; another segment's correction changes only the total count.
TEST(Map, CorrectionsComposePerSegmentAndAreCounted) {
  Map map(small_options());
  geometry::Sim3d S;
  std::uint32_t count = 7;
  ASSERT_TRUE(map.read_correction(0, S, count));
  EXPECT_EQ(count, 0U);
  EXPECT_EQ(map.correction_count(), 0U);
  EXPECT_DOUBLE_EQ(S.s, 1.0);
  geometry::Sim3d a;
  a.R = Eigen::AngleAxisd(0.2, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  a.t = Eigen::Vector3d(0.1, -0.2, 0.3);
  a.s = 1.05;
  geometry::Sim3d b;
  b.R = Eigen::AngleAxisd(-0.1, Eigen::Vector3d::UnitX()).toRotationMatrix();
  b.t = Eigen::Vector3d(-0.3, 0.0, 0.2);
  b.s = 0.97;
  geometry::Sim3d c;
  c.t = Eigen::Vector3d(5.0, 0.0, 0.0);
  c.s = 2.0;
  {
    std::lock_guard<platform::PiMutex> lock(map.writer_lock());
    map.publish_correction(0, a);
    map.publish_correction(3, c);
    map.publish_correction(0, b);
    map.publish_correction(kMaxSegments, c);  // out of range: ignored
  }
  EXPECT_EQ(map.correction_count(), 3U);
  ASSERT_TRUE(map.read_correction(0, S, count));
  EXPECT_EQ(count, 2U);
  const geometry::Sim3d ba = b * a;
  const Eigen::Vector3d p(1.0, 2.0, 3.0);
  EXPECT_LT((S * p - ba * p).norm(), 1e-12);
  EXPECT_NEAR(S.s, 1.05 * 0.97, 1e-12);
  ASSERT_TRUE(map.read_correction(3, S, count));
  EXPECT_EQ(count, 1U);
  EXPECT_LT((S * p - c * p).norm(), 1e-12);
  ASSERT_TRUE(map.read_correction(1, S, count));
  EXPECT_EQ(count, 0U);
  EXPECT_LT((S * p - p).norm(), 1e-12);
}

}  // namespace
TEST(Map, MergeSegmentMovesKeyframesAndPointsIntoTheOlderFrame) {
  Map m(small_options());
  const KfData d = make_kf(8, 1);
  // The same two cameras and points, seen by segment 0 in its frame and by segment 1 in a
  // frame that S_1_0 relates to it (another origin, heading and scale).
  geometry::Sim3d S_1_0;
  S_1_0.R = Eigen::AngleAxisd(0.7, Eigen::Vector3d(0.2, 1.0, 0.1).normalized()).toRotationMatrix();
  S_1_0.t = Eigen::Vector3d(4.0, -1.0, 2.5);
  S_1_0.s = 0.4;
  const SE3d T0 = SE3d::Identity();
  SE3d T1 = SE3d::Identity();
  T1.translation() = Eigen::Vector3d(0.3, 0.0, 0.1);
  KeyframeInput a0 = d.input(T0, 1);
  KeyframeInput b0 = d.input(T1, 2);
  KeyframeInput a1 = d.input(geometry::apply_to_pose(S_1_0, T0), 3);
  KeyframeInput b1 = d.input(geometry::apply_to_pose(S_1_0, T1), 4);
  a1.segment = 1;
  b1.segment = 1;
  const Result<KeyframeId> ka0 = m.add_keyframe(a0);
  const Result<KeyframeId> kb0 = m.add_keyframe(b0);
  const Result<KeyframeId> ka1 = m.add_keyframe(a1);
  const Result<KeyframeId> kb1 = m.add_keyframe(b1);
  ASSERT_TRUE(ka0.is_ok() && kb0.is_ok() && ka1.is_ok() && kb1.is_ok());
  std::vector<PointId> seg1;
  for (std::uint32_t k = 0; k < 4; ++k) {
    const Eigen::Vector3d p_w(0.2 * k, 0.1, 2.0 + 0.1 * k);
    ASSERT_TRUE(m.add_point(p_w, ka0.value(), k).is_ok());
    const Result<PointId> q = m.add_point(S_1_0 * p_w, ka1.value(), k);
    ASSERT_TRUE(q.is_ok());
    seg1.push_back(q.value());
  }
  geometry::Sim3d S;
  std::uint32_t count = 0;
  {
    std::lock_guard<platform::PiMutex> lock(m.writer_lock());
    EXPECT_EQ(m.merge_segment(1, 1, S_1_0.inverse()), 0U);  // into itself: refused
    EXPECT_EQ(m.merge_segment(1, 0, S_1_0.inverse()), 2U);
    EXPECT_EQ(m.merge_segment(1, 0, S_1_0.inverse()), 0U);  // already merged
  }
  // Poses and points of segment 1 land on segment 0's, within rounding.
  for (const auto& [merged, original] :
       {std::pair{ka1.value(), ka0.value()}, std::pair{kb1.value(), kb0.value()}}) {
    EXPECT_EQ(m.keyframe_segment(merged), 0U);
    SE3d T_m;
    SE3d T_o;
    ASSERT_TRUE(m.keyframe_pose(merged, T_m) && m.keyframe_pose(original, T_o));
    EXPECT_LT((T_m.matrix() - T_o.matrix()).norm(), 1e-9);
  }
  PointView v;
  for (std::uint32_t k = 0; k < 4; ++k) {
    ASSERT_TRUE(m.read_point(seg1[k], v));
    EXPECT_LT((v.p_w - Eigen::Vector3d(0.2 * k, 0.1, 2.0 + 0.1 * k)).norm(), 1e-9);
  }
  // The cells hold them under segment 0 now, none under segment 1.
  PointId buf[16];
  EXPECT_EQ(m.query_radius(Eigen::Vector3d(0.3, 0.1, 2.15), 1.0, 0, buf), 8U);
  EXPECT_EQ(m.query_radius(S_1_0 * Eigen::Vector3d(0.3, 0.1, 2.15), 1.0, 1, buf), 0U);
  // The merge is recorded and published as a correction of segment 1.
  SegmentMerge rec;
  ASSERT_TRUE(m.segment_merge(1, rec));
  EXPECT_EQ(rec.into, 0U);
  EXPECT_FALSE(m.segment_merge(0, rec));
  ASSERT_TRUE(m.read_correction(1, S, count));
  EXPECT_EQ(count, 1U);
  const Eigen::Vector3d p(1.0, 2.0, 3.0);
  EXPECT_LT((S * (S_1_0 * p) - p).norm(), 1e-9);
  EXPECT_EQ(m.merged_segment(1, S), 0U);
  EXPECT_LT((S * (S_1_0 * p) - p).norm(), 1e-9);
  // A merged segment cannot be discarded any more (the merge claimed it first).
  EXPECT_FALSE(m.discard_segment(1));
  EXPECT_FALSE(m.segment_discarded(1));
}

// A discarded segment (a failed start) is flagged for every reader, counted once, and never
// merges, neither from nor into; a segment merges or is discarded, whichever comes first.
TEST(Map, DiscardedSegmentNeverMerges) {
  Map m(small_options());
  const KfData d = make_kf(8, 1);
  KeyframeInput a = d.input(SE3d::Identity(), 1);
  KeyframeInput b = d.input(SE3d::Identity(), 2);
  KeyframeInput c = d.input(SE3d::Identity(), 3);
  b.segment = 1;
  c.segment = 2;
  ASSERT_TRUE(m.add_keyframe(a).is_ok());
  ASSERT_TRUE(m.add_keyframe(b).is_ok());
  ASSERT_TRUE(m.add_keyframe(c).is_ok());
  EXPECT_EQ(m.discarded_segments(), 0U);
  EXPECT_FALSE(m.segment_discarded(1));
  EXPECT_TRUE(m.discard_segment(1));
  EXPECT_FALSE(m.discard_segment(1));  // once
  EXPECT_FALSE(m.discard_segment(kMaxSegments));
  EXPECT_TRUE(m.segment_discarded(1));
  EXPECT_FALSE(m.segment_discarded(0));
  EXPECT_FALSE(m.segment_discarded(kMaxSegments));
  EXPECT_EQ(m.discarded_segments(), 1U);
  const geometry::Sim3d I;
  std::lock_guard<platform::PiMutex> lock(m.writer_lock());
  EXPECT_EQ(m.merge_segment(1, 0, I), 0U);  // from a discarded segment
  EXPECT_EQ(m.merge_segment(2, 1, I), 0U);  // into a discarded segment
  SegmentMerge rec;
  EXPECT_FALSE(m.segment_merge(1, rec));
  EXPECT_FALSE(m.segment_merge(2, rec));
  // The refused merge into 1 left segment 2 free to merge elsewhere.
  EXPECT_EQ(m.merge_segment(2, 0, I), 1U);
  EXPECT_EQ(m.keyframe_segment(2), 0U);
}

}  // namespace mer::map
