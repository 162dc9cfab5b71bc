// The tracker's check of a relocalizer's pose (tracking.relocalization_check) on rendered
// frames: RGB-D room_orbit tracked, then black frames (tracking lost), then a pose handed in
// as the relocalizer would. After a short loss a pose within the motion bound is trusted at
// once and one outside it is refused when the frames do not confirm it; after a long loss even
// the right pose is confirmed on the following frames before a frame is reported tracked.
#include <cstdio>
#include <memory>
#include <numbers>

#include <gtest/gtest.h>

#include "backend/local_ba.h"
#include "depth/keyframe_builder.h"
#include "frontend/tracker.h"
#include "hal/synthetic/synthetic_camera.h"

namespace mer::frontend {
namespace {

constexpr double kFps = 30.0;
constexpr int kTrackedFrames = 90;  // tracked before the loss

/// Tracker, keyframe builder and local BA in lockstep on room_orbit (RGB-D: the map's world
/// frame is the first camera's, in metres).
class RelocRig {
 public:
  explicit RelocRig(const TrackingOptions& topts) {
    cam_opts_.num_frames = 100000;
    cam_ = std::make_unique<hal::SyntheticCamera>("room_orbit", cam_opts_, false);
    EXPECT_TRUE(cam_->open(8).is_ok());
    frame_.gray.create(cam_opts_.height, cam_opts_.width, CV_8UC1);
    frame_.depth.create(cam_opts_.height, cam_opts_.width, CV_32FC1);
    map::MapOptions mopts;
    mopts.max_keyframes = 200;
    mopts.max_points = 60000;
    map_ = std::make_unique<map::Map>(mopts);
    const auto& k = cam_->intrinsics();
    tracker_ = std::make_unique<Tracker>(topts, *map_, geometry::Pinhole{k.fx, k.fy, k.cx, k.cy},
                                         cam_opts_.width, cam_opts_.height, "rgbd", false);
    EXPECT_TRUE(tracker_->init().is_ok());
    tracker_->enable_relocalization(true);
    const backend::LocalBaOptions ba_opts;
    builder_ = std::make_unique<depth::KeyframeBuilder>(
        depth::DepthOptions{}, "rgbd", *map_, tracker_->level_sigma2(), ba_opts.depth_sigma_rel);
    EXPECT_TRUE(builder_->init().is_ok());
    ba_ = std::make_unique<backend::LocalBundleAdjuster>(ba_opts, *map_, tracker_->level_sigma2(),
                                                         true, builder_->metric_map_depth());
    job_.reserve(tracker_->max_keypoints(), cam_opts_.width, cam_opts_.height);
  }

  /// The true camera-to-world pose of frame i (ground-truth world).
  SE3d truth(int i) const { return cam_->sample_at(i / kFps).T_w_c; }
  /// Frame i's true pose in the map's world frame (the first frame's camera).
  SE3d truth_in_map(int i) const { return T_map_gt_ * truth(i); }

  /// Renders and tracks frame i (black when `black`), building keyframes as the pipeline does.
  TrackingResult step(int i, bool black = false) {
    frame_.seq = static_cast<std::uint64_t>(i);
    frame_.t_ns = static_cast<std::int64_t>(static_cast<double>(i) / kFps * 1e9);
    frame_.has_ground_truth = true;
    frame_.T_w_c_gt = truth(i);
    cam_->render(frame_.T_w_c_gt, frame_.gray, &frame_.depth, static_cast<std::uint64_t>(i));
    if (black) {
      frame_.gray.setTo(0);
      frame_.depth.setTo(0.0F);
    }
    const TrackingResult r = tracker_->spin_once(frame_);
    if (i == 0 && r.state == TrackState::kTracked) T_map_gt_ = r.T_w_c * truth(0).inverse();
    if (r.keyframe_job) {
      tracker_->fill_keyframe_job(frame_, job_);
      const depth::KeyframeBuildReport rep = builder_->spin_once(job_);
      if (rep.ok) (void)ba_->spin_once(rep.keyframe, job_.K);
    }
    return r;
  }

  /// Hands the tracker a relocalizer's pose for frame i (camera-to-world in the map frame),
  /// found against the newest keyframe.
  void hint(int i, const SE3d& T_w_c) {
    RelocalizationHint h;
    h.valid = true;
    h.seq = static_cast<std::uint64_t>(i);
    h.T_c_w = T_w_c.inverse();
    h.keyframe = map_->newest_keyframe();
    h.generation = map_->keyframe_generation(h.keyframe);
    tracker_->set_relocalization_hint(h);
  }

  const TrackerCounters& counters() const { return tracker_->counters(); }

 private:
  hal::SyntheticOptions cam_opts_;
  std::unique_ptr<hal::SyntheticCamera> cam_;
  hal::Frame frame_;
  std::unique_ptr<map::Map> map_;
  std::unique_ptr<Tracker> tracker_;
  std::unique_ptr<depth::KeyframeBuilder> builder_;
  std::unique_ptr<backend::LocalBundleAdjuster> ba_;
  map::KeyframeJob job_;
  SE3d T_map_gt_ = SE3d::Identity();
};

/// Tracks frames [0, kTrackedFrames), then `black` black frames; returns the next frame index.
int track_then_lose(RelocRig& rig, int black) {
  int tracked = 0;
  for (int i = 0; i < kTrackedFrames; ++i) {
    tracked += rig.step(i).state == TrackState::kTracked ? 1 : 0;
  }
  EXPECT_GE(tracked, kTrackedFrames - 2);
  int i = kTrackedFrames;
  for (; i < kTrackedFrames + black; ++i) {
    const TrackingResult r = rig.step(i, true);
    EXPECT_NE(r.state, TrackState::kTracked) << "black frame " << i;
  }
  return i;
}

TrackingOptions options(bool new_segments = false) {
  TrackingOptions o;
  o.relocalize_after_lost_frames = 0;
  o.new_segments = new_segments;
  return o;
}

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

// A short loss and a wrong pose (2 m to the side, or facing away): outside the bound it is
// a candidate, the following frames do not confirm it and it is refused; no frame is ever
// reported tracked at it. (The tracker then finds the camera again from its last tracked
// pose, as after any short loss: those frames are tracked at the true pose.)
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
    for (int k = 0; k < 10; ++k, ++i) {
      const TrackingResult r = rig.step(i);
      if (r.state != TrackState::kTracked) continue;
      EXPECT_FALSE(r.relocalized) << "frame " << i;
      EXPECT_LT((r.T_w_c.translation() - rig.truth_in_map(i).translation()).norm(), 0.05)
          << "frame " << i << (turned ? " (turned)" : " (shifted)");
    }
    EXPECT_EQ(rig.counters().relocalization_candidates, 1U);
    EXPECT_EQ(rig.counters().relocalization_confirmed, 0U);
    EXPECT_EQ(
        rig.counters().relocalization_rejected_lost + rig.counters().relocalization_rejected_found,
        1U);
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

// With the check off, a relocalizer's pose is trusted as it comes (the behaviour the check
// replaces): no candidate is counted.
TEST(RelocalizationCheck, OffTrustsEveryPose) {
  TrackingOptions o = options();
  o.relocalization_check.enabled = false;
  RelocRig rig(o);
  const int i = track_then_lose(rig, 3);
  rig.hint(i - 1, rig.truth_in_map(i - 1));
  EXPECT_EQ(rig.step(i).state, TrackState::kTracked);
  EXPECT_EQ(rig.counters().relocalization_trusted, 1U);
  EXPECT_EQ(rig.counters().relocalization_candidates, 0U);
}

}  // namespace
}  // namespace mer::frontend
