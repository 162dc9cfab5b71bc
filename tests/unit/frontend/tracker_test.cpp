// The front end end to end on rendered frames: Tracker + keyframe creation in lockstep
// against the synthetic camera's ground truth (initialization refusals, tracking accuracy
// in mono and RGB-D, focal estimation, allocation-free steady state).
#include "frontend/tracker.h"

#include <cmath>
#include <cstdio>
#include <memory>
#include <vector>

#include <gtest/gtest.h>

#include "backend/local_ba.h"
#include "depth/keyframe_builder.h"
#include "eval/trajectory_eval.h"
#include "hal/synthetic/synthetic_camera.h"
#include "platform/alloc_counter.h"

namespace mer::frontend {
namespace {

constexpr double kFps = 30.0;

struct RunOutcome {
  bool initialized = false;
  std::uint64_t init_seq = 0;
  SE3d init_T_w_c = SE3d::Identity();  ///< estimate at the initialization frame
  int frames_after_init = 0;
  int tracked_after_init = 0;
  std::vector<Eigen::Vector3d> est;
  std::vector<Eigen::Vector3d> gt;
  std::uint64_t steady_allocations = 0;
  int steady_frames = 0;
  double focal = 0.0;
  TrackerCounters counters;
  double path_length = 0.0;
  double ate_rmse = 0.0;
};

struct Rig {
  hal::SyntheticOptions cam_opts;
  std::unique_ptr<hal::SyntheticCamera> cam;
  hal::Frame frame;
  Rig() {
    cam_opts.num_frames = 100000;
    cam = std::make_unique<hal::SyntheticCamera>("room_orbit", cam_opts, false);
    EXPECT_TRUE(cam->open(8).is_ok());
    frame.gray.create(cam_opts.height, cam_opts.width, CV_8UC1);
    frame.depth.create(cam_opts.height, cam_opts.width, CV_32FC1);
  }
  geometry::Pinhole pinhole() const {
    const auto& k = cam->intrinsics();
    return {k.fx, k.fy, k.cx, k.cy};
  }
  void render(std::uint64_t i, const SE3d& T_w_c) {
    frame.seq = i;
    frame.t_ns = static_cast<std::int64_t>(static_cast<double>(i) / kFps * 1e9);
    frame.has_ground_truth = true;
    frame.T_w_c_gt = T_w_c;
    cam->render(T_w_c, frame.gray, &frame.depth, i);
  }
};

double ate_sim3(const std::vector<Eigen::Vector3d>& est, const std::vector<Eigen::Vector3d>& gt,
                eval::Alignment a) {
  const eval::Sim3 S = eval::align_positions(est, gt, a);
  double sum = 0.0;
  for (std::size_t i = 0; i < est.size(); ++i) sum += (S.apply(est[i]) - gt[i]).squaredNorm();
  return std::sqrt(sum / static_cast<double>(est.size()));
}

template <typename PoseFn>
RunOutcome run(Rig& rig, int frames, PoseFn&& pose_at, SensorMode mode, bool focal_auto,
               double focal_guess_scale = 1.0, const TrackingOptions& topts = {}) {
  map::MapOptions mopts;
  mopts.max_keyframes = 200;
  mopts.max_points = 60000;
  map::Map map(mopts);
  geometry::Pinhole K = rig.pinhole();
  K.fx *= focal_guess_scale;
  K.fy *= focal_guess_scale;
  Tracker tracker(topts, map, K, rig.cam_opts.width, rig.cam_opts.height, mode, focal_auto);
  EXPECT_TRUE(tracker.init().is_ok());
  // Wired as the pipeline wires them (metric depth edges in RGB-D).
  const backend::LocalBaOptions ba_opts;
  depth::KeyframeBuilder builder(depth::DepthOptions{}, mode, map, tracker.level_sigma2(),
                                 ba_opts.depth_sigma_rel);
  EXPECT_TRUE(builder.init().is_ok());
  backend::LocalBundleAdjuster ba(ba_opts, map, tracker.level_sigma2(), true,
                                  builder.metric_map_depth());
  map::KeyframeJob job;
  job.reserve(tracker.max_keypoints(), rig.cam_opts.width, rig.cam_opts.height);
  RunOutcome out;
  for (int i = 0; i < frames; ++i) {
    rig.render(static_cast<std::uint64_t>(i), pose_at(i));
    const std::uint64_t a0 = platform::alloc::thread_allocations();
    const TrackingResult r = tracker.spin_once(rig.frame);
    const std::uint64_t allocs = platform::alloc::thread_allocations() - a0;
    if (r.steady) {
      out.steady_allocations += allocs;
      ++out.steady_frames;
    }
    if (r.keyframe_job) {
      tracker.fill_keyframe_job(rig.frame, job);
      const depth::KeyframeBuildReport rep = builder.spin_once(job);
      if (rep.ok) (void)ba.spin_once(rep.keyframe, job.K);
    }
    if (out.initialized) ++out.frames_after_init;
    if (r.state == TrackState::kTracked) {
      if (!out.initialized) {
        out.initialized = true;
        out.init_seq = r.seq;
        out.init_T_w_c = r.T_w_c;
        out.frames_after_init = 1;
      }
      ++out.tracked_after_init;
      if (!out.gt.empty()) {
        out.path_length += (rig.frame.T_w_c_gt.translation() - out.gt.back()).norm();
      }
      out.est.push_back(r.T_w_c.translation());
      out.gt.push_back(rig.frame.T_w_c_gt.translation());
    }
  }
  out.focal = tracker.focal().value;
  out.counters = tracker.counters();
  if (out.est.size() >= 3) {
    out.ate_rmse =
        ate_sim3(out.est, out.gt,
                 mode == SensorMode::kRgbd ? eval::Alignment::kSe3 : eval::Alignment::kSim3);
  }
  return out;
}

TEST(TrackerSynthetic, PureRotationIsRefusedNotInitialized) {
  Rig rig;
  const Eigen::Vector3d eye(0.3, -0.2, 1.3);
  auto pose = [&](int i) {
    const double a = 0.6 * static_cast<double>(i) * M_PI / 180.0;  // 18 deg/s yaw, no translation
    return look_at(eye, eye + Eigen::Vector3d(std::cos(a), std::sin(a), 0.05),
                   Eigen::Vector3d::UnitZ());
  };
  const RunOutcome o = run(rig, 60, pose, SensorMode::kMono, false);
  EXPECT_FALSE(o.initialized);
  EXPECT_GT(o.counters.init_attempts, 0U);
  EXPECT_EQ(o.counters.init_refusals, o.counters.init_attempts);
}

TEST(TrackerSynthetic, StaticStartIsRefused) {
  Rig rig;
  const SE3d T = rig.cam->sample_at(0.0).T_w_c;
  const RunOutcome o = run(
      rig, 30, [&](int) { return T; }, SensorMode::kMono, false);
  EXPECT_FALSE(o.initialized);
}

// Tracking never breaks after initialization and the trajectory is accurate. The
// initializer waits for 3 degrees of parallax (or a well-determined essential model): on this
// texture seed the camera faces a wall whose pairs are refused as ambiguous until frame ~275,
// so the run is long enough to track 145 frames after it. Measured: 0.72 % of the path
// (the target is 1 %).
TEST(TrackerSynthetic, MonocularOrbitTracksEveryFrameAfterInit) {
  Rig rig;
  const RunOutcome o = run(
      rig, 420, [&](int i) { return rig.cam->sample_at(i / kFps).T_w_c; }, SensorMode::kMono,
      false);
  ASSERT_TRUE(o.initialized);
  EXPECT_LT(o.init_seq, 300U);
  EXPECT_GE(o.tracked_after_init, 0.98 * o.frames_after_init);
  EXPECT_GT(o.path_length, 0.5);
  EXPECT_LT(o.ate_rmse, 0.01 * o.path_length)
      << "ATE " << o.ate_rmse << " m over " << o.path_length << " m";
  std::printf("mono: init at %llu, ATE %.4f m over %.3f m (%.2f %%)\n",
              static_cast<unsigned long long>(o.init_seq), o.ate_rmse, o.path_length,
              100.0 * o.ate_rmse / o.path_length);
  ASSERT_GT(o.steady_frames, 100);
  EXPECT_EQ(o.steady_allocations, 0U);
}

// The same wall with tracking.init.plane_hints: the reference's first ambiguous pair reports
// both candidates' plane normals; the true one stays put while the twin's turns with the
// orbit, and a later frame of the same reference initializes with the true motion about two
// seconds in, not nine (the option stays off by default: see its doc line).
TEST(TrackerSynthetic, PlaneHintsInitializeOnTheWallWithTheTrueMotion) {
  Rig rig;
  TrackingOptions topts;
  topts.init.plane_hints = true;
  auto pose = [&](int i) { return rig.cam->sample_at(i / kFps).T_w_c; };
  const RunOutcome o = run(rig, 90, pose, SensorMode::kMono, false, 1.0, topts);
  ASSERT_TRUE(o.initialized) << "no initialization in 90 frames";
  EXPECT_LT(o.init_seq, 90U);
  // The world frame is the reference camera: compare with the true relative motion.
  const auto ref = static_cast<int>(o.counters.reference_seq);
  const SE3d T_ref_c_gt = pose(ref).inverse() * pose(static_cast<int>(o.init_seq));
  const double rot_err_deg =
      Eigen::AngleAxisd(o.init_T_w_c.linear() * T_ref_c_gt.linear().transpose()).angle() * 180.0 /
      M_PI;
  const Eigen::Vector3d t_est = o.init_T_w_c.translation().normalized();
  const Eigen::Vector3d t_gt = T_ref_c_gt.translation().normalized();
  const double dir_err_deg = std::atan2(t_est.cross(t_gt).norm(), t_est.dot(t_gt)) * 180.0 / M_PI;
  std::printf(
      "plane hints: init at %llu from %d, rotation error %.2f deg, direction error %.2f "
      "deg (true rotation %.1f deg)\n",
      static_cast<unsigned long long>(o.init_seq), ref, rot_err_deg, dir_err_deg,
      Eigen::AngleAxisd(T_ref_c_gt.linear()).angle() * 180.0 / M_PI);
  // The twin is off by degrees of rotation and tens of degrees of direction.
  EXPECT_LT(rot_err_deg, 1.5);
  EXPECT_LT(dir_err_deg, 6.0);
  // Without the hints the same frames are all refused.
  EXPECT_FALSE(run(rig, 90, pose, SensorMode::kMono, false).initialized);
}

// RGB-D: metric from the first frame; the target is ATE <= 1 cm.
TEST(TrackerSynthetic, RgbdOrbitTracksFromTheFirstFrame) {
  Rig rig;
  const RunOutcome o = run(
      rig, 300, [&](int i) { return rig.cam->sample_at(i / kFps).T_w_c; }, SensorMode::kRgbd,
      false);
  ASSERT_TRUE(o.initialized);
  EXPECT_EQ(o.init_seq, 0U);
  EXPECT_GE(o.tracked_after_init, 0.98 * o.frames_after_init);
  EXPECT_LT(o.ate_rmse, 0.01);
  std::printf("rgbd: ATE %.4f m over %.3f m\n", o.ate_rmse, o.path_length);
  EXPECT_EQ(o.steady_allocations, 0U);
}

// tracking.extractor.num_levels accepts 1: matching predicts no level then (it used to read
// the scale of a level 1 that a one-level pyramid does not have, and abort).
TEST(TrackerSynthetic, OneLevelPyramidTracks) {
  Rig rig;
  TrackingOptions topts;
  topts.extractor.num_levels = 1;
  const RunOutcome o = run(
      rig, 60, [&](int i) { return rig.cam->sample_at(i / kFps).T_w_c; }, SensorMode::kRgbd, false,
      1.0, topts);
  ASSERT_TRUE(o.initialized);
  EXPECT_GE(o.tracked_after_init, 0.95 * o.frames_after_init);
  EXPECT_LT(o.ate_rmse, 0.02);
}

TEST(TrackerSynthetic, FocalEstimatedFromAGuessThirtyPercentOff) {
  for (const double scale : {0.7, 1.3}) {
    Rig rig;
    const RunOutcome o = run(
        rig, 320, [&](int i) { return rig.cam->sample_at(i / kFps).T_w_c; }, SensorMode::kMono,
        true, scale);
    ASSERT_TRUE(o.initialized) << "guess x" << scale;
    const double truth = rig.pinhole().fx;
    EXPECT_LT(std::abs(o.focal - truth) / truth, 0.02)
        << "guess x" << scale << ": estimated " << o.focal << " px, truth " << truth << " px";
    std::printf("focal guess x%.1f: %.2f px, truth %.2f px (%.2f %%)\n", scale, o.focal, truth,
                100.0 * (o.focal - truth) / truth);
  }
}

}  // namespace
}  // namespace mer::frontend
