// Relocalization on a synthetic kidnap: a map of part of a room, a frame from an earlier place
// (far from the last tracked pose) is relocalized to within millimetres; a frame of a part of
// the room the map does not hold is refused; spin_once does not allocate after a warm-up.
#include "loop/relocalizer.h"

#include <cmath>
#include <cstdio>
#include <random>
#include <vector>

#include <gtest/gtest.h>

#include "platform/alloc_counter.h"
#include "support/doc_check.h"
#include "synthetic_map.h"

namespace mer::loop {
namespace {

TEST(RelocalizerOptions, EveryFieldHasADocLine) {
  testing::DocCheck v;
  RelocalizerOptions o;
  o.visit(v);
  EXPECT_EQ(v.fields, 12 + 8);  // its own and the nested pnp section's
}

// A map of headings 0..200 degrees (21 keyframes): the tracker was last at 200 degrees.
struct Kidnap {
  scene::OrbitWorld world;
  map::Map map{scene::OrbitWorld::map_options()};
  std::mt19937_64 rng{21};
  std::vector<map::KeyframeId> ids;
  KeyframeDatabase db{map};
  Relocalizer reloc{RelocalizerOptions{}, map, db};
  Kidnap() { ids = world.build(map, 0.0, 10.0, 21, rng); }

  RelocResult locate(const SE3d& T_w_c, const scene::View& v) {
    RelocQuery q;
    q.seq = 1000;
    q.t_ns = 1;
    q.keypoints = v.keypoints;
    q.descriptors = v.descriptors;
    q.K = world.K;
    (void)T_w_c;
    return reloc.spin_once(q);
  }
};

TEST(Relocalizer, KidnappedFrameIsRelocalizedNearAnEarlierKeyframe) {
  Kidnap k;
  // Near the keyframe at 60 degrees: 4 degrees and 8 cm off it, 140 degrees from the last pose.
  const SE3d T_w_c = scene::OrbitWorld::pose(64.0, 0.08);
  const scene::View v = k.world.observe(T_w_c, k.rng);
  const RelocResult r = k.locate(T_w_c, v);
  std::printf(
      "relocalized: %d, keyframe %u, %d matches, %d PnP inliers, %d refined inliers, "
      "%d of %d candidates, %.2f ms\n",
      r.success, r.keyframe, r.matches, r.pnp_inliers, r.inliers, r.candidates_tried, r.retrieved,
      r.ms);
  ASSERT_TRUE(r.success);
  const SE3d T_err = r.T_c_w * T_w_c;  // identity when exact
  const double t_err = T_err.translation().norm();
  const double r_err = Eigen::AngleAxisd(T_err.linear()).angle() * 180.0 / M_PI;
  std::printf("pose error %.2f mm, %.3f deg\n", 1000.0 * t_err, r_err);
  EXPECT_LT(t_err, 0.02);
  EXPECT_LT(r_err, 0.5);
  EXPECT_GE(r.inliers, 200);  // most of the ~640 visible points: the refinement found them
  // The keyframe it matched is one of those that see this place.
  SE3d T_w_kf;
  ASSERT_TRUE(k.map.keyframe_pose(r.keyframe, T_w_kf));
  EXPECT_LT(Eigen::AngleAxisd(T_w_kf.linear().transpose() * T_w_c.linear()).angle() * 180.0 / M_PI,
            30.0);
}

TEST(Relocalizer, FrameOfAnUnmappedPlaceIsRefused) {
  Kidnap k;
  // 280 degrees: the camera's 77 degree view there overlaps nothing the map holds.
  {
    const SE3d T_w_c = scene::OrbitWorld::pose(280.0);
    const RelocResult r = k.locate(T_w_c, k.world.observe(T_w_c, k.rng));
    std::printf("unmapped: success %d, %d matches, %d inliers\n", r.success, r.matches, r.inliers);
    EXPECT_FALSE(r.success);
    EXPECT_LT(r.inliers, RelocalizerOptions{}.min_inliers);
  }
  // At 260 and 300 degrees a fifth of the view is mapped: relocalized or not, never wrong.
  for (const double deg : {260.0, 300.0}) {
    const SE3d T_w_c = scene::OrbitWorld::pose(deg);
    const RelocResult r = k.locate(T_w_c, k.world.observe(T_w_c, k.rng));
    if (r.success) {
      EXPECT_LT((r.T_c_w * T_w_c).translation().norm(), 0.02) << deg;
    }
  }
  // Nothing but clutter.
  const scene::View noise = [&] {
    scene::View v = k.world.observe(scene::OrbitWorld::pose(0.0), k.rng, 10, 0.3, 700);
    const std::size_t real = v.keypoints.size() - 700;
    v.keypoints.erase(v.keypoints.begin(), v.keypoints.begin() + static_cast<std::ptrdiff_t>(real));
    v.descriptors.erase(v.descriptors.begin(),
                        v.descriptors.begin() + static_cast<std::ptrdiff_t>(real));
    return v;
  }();
  EXPECT_FALSE(k.locate(SE3d::Identity(), noise).success);
}

TEST(Relocalizer, SpinOnceDoesNotAllocateAfterWarmUp) {
  if (!platform::alloc::counter_linked()) GTEST_SKIP() << "allocation counter not linked";
  Kidnap k;
  const SE3d T_ok = scene::OrbitWorld::pose(120.0, 0.05);
  const SE3d T_no = scene::OrbitWorld::pose(280.0);
  const scene::View ok = k.world.observe(T_ok, k.rng);
  const scene::View no = k.world.observe(T_no, k.rng);
  (void)k.locate(T_ok, ok);  // warm-up (keys the database)
  const std::uint64_t before = platform::alloc::thread_allocations();
  const RelocResult a = k.locate(T_ok, ok);
  const RelocResult b = k.locate(T_no, no);
  EXPECT_EQ(platform::alloc::thread_allocations() - before, 0U);
  EXPECT_TRUE(a.success);
  EXPECT_FALSE(b.success);
}

/// One query at heading 60 degrees with a zero time budget and every candidate failing;
/// `deterministic` as in lockstep.
RelocResult spin_with_no_time(bool deterministic) {
  Kidnap k;
  RelocalizerOptions o;
  o.max_time_ms = 0.0;     // only the first candidate, unless deterministic
  o.min_inliers = 100000;  // every candidate fails
  Relocalizer reloc(o, k.map, k.db, -1, deterministic);
  const scene::View v = k.world.observe(scene::OrbitWorld::pose(60.0), k.rng);
  RelocQuery q;
  q.keypoints = v.keypoints;
  q.descriptors = v.descriptors;
  q.K = k.world.K;
  return reloc.spin_once(q);
}

TEST(Relocalizer, StopsStartingCandidatesAfterMaxTime) {
  const RelocResult r = spin_with_no_time(false);
  EXPECT_FALSE(r.success);
  EXPECT_EQ(r.candidates_tried, 1);
  EXPECT_TRUE(r.timed_out);
  EXPECT_GT(r.retrieved, 1);
}

TEST(Relocalizer, DeterministicModeChecksEveryCandidateWhateverTheTime) {
  // Lockstep replays must not depend on the machine's load: the same budget that stops after
  // the first candidate above is not applied.
  const RelocResult r = spin_with_no_time(true);
  EXPECT_FALSE(r.success);
  EXPECT_FALSE(r.timed_out);
  EXPECT_GT(r.retrieved, 1);
  EXPECT_EQ(r.candidates_tried, r.retrieved);
}

}  // namespace
}  // namespace mer::loop
