// The tracker's check of a relocalizer's pose (tracking.relocalization_check) on rendered
// frames: RGB-D room_orbit tracked, then black frames (tracking lost), then a pose handed in
// as the relocalizer would. After a short loss a pose within the motion bound is trusted at
// once and one outside it is refused; after a long loss even the right pose is confirmed on
// the following frames before a frame is reported tracked, on more of them at a place
// refused earlier in the spell.
#include <array>
#include <numbers>

#include <gtest/gtest.h>

#include "reloc_rig.h"

namespace mer::frontend {
namespace {

using test::kTrackedFrames;
using test::options;
using test::RelocRig;
using test::track_then_lose;

// A short loss, the right pose: within the bound, tracked at once with a relocalization
// keyframe.
TEST(RelocalizationCheck, RightPoseAfterAShortLossIsTrustedAtOnce) {
  RelocRig rig(options());
  const int i = track_then_lose(rig, 3);
  rig.hint(i - 1, rig.truth_in_map(i - 1));
  const TrackingResult r = rig.step(i);
  EXPECT_EQ(r.state, TrackState::kTracked);
  EXPECT_TRUE(r.relocalized);
  EXPECT_EQ(rig.counters().relocalization_trusted, 1U);
  EXPECT_EQ(rig.counters().relocalization_candidates, 0U);
  EXPECT_LT((r.T_w_c.translation() - rig.truth_in_map(i).translation()).norm(), 0.05);
}

// A short loss and a wrong pose (2 m to the side, or facing away): outside the motion bound
// the camera cannot be there, so it is refused at once, counted against its place, and the
// tracker finds the camera again from its last tracked pose, as after any short loss: every
// frame reported tracked is at the true pose and none is a relocalization.
TEST(RelocalizationCheck, WrongPoseAfterAShortLossIsRefused) {
  for (const bool turned : {false, true}) {
    RelocRig rig(options());
    int i = track_then_lose(rig, 3);
    SE3d wrong = rig.truth_in_map(i - 1);
    if (turned) {
      wrong.linear() =
          wrong.linear() *
          Eigen::AngleAxisd(std::numbers::pi, Eigen::Vector3d::UnitY()).toRotationMatrix();
    } else {
      wrong.translation() += wrong.linear() * Eigen::Vector3d(2.0, 0.0, 0.0);  // 2 m to the right
    }
    rig.hint(i - 1, wrong);
    int tracked = 0;
    for (int k = 0; k < 10; ++k, ++i) {
      const TrackingResult r = rig.step(i);
      if (r.state != TrackState::kTracked) continue;
      ++tracked;
      EXPECT_FALSE(r.relocalized) << "frame " << i;
      EXPECT_LT((r.T_w_c.translation() - rig.truth_in_map(i).translation()).norm(), 0.05)
          << "frame " << i << (turned ? " (turned)" : " (shifted)");
    }
    EXPECT_GT(tracked, 0) << "the camera is found again from its last pose";
    EXPECT_EQ(rig.counters().relocalization_rejected_bound, 1U);
    EXPECT_EQ(rig.counters().relocalization_candidates, 0U);
    EXPECT_EQ(rig.counters().relocalization_trusted, 0U);
  }
}

// A long loss (1 s): even the right pose is confirmed first; the frames before confirmation
// are reported lost, the confirming one is tracked with a relocalization keyframe.
TEST(RelocalizationCheck, RightPoseAfterALongLossIsConfirmedFirst) {
  TrackingOptions o = options();
  RelocRig rig(o);
  int i = track_then_lose(rig, 30);
  rig.hint(i - 1, rig.truth_in_map(i - 1));
  const int confirm = o.relocalization_check.confirm_frames;
  for (int k = 1; k < confirm; ++k, ++i) {
    EXPECT_NE(rig.step(i).state, TrackState::kTracked) << "confirming frame " << k;
  }
  const TrackingResult r = rig.step(i);
  EXPECT_EQ(r.state, TrackState::kTracked);
  EXPECT_TRUE(r.relocalized);
  EXPECT_EQ(rig.counters().relocalization_candidates, 1U);
  EXPECT_EQ(rig.counters().relocalization_confirmed, 1U);
  EXPECT_LT((r.T_w_c.translation() - rig.truth_in_map(i).translation()).norm(), 0.05);
}

/// Frame i-1's true pose turned by `deg` about the camera's vertical axis.
SE3d turned_truth(const RelocRig& rig, int i, double deg) {
  SE3d T = rig.truth_in_map(i - 1);
  T.linear() =
      T.linear() * Eigen::AngleAxisd(deg * std::numbers::pi / 180.0, Eigen::Vector3d::UnitY())
                       .toRotationMatrix();
  return T;
}

// The bound follows the last tracked motion: after a 1/3 s loss the orbit's own turn is
// trusted at once, but a pose turned 40 degrees against it is refused. (A bound on speed
// alone, 180 deg/s, allowed 70 degrees here: a look-alike on the next wall.)
TEST(RelocalizationCheck, BoundIsCentredOnTheLastMotion) {
  for (const bool wrong : {false, true}) {
    RelocRig rig(options());
    const int i = track_then_lose(rig, 10);
    rig.hint(i - 1, wrong ? turned_truth(rig, i, 40.0) : rig.truth_in_map(i - 1));
    (void)rig.step(i);
    EXPECT_EQ(rig.counters().relocalization_trusted, wrong ? 0U : 1U);
    EXPECT_EQ(rig.counters().relocalization_rejected_bound, wrong ? 1U : 0U);
    EXPECT_EQ(rig.counters().relocalization_candidates, 0U);
  }
}

// The evidence for a place is the lost spell's: after a long loss, a pose at a place whose
// offer was refused earlier in the spell (here a wrong pose found against the newest
// keyframe) must be confirmed on one more frame per refusal, also when the new offer comes
// through another keyframe that shares map-points with it. Without the earlier refusal the
// same right pose is confirmed on confirm_frames frames.
TEST(RelocalizationCheck, PlaceRefusedInTheSpellNeedsMoreConfirmingFrames) {
  const TrackingOptions o = options();
  const int confirm = o.relocalization_check.confirm_frames;
  for (const bool refused_before : {false, true}) {
    RelocRig rig(o);
    int i = track_then_lose(rig, 30);
    const map::KeyframeId newest = rig.map().newest_keyframe();
    std::array<map::CovisibleKeyframe, 4> covis{};
    ASSERT_GT(rig.map().covisible_keyframes(newest, covis), 0U);
    if (refused_before) {
      SE3d wrong = rig.truth_in_map(i - 1);
      wrong.translation() += wrong.linear() * Eigen::Vector3d(2.0, 0.0, 0.0);
      rig.hint(i - 1, wrong, newest);
      const auto refusals = [&rig] {
        return rig.counters().relocalization_rejected_lost +
               rig.counters().relocalization_rejected_found;
      };
      for (int k = 0; k < 10 && refusals() == 0; ++k) {
        EXPECT_NE(rig.step(i++).state, TrackState::kTracked);
      }
      EXPECT_EQ(rig.counters().relocalization_candidates, 1U);
      ASSERT_EQ(rig.counters().relocalization_rejected_lost +
                    rig.counters().relocalization_rejected_found,
                1U)
          << "the wrong pose is refused";
    }
    rig.hint(i - 1, rig.truth_in_map(i - 1), covis[0].id);
    const int needed = confirm + (refused_before ? 1 : 0);
    int frames = 0;
    TrackingResult r;
    do {
      r = rig.step(i++);
      ++frames;
    } while (r.state != TrackState::kTracked && frames < needed + 5);
    EXPECT_EQ(frames, needed) << (refused_before ? "refused before" : "first offer");
    EXPECT_TRUE(r.relocalized);
    EXPECT_EQ(rig.counters().relocalization_longer_checks, refused_before ? 1U : 0U);
    EXPECT_LT((r.T_w_c.translation() - rig.truth_in_map(i - 1).translation()).norm(), 0.05);
  }
}

// With the check off, a relocalizer's pose is trusted as it comes (the behaviour the check
// replaces): the same turned pose, a candidate with the check on, is trusted at once.
TEST(RelocalizationCheck, OffTrustsEveryPose) {
  TrackingOptions o = options();
  o.relocalization_check.enabled = false;
  RelocRig rig(o);
  const int i = track_then_lose(rig, 10);
  rig.hint(i - 1, turned_truth(rig, i, 40.0));
  (void)rig.step(i);
  EXPECT_EQ(rig.counters().relocalization_trusted, 1U);
  EXPECT_EQ(rig.counters().relocalization_candidates, 0U);
}

// after_long_loss: merge. While the loss is short the relocalizer is asked and its pose is
// trusted within the bound, as with confirm. After a long loss (1 s) no relocalization is
// requested and a pose handed in anyway (a late threaded answer) is refused, even the right
// one: a new segment holds the frames and a merge brings them back. Without a new segment to
// hold them (new_segments off) the relocalizer stays the way back and is still asked.
TEST(RelocalizationCheck, AfterALongLossMergeModeLeavesTheReturnToANewSegment) {
  for (const bool segments : {true, false}) {
    TrackingOptions o = options(segments);
    o.relocalization_check.after_long_loss = LongLossReturn::kMerge;
    o.new_segment_after_s = 2.0;  // the loss below stays in its first segment
    RelocRig rig(o);
    int i = track_then_lose(rig, 3);
    EXPECT_GT(rig.counters().relocalization_requests, 0U) << "short loss: asked";
    for (; i < kTrackedFrames + 30; ++i) (void)rig.step(i, true);
    const std::uint64_t asked = rig.counters().relocalization_requests;
    const TrackingResult lost = rig.step(i++, true);
    EXPECT_EQ(lost.relocalization_request, !segments) << "long loss";
    EXPECT_EQ(rig.counters().relocalization_requests, asked + (segments ? 0U : 1U));
    rig.hint(i - 1, rig.truth_in_map(i - 1));
    const TrackingResult r = rig.step(i);
    EXPECT_FALSE(r.relocalized);
    EXPECT_EQ(rig.counters().relocalization_rejected_long_loss, segments ? 1U : 0U);
    EXPECT_EQ(rig.counters().relocalization_candidates, segments ? 0U : 1U);
  }
}

}  // namespace
}  // namespace mer::frontend
