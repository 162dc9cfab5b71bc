// A lockstep rig for tests of the tracker's relocalization and map segments: tracker,
// keyframe builder and local BA on rendered RGB-D room_orbit frames, black frames to lose
// tracking, and relocalizer poses handed in as the pipeline does.
#pragma once

#include <functional>
#include <memory>
#include <utility>

#include <gtest/gtest.h>

#include "backend/local_ba.h"
#include "depth/keyframe_builder.h"
#include "frontend/tracker.h"
#include "hal/synthetic/synthetic_camera.h"

namespace mer::frontend::test {

constexpr double kFps = 30.0;
constexpr int kTrackedFrames = 90;  // tracked before the loss

/// Tracker, keyframe builder and local BA in lockstep on room_orbit (RGB-D: the map's world
/// frame is the first camera's, in metres).
class RelocRig {
 public:
  /// `path` (when set) replaces the room_orbit trajectory: the true
  /// camera-to-world pose of frame i in the camera's room.
  explicit RelocRig(const TrackingOptions& topts, SensorMode mode = SensorMode::kRgbd,
                    std::function<SE3d(const hal::SyntheticCamera&, int)> path = {})
      : path_(std::move(path)) {
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
                                         cam_opts_.width, cam_opts_.height, mode, false);
    EXPECT_TRUE(tracker_->init().is_ok());
    tracker_->enable_relocalization(true);
    const backend::LocalBaOptions ba_opts;
    builder_ = std::make_unique<depth::KeyframeBuilder>(
        depth::DepthOptions{}, mode, *map_, tracker_->level_sigma2(), ba_opts.depth_sigma_rel);
    EXPECT_TRUE(builder_->init().is_ok());
    ba_ = std::make_unique<backend::LocalBundleAdjuster>(ba_opts, *map_, tracker_->level_sigma2(),
                                                         true, builder_->metric_map_depth());
    job_.reserve(tracker_->max_keypoints(), cam_opts_.width, cam_opts_.height);
  }

  /// The true camera-to-world pose of frame i (ground-truth world).
  SE3d truth(int i) const { return path_ ? path_(*cam_, i) : cam_->sample_at(i / kFps).T_w_c; }
  /// Frame i's true pose in the map's world frame (the first frame's camera).
  SE3d truth_in_map(int i) const { return T_map_gt_ * truth(i); }

  /// Renders and tracks frame i (black when `black`), building keyframes as the pipeline does;
  /// with `build` false a keyframe job is only queued (filled), as when keyframe creation is
  /// busy on its thread: build_queued() runs it.
  TrackingResult step(int i, bool black = false, bool build = true) {
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
      queued_ = true;
      if (build) build_queued();
    }
    return r;
  }

  /// Creates the keyframe of the job queued last (and its local BA); false when none is queued.
  bool build_queued() {
    if (!queued_) return false;
    queued_ = false;
    const depth::KeyframeBuildReport rep = builder_->spin_once(job_);
    if (rep.ok) (void)ba_->spin_once(rep.keyframe, job_.K);
    return true;
  }

  /// Hands the tracker a relocalizer's pose for frame i (camera-to-world in the map frame),
  /// found against `kf` (the newest keyframe when kNoId).
  void hint(int i, const SE3d& T_w_c, map::KeyframeId kf = map::kNoId) {
    RelocalizationHint h;
    h.valid = true;
    h.seq = static_cast<std::uint64_t>(i);
    h.T_c_w = T_w_c.inverse();
    h.keyframe = kf == map::kNoId ? map_->newest_keyframe() : kf;
    h.generation = map_->keyframe_generation(h.keyframe);
    tracker_->set_relocalization_hint(h);
  }

  map::Map& map() { return *map_; }
  const Tracker& tracker() const { return *tracker_; }

  const TrackerCounters& counters() const { return tracker_->counters(); }

 private:
  std::function<SE3d(const hal::SyntheticCamera&, int)> path_;
  hal::SyntheticOptions cam_opts_;
  std::unique_ptr<hal::SyntheticCamera> cam_;
  hal::Frame frame_;
  std::unique_ptr<map::Map> map_;
  std::unique_ptr<Tracker> tracker_;
  std::unique_ptr<depth::KeyframeBuilder> builder_;
  std::unique_ptr<backend::LocalBundleAdjuster> ba_;
  map::KeyframeJob job_;
  bool queued_ = false;  // job_ holds a job not built yet
  SE3d T_map_gt_ = SE3d::Identity();
};

/// Tracks frames [0, kTrackedFrames), then `black` black frames; returns the next frame index.
inline int track_then_lose(RelocRig& rig, int black) {
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

inline TrackingOptions options(bool new_segments = false) {
  TrackingOptions o;
  o.relocalize_after_lost_frames = 0;
  o.new_segments = new_segments;
  return o;
}

}  // namespace mer::frontend::test
