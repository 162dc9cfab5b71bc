// The tracker across map segments and relocalizer poses, on rendered RGB-D room_orbit frames
// (reloc_rig.h): a pose against another segment's keyframe returns tracking to that segment,
// a relocalizer's pose of an earlier frame is not taken as one frame's motion, a loop
// correction of another segment leaves the tracked pose alone, and a segment's start is
// written to the map by keyframe creation, never by the tracker.
#include <atomic>
#include <cmath>
#include <mutex>
#include <numbers>
#include <thread>

#include <gtest/gtest.h>

#include "reloc_rig.h"

namespace mer::frontend {
namespace {

using test::options;
using test::RelocRig;
using test::track_then_lose;

// Black frames that start a new segment: 20 / 30 fps = 0.67 s, past new_segment_after_s.
constexpr int kNewSegmentBlack = 20;

struct TwoSegments {
  int next = 0;                      // the next frame index
  map::KeyframeId kf0 = map::kNoId;  // segment 0's newest keyframe
};

/// Tracks segment 0, loses it long enough to start segment 1, tracks `frames` frames in
/// segment 1 (RGB-D starts at once), then loses that for 3 black frames (relocalizing).
TwoSegments track_two_segments(RelocRig& rig, int frames) {
  TwoSegments out;
  int i = track_then_lose(rig, kNewSegmentBlack);
  out.kf0 = rig.map().newest_keyframe();
  EXPECT_EQ(rig.map().keyframe_segment(out.kf0), 0U);
  EXPECT_EQ(rig.counters().new_segments, 1U);
  int in_one = 0;
  for (int k = 0; k < frames; ++k, ++i) {
    const TrackingResult r = rig.step(i);
    in_one += r.state == TrackState::kTracked && r.segment == 1 ? 1 : 0;
  }
  EXPECT_GE(in_one, frames - 2);
  EXPECT_EQ(rig.map().keyframe_segment(rig.map().newest_keyframe()), 1U);
  for (int k = 0; k < 3; ++k, ++i) {
    EXPECT_NE(rig.step(i, true).state, TrackState::kTracked) << "black frame " << i;
  }
  out.next = i;
  return out;
}

// Relocalizing in segment 1, a relocalizer's pose against a keyframe of segment 0 is in
// segment 0's world frame: tracking returns to segment 0 (confirmed on the following frames,
// as every pose outside the motion bound is), at the true pose, and each frame from the
// first is anchored (to the keyframe relocalized against while segment 1's is the newest).
TEST(TrackerSegments, PoseFromAnotherSegmentWhileRelocalizingReturnsToIt) {
  RelocRig rig(options(true));
  const TwoSegments two = track_two_segments(rig, 30);
  int i = two.next;
  rig.hint(i - 1, rig.truth_in_map(i - 1), two.kf0);
  int tracked = 0;
  for (int k = 0; k < 10; ++k, ++i) {
    const TrackingResult r = rig.step(i);
    if (r.state != TrackState::kTracked) continue;
    EXPECT_EQ(r.segment, 0U) << "frame " << i;
    EXPECT_TRUE(r.has_anchor) << "frame " << i;
    EXPECT_LT((r.T_w_c.translation() - rig.truth_in_map(i).translation()).norm(), 0.05)
        << "frame " << i;
    if (tracked++ == 0) {
      EXPECT_TRUE(r.relocalized) << "frame " << i;
    }
  }
  EXPECT_GE(tracked, 5);
  EXPECT_EQ(rig.counters().segment_returns, 1U);
  EXPECT_EQ(rig.counters().relocalization_confirmed, 1U);
}

// The same pose refused (the frames do not confirm it: it is 2 m off): tracking stays in
// segment 1 and finds it again from its own last pose.
TEST(TrackerSegments, RefusedPoseFromAnotherSegmentStaysInTheSegment) {
  RelocRig rig(options(true));
  const TwoSegments two = track_two_segments(rig, 30);
  int i = two.next;
  SE3d wrong = rig.truth_in_map(i - 1);
  wrong.translation() += wrong.linear() * Eigen::Vector3d(2.0, 0.0, 0.0);
  rig.hint(i - 1, wrong, two.kf0);
  int tracked = 0;
  for (int k = 0; k < 10; ++k, ++i) {
    const TrackingResult r = rig.step(i);
    if (r.state != TrackState::kTracked) continue;
    ++tracked;
    EXPECT_EQ(r.segment, 1U) << "frame " << i;
    EXPECT_FALSE(r.relocalized) << "frame " << i;
  }
  EXPECT_GE(tracked, 5);
  EXPECT_EQ(rig.counters().segment_returns, 0U);
}

// Threaded, a relocalizer's pose is of the frame it was asked for, some frames back: the
// motion from it to the frame it is used at spans those frames, and the next prediction
// takes one frame's share (taking all of it as one frame's motion overshoots k-fold).
TEST(TrackerSegments, PoseOfAnEarlierFrameIsNotOneFramesMotion) {
  constexpr int kFramesBack = 6;
  RelocRig rig(options());
  int i = track_then_lose(rig, 3);
  rig.hint(i - kFramesBack, rig.truth_in_map(i - kFramesBack));
  const TrackingResult r = rig.step(i);
  ASSERT_EQ(r.state, TrackState::kTracked);
  const SE3d truth_step = rig.truth_in_map(i).inverse() * rig.truth_in_map(i - 1);
  const SE3d& v = rig.tracker().velocity();
  const double step_m = truth_step.translation().norm();
  ASSERT_GT(step_m, 1e-3);  // the orbit moves
  EXPECT_LT((v.translation() - truth_step.translation()).norm(), 0.5 * step_m)
      << "velocity " << v.translation().norm() << " m/frame, truth " << step_m;
  const double turn = Eigen::AngleAxisd(v.linear() * truth_step.linear().transpose()).angle();
  EXPECT_LT(turn, 0.5 * Eigen::AngleAxisd(truth_step.linear()).angle() + 1e-4);
}

// Monocular, a camera swaying sideways in front of room_orbit's first wall (0.4 m either
// way, a 4 s period): enough parallax for a two-view start within a few frames.
SE3d sway(const hal::SyntheticCamera& cam, int i) {
  SE3d T = cam.sample_at(0.0).T_w_c;
  const double x = 0.4 * std::sin(2.0 * std::numbers::pi * static_cast<double>(i) / 120.0);
  T.translation() += T.linear() * Eigen::Vector3d(x, 0.0, 0.0);
  return T;
}

// A return to an earlier segment that fails (the relocalizer's pose finds nothing) goes back
// to starting the new segment from the reference frame it had: the start does not begin again.
TEST(TrackerSegments, FailedReturnKeepsTheNewSegmentsReference) {
  RelocRig rig(options(true), SensorMode::kMono, sway);
  int i = 0;
  int tracked = 0;
  for (; i < 90; ++i) tracked += rig.step(i).state == TrackState::kTracked ? 1 : 0;
  ASSERT_GT(tracked, 45);
  const map::KeyframeId kf0 = rig.map().newest_keyframe();
  ASSERT_EQ(rig.map().keyframe_segment(kf0), 0U);
  for (int k = 0; k < kNewSegmentBlack; ++k, ++i) (void)rig.step(i, true);
  ASSERT_EQ(rig.counters().new_segments, 1U);
  const int reference = i;  // the first frame after the loss: segment 1's two-view reference
  EXPECT_NE(rig.step(i++).state, TrackState::kTracked);
  SE3d nowhere = SE3d::Identity();
  nowhere.translation() = Eigen::Vector3d(100.0, 0.0, 0.0);
  rig.hint(i - 1, nowhere, kf0);
  int started = -1;
  for (int k = 0; k < 60 && started < 0; ++k, ++i) {
    const TrackingResult r = rig.step(i);
    if (r.state == TrackState::kTracked) {
      EXPECT_EQ(r.segment, 1U) << "frame " << i;
      started = i;
    }
  }
  ASSERT_GE(started, 0) << "segment 1 never started";
  EXPECT_EQ(rig.counters().segment_reference_seq, static_cast<std::uint64_t>(reference));
  EXPECT_EQ(rig.counters().segment_returns, 0U);
  EXPECT_GE(rig.counters().relocalization_hints, 1U);
}

// A loop correction published for another segment moves that segment's map, not the one
// tracked: the tracker's pose and prediction stay where they are.
TEST(TrackerSegments, CorrectionOfAnotherSegmentIsNotFollowed) {
  RelocRig rig(options(true));
  int i = 0;
  for (; i < 60; ++i) (void)rig.step(i);
  const std::uint64_t wide_before = rig.counters().wide_searches;
  geometry::Sim3d S;
  S.t = Eigen::Vector3d(1.0, 0.0, 0.0);
  S.s = 1.5;
  {
    std::lock_guard<platform::PiMutex> lock(rig.map().writer_lock());
    rig.map().publish_correction(1, S);
  }
  for (int k = 0; k < 5; ++k, ++i) {
    const TrackingResult r = rig.step(i);
    ASSERT_EQ(r.state, TrackState::kTracked) << "frame " << i;
    EXPECT_LT((r.T_w_c.translation() - rig.truth_in_map(i).translation()).norm(), 0.05)
        << "frame " << i;
  }
  EXPECT_EQ(rig.counters().wide_searches, wide_before);
}

TEST(TrackerSegments, StartIsWrittenByKeyframeCreationNotByTheTracker) {
  RelocRig rig(options());
  // Another thread holds the map's writer lock (a loop correction, say) while the first frame
  // initializes: the tracker must neither wait for it nor give up the start.
  std::atomic<int> phase{0};
  std::thread writer([&] {
    const std::lock_guard<platform::PiMutex> lock(rig.map().writer_lock());
    phase.store(1);
    while (phase.load() != 2) std::this_thread::yield();
  });
  while (phase.load() != 1) std::this_thread::yield();
  const TrackingResult r0 = rig.step(0, false, /*build=*/false);
  phase.store(2);
  writer.join();
  EXPECT_EQ(r0.state, TrackState::kTracked);
  EXPECT_TRUE(r0.keyframe_job);
  EXPECT_EQ(rig.map().live_keyframes(), 0U) << "the tracker wrote the map itself";
  // Keyframe creation has not run yet (busy on its thread): no pose, nothing lost.
  const TrackingResult r1 = rig.step(1, false, /*build=*/false);
  EXPECT_EQ(r1.state, TrackState::kNotInitialized);
  EXPECT_FALSE(r1.keyframe_job);
  EXPECT_EQ(rig.counters().segment_start_waits, 1U);
  EXPECT_EQ(rig.map().segment_start(0).state, map::SegmentStartState::kPending);
  // Once it has, tracking resumes from the start's keyframe and points.
  ASSERT_TRUE(rig.build_queued());
  const map::SegmentStartRecord start = rig.map().segment_start(0);
  ASSERT_EQ(start.state, map::SegmentStartState::kInserted);
  EXPECT_EQ(rig.map().live_keyframes(), 1U);
  EXPECT_EQ(rig.map().keyframe_seq(start.last), 0U);
  EXPECT_GT(rig.map().live_points(), 100U);
  int tracked = 0;
  for (int i = 2; i < 30; ++i) tracked += rig.step(i).state == TrackState::kTracked ? 1 : 0;
  EXPECT_EQ(tracked, 28);
  EXPECT_EQ(rig.counters().segment_start_waits, 1U);
}

}  // namespace
}  // namespace mer::frontend
