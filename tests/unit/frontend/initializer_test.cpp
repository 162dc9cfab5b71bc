// The initializer on rendered room frames: degenerate starts (a blank frame, the same frame
// twice, no depth) are refused with their reason, a two-view start's motion matches the true
// one, and an RGB-D frame with depth starts at once.
#include "frontend/initializer.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdio>
#include <memory>
#include <string>
#include <utility>
#include <vector>

#include <gtest/gtest.h>

#include "features/extractor.h"
#include "hal/synthetic/synthetic_camera.h"

namespace mer::frontend {
namespace {

constexpr double kFps = 30.0;
constexpr double kRadToDeg = 180.0 / M_PI;

/// Renders room_orbit's room from given poses and hands each frame's features to an
/// Initializer, as the tracker does.
struct InitRig {
  TrackingOptions opts;
  hal::SyntheticOptions cam_opts;
  std::unique_ptr<hal::SyntheticCamera> cam;
  hal::Frame frame;
  geometry::Pinhole K;
  std::unique_ptr<features::Extractor> extractor;
  KeypointGrid grid;
  std::unique_ptr<FocalEstimator> focal;
  std::unique_ptr<Initializer> init;

  explicit InitRig(SensorMode mode, const std::string& scenario = "room_orbit",
                   const hal::SyntheticOptions& camera = {}) {
    cam_opts = camera;
    cam_opts.num_frames = 100000;
    cam = std::make_unique<hal::SyntheticCamera>(scenario, cam_opts, false);
    EXPECT_TRUE(cam->open(8).is_ok());
    frame.gray.create(cam_opts.height, cam_opts.width, CV_8UC1);
    frame.depth.create(cam_opts.height, cam_opts.width, CV_32FC1);
    const auto& k = cam->intrinsics();
    K = {k.fx, k.fy, k.cx, k.cy};
    auto ex = features::make_extractor(opts.extractor, cam_opts.width, cam_opts.height);
    EXPECT_TRUE(ex.is_ok());
    extractor = std::move(ex.value());
    const int max_kp = opts.extractor.num_features + opts.extractor.num_levels;
    grid.reserve(cam_opts.width, cam_opts.height, opts.match.grid_cell_px, max_kp);
    focal = std::make_unique<FocalEstimator>(opts.focal, K.fx, false);
    focal->reserve();
    init = std::make_unique<Initializer>(opts, mode);
    init->reserve(max_kp, cam_opts.width, cam_opts.height);
  }

  /// Renders frame `seq` at `T_w_c` (`noise_index`: the image noise's draw).
  void render(std::uint64_t seq, const SE3d& T_w_c, std::uint64_t noise_index) {
    frame.seq = seq;
    frame.t_ns = static_cast<std::int64_t>(static_cast<double>(seq) / cam_opts.fps * 1e9);
    frame.has_ground_truth = true;
    frame.T_w_c_gt = T_w_c;
    cam->render(T_w_c, frame.gray, &frame.depth, noise_index);
  }

  /// Extracts the current frame's features and asks the initializer.
  InitDecision decide() {
    extractor->extract(frame.gray);
    grid.build(extractor->keypoints(), extractor->descriptors());
    const InitDecision d = init->spin_once(frame, grid, K, *focal);
    K = d.K;
    return d;
  }
};

// A sideways walk at 0.3 m/s past the room's centre, looking at a fixed point near the
// (-x, -y) corner: two walls, the floor and boxes in view, the camera turning as it moves.
SE3d corner_walk(int i) {
  const Eigen::Vector3d side = Eigen::Vector3d(2.5, -3.0, 0.0).normalized();
  const Eigen::Vector3d eye = Eigen::Vector3d(0.0, 0.0, 1.3) + 0.01 * i * side;
  return look_at(eye, Eigen::Vector3d(-2.5, -2.0, 1.0), Eigen::Vector3d::UnitZ());
}

TEST(Initializer, BlankFrameIsRefusedForTooFewFeatures) {
  InitRig rig(SensorMode::kMono);
  rig.render(0, corner_walk(0), 0);
  rig.frame.gray.setTo(0);
  const InitDecision d = rig.decide();
  EXPECT_FALSE(d.started);
  EXPECT_EQ(d.refusal, InitRefusal::kTooFewFeatures);
  EXPECT_STREQ(refusal_name(d), "too_few_features");
  EXPECT_FALSE(d.two_view_tried);
  EXPECT_FALSE(rig.init->has_reference());
}

TEST(Initializer, SameFrameTwiceIsRefusedAsStatic) {
  InitRig rig(SensorMode::kMono);
  rig.render(0, corner_walk(0), 0);
  const InitDecision first = rig.decide();
  EXPECT_FALSE(first.started);
  EXPECT_EQ(first.refusal, InitRefusal::kNoReference);
  ASSERT_TRUE(rig.init->has_reference());
  EXPECT_EQ(rig.init->reference_seq(), 0U);

  // The same image again (a later frame number): every keypoint matches where it was.
  rig.render(1, corner_walk(0), 0);
  const InitDecision second = rig.decide();
  EXPECT_FALSE(second.started);
  EXPECT_TRUE(second.two_view_tried);
  EXPECT_EQ(second.refusal, InitRefusal::kTwoView);
  EXPECT_EQ(second.two_view, geometry::TwoViewRefusal::kStatic);
  EXPECT_STREQ(refusal_name(second), "static");  // summary.json `last_init_refusal`
  // The reference is kept: it is not too old yet.
  EXPECT_EQ(rig.init->reference_seq(), 0U);
}

TEST(Initializer, RgbdFrameWithoutDepthIsRefused) {
  InitRig rig(SensorMode::kRgbd);
  rig.render(0, corner_walk(0), 0);
  rig.frame.depth = cv::Mat();
  const InitDecision d = rig.decide();
  EXPECT_FALSE(d.started);
  EXPECT_EQ(d.refusal, InitRefusal::kNoDepth);
  EXPECT_STREQ(refusal_name(d), "no_depth");
}

TEST(Initializer, RgbdStartsFromOneFrameWithDepth) {
  InitRig rig(SensorMode::kRgbd);
  rig.render(5, corner_walk(0), 5);
  const InitDecision d = rig.decide();
  ASSERT_TRUE(d.started) << refusal_name(d);
  EXPECT_EQ(d.num_views, 1);
  EXPECT_EQ(d.ref_seq, 5U);
  EXPECT_TRUE(d.T_c_w.isApprox(SE3d::Identity()));
  EXPECT_GE(d.num_points, rig.opts.init.rgbd_min_points);
  // The points are the keypoints' sensor depths: the median is the scene's, metres.
  EXPECT_GT(d.median_depth, 1.0);
  EXPECT_LT(d.median_depth, 5.0);
  map::SegmentStart st;
  st.reserve(static_cast<int>(rig.grid.capacity()));
  std::vector<features::Keypoint> kps(rig.grid.keypoints().begin(), rig.grid.keypoints().end());
  rig.init->fill_segment_start(st, kps);
  EXPECT_EQ(st.num_views, 1);
  EXPECT_EQ(st.num_points, d.num_points);
  EXPECT_EQ(st.ref_num_keypoints, 0);
}

// Walking sideways, the two-view start comes within a second and its motion (the frame's pose
// in the reference camera's frame, translation up to scale) is the true one.
TEST(Initializer, TwoViewStartMatchesTheTrueMotion) {
  InitRig rig(SensorMode::kMono);
  InitDecision d;
  int start = -1;
  for (int i = 0; i < 30 && start < 0; ++i) {
    rig.render(static_cast<std::uint64_t>(i), corner_walk(i), static_cast<std::uint64_t>(i));
    d = rig.decide();
    if (d.started) start = i;
  }
  ASSERT_GE(start, 0) << "no start in 30 frames; last refusal " << refusal_name(d);
  EXPECT_EQ(d.num_views, 2);
  EXPECT_TRUE(d.two_view_tried);
  EXPECT_GE(d.num_points, rig.opts.init.two_view.min_triangulated);
  EXPECT_GE(d.num_matches, d.num_points);
  EXPECT_NEAR(d.median_depth, 1.0, 0.5);  // points at unit median depth in the reference

  const auto ref = static_cast<int>(d.ref_seq);
  ASSERT_LT(ref, start);
  const SE3d T_ref_c_gt = corner_walk(ref).inverse() * corner_walk(start);
  const double rot_err_deg =
      Eigen::AngleAxisd(d.T_w_c.linear() * T_ref_c_gt.linear().transpose()).angle() * kRadToDeg;
  const Eigen::Vector3d t_est = d.T_w_c.translation().normalized();
  const Eigen::Vector3d t_gt = T_ref_c_gt.translation().normalized();
  const double dir_err_deg = std::atan2(t_est.cross(t_gt).norm(), t_est.dot(t_gt)) * kRadToDeg;
  std::printf(
      "two-view start at frame %d from %d: %d points, rotation error %.3f deg (true %.2f deg), "
      "direction error %.3f deg\n",
      start, ref, d.num_points, rot_err_deg,
      Eigen::AngleAxisd(T_ref_c_gt.linear()).angle() * kRadToDeg, dir_err_deg);
  EXPECT_LT(rot_err_deg, 0.3);
  EXPECT_LT(dir_err_deg, 2.0);
  EXPECT_TRUE((d.T_c_w * d.T_w_c).isApprox(SE3d::Identity(), 1e-9));

  // The keyframe job's copy of the start: two views, the reference's keypoints, and every
  // point in front of the reference camera.
  map::SegmentStart st;
  st.reserve(static_cast<int>(rig.grid.capacity()));
  std::vector<features::Keypoint> kps(rig.grid.keypoints().begin(), rig.grid.keypoints().end());
  rig.init->fill_segment_start(st, kps);
  EXPECT_EQ(st.num_views, 2);
  EXPECT_EQ(st.ref_seq, d.ref_seq);
  EXPECT_EQ(st.num_points, d.num_points);
  EXPECT_GT(st.ref_num_keypoints, 0);
  for (int p = 0; p < st.num_points; ++p) {
    EXPECT_GT(st.points_w[static_cast<std::size_t>(p)].z(), 0.0) << "point " << p;
  }
}

// Both motion errors of a start against the truth, deg: rotation and translation direction.
std::pair<double, double> start_errors_deg(const InitDecision& d, const SE3d& T_w_ref_gt,
                                           const SE3d& T_w_c_gt) {
  const SE3d T_ref_c_gt = T_w_ref_gt.inverse() * T_w_c_gt;
  const double rot =
      Eigen::AngleAxisd(d.T_w_c.linear() * T_ref_c_gt.linear().transpose()).angle() * kRadToDeg;
  const Eigen::Vector3d t_est = d.T_w_c.translation().normalized();
  const Eigen::Vector3d t_gt = T_ref_c_gt.translation().normalized();
  return {rot, std::atan2(t_est.cross(t_gt).norm(), t_est.dot(t_gt)) * kRadToDeg};
}

// Driving down the hall (hall_turn: 10 Hz, a wide image, boxes along the walls), the
// essential model's translation direction is uncertain for the first frames; the frames
// tracked in between settle it, and the start comes earlier than from two views alone, with
// the true motion.
TEST(Initializer, WindowSettlesAnUncertainMotionEarlierThanTwoViews) {
  constexpr int kFrames = 30;
  hal::SyntheticOptions hall;
  hall.fps = 10.0;
  hall.width = 1241;
  hall.height = 376;
  hall.fov_x_deg = 81.6;
  hall.num_boxes = 16;
  hall.texture = "procedural";
  std::array<int, 2> start{-1, -1};
  for (const bool window : {false, true}) {
    InitRig rig(SensorMode::kMono, "hall_turn", hall);
    rig.opts.init.window.enabled = window;
    rig.init = std::make_unique<Initializer>(rig.opts, SensorMode::kMono);
    rig.init->reserve(static_cast<int>(rig.grid.capacity()), hall.width, hall.height);
    const auto pose = [&](int i) { return rig.cam->sample_at(i / hall.fps).T_w_c; };
    InitDecision d;
    int& first = start[window ? 1 : 0];
    for (int i = 0; i < kFrames && first < 0; ++i) {
      rig.render(static_cast<std::uint64_t>(i), pose(i), static_cast<std::uint64_t>(i));
      d = rig.decide();
      std::printf("window %d frame %d: %s\n", window, i, d.started ? "start" : refusal_name(d));
      if (d.started) first = i;
    }
    if (!window) {
      if (first < 0) first = kFrames;  // none within the frames tried
      EXPECT_EQ(d.window_views, 0);
      continue;
    }
    ASSERT_GE(first, 0) << "no start in " << kFrames << " frames; last refusal " << refusal_name(d);
    EXPECT_GE(d.window_views, rig.opts.init.window.min_views);
    EXPECT_GE(d.num_points, rig.opts.init.two_view.min_triangulated);
    const auto [rot_err, dir_err] =
        start_errors_deg(d, pose(static_cast<int>(d.ref_seq)), pose(first));
    std::printf(
        "window start at frame %d from %llu: %d views, %d points, rotation error %.3f "
        "deg, direction error %.3f deg\n",
        first, static_cast<unsigned long long>(d.ref_seq), d.window_views, d.num_points, rot_err,
        dir_err);
    EXPECT_LT(rot_err, 0.3);
    EXPECT_LT(dir_err, 2.0);
  }
  EXPECT_LT(start[1], start[0]);
}

// Turning on the spot (room_rotation's yaw sweeps of +-40 deg and pitch sweeps of +-15 deg,
// without its hand translation), the pairs are refused as pure rotations: no metric map, but
// each such frame has its orientation, in the world of its chain of references, within a
// fraction of a degree.
TEST(Initializer, PureRotationGivesOrientationAndNoMap) {
  hal::SyntheticOptions room;
  room.num_boxes = 10;
  room.sweep_yaw_deg = 40.0;
  room.sweep_pitch_deg = 15.0;
  room.sweep_period_s = 6.0;
  room.sweep_translation_m = 0.0;
  room.texture = "procedural";
  InitRig rig(SensorMode::kMono, "room_rotation", room);
  const auto pose = [&](int i) { return rig.cam->sample_at(i / room.fps).T_w_c; };
  constexpr int kFrames = 150;
  std::uint32_t chain = rig.init->orientation_chain();
  int chain_world = -1;  // frame whose camera is the current chain's world
  int chains = 0;
  int oriented = 0;
  double worst_deg = 0.0;
  double sum_sq = 0.0;
  for (int i = 0; i < kFrames; ++i) {
    rig.render(static_cast<std::uint64_t>(i), pose(i), static_cast<std::uint64_t>(i));
    const InitDecision d = rig.decide();
    ASSERT_FALSE(d.started) << "frame " << i << ": a metric map from a rotation";
    if (d.has_orientation) {
      ASSERT_EQ(d.orientation_chain, chain);
      ASSERT_GE(chain_world, 0);
      const Eigen::Matrix3d R_c_world_gt =
          pose(i).linear().transpose() * pose(chain_world).linear();
      const double err = Eigen::AngleAxisd(d.R_c_w * R_c_world_gt.transpose()).angle() * kRadToDeg;
      worst_deg = std::max(worst_deg, err);
      sum_sq += err * err;
      ++oriented;
    }
    if (rig.init->orientation_chain() != chain || chain_world < 0) {
      ++chains;
      chain = rig.init->orientation_chain();
      chain_world = static_cast<int>(rig.init->reference_seq());
    }
  }
  std::printf(
      "pure rotation: %d of %d frames with an orientation in %d chain(s), RMS error %.3f "
      "deg, worst %.3f deg\n",
      oriented, kFrames, chains, std::sqrt(sum_sq / std::max(oriented, 1)), worst_deg);
  EXPECT_GE(oriented, kFrames / 2);
  EXPECT_LT(worst_deg, 0.5);
}

// The matches to the reference, checked against the rendered depth and the true poses: with
// init.align each match is moved to where the reference keypoint's patch aligns, and the
// ones whose patch does not align are dropped, so that few remain more than kGtWrongMatchPx
// from the true pixel; without it a descriptor match lands on an independent detection near
// the point, or on a look-alike corner.
TEST(Initializer, AlignedMatchesMeasureTheReferencePoint) {
  constexpr int kFrames = 12;
  std::array<std::pair<long, long>, 2> audit{};  // (checked, wrong), align off then on
  for (const bool align : {false, true}) {
    InitRig rig(SensorMode::kMono);
    rig.opts.init.align.enabled = align;
    rig.opts.init.window.enabled = false;
    rig.opts.init.two_view.min_parallax_deg = 90.0;  // never start: one reference, audited
    rig.opts.init.two_view.confident_parallax_deg = 90.0;
    rig.init = std::make_unique<Initializer>(rig.opts, SensorMode::kMono);
    rig.init->reserve(rig.opts.extractor.num_features + rig.opts.extractor.num_levels,
                      rig.cam_opts.width, rig.cam_opts.height);
    auto& [checked, wrong] = audit[align ? 1 : 0];
    for (int i = 0; i < kFrames; ++i) {
      rig.render(static_cast<std::uint64_t>(i), corner_walk(i), static_cast<std::uint64_t>(i));
      const InitDecision d = rig.decide();
      ASSERT_FALSE(d.started);
      checked += d.gt_checked;
      wrong += d.gt_wrong;
    }
  }
  const auto share = [](const std::pair<long, long>& a) {
    return static_cast<double>(a.second) / static_cast<double>(std::max(a.first, 1L));
  };
  std::printf("matches more than %.0f px off: %ld of %ld unaligned, %ld of %ld aligned\n",
              kGtWrongMatchPx, audit[0].second, audit[0].first, audit[1].second, audit[1].first);
  ASSERT_GT(audit[0].first, 1000);
  ASSERT_GT(audit[1].first, audit[0].first / 3);  // most matches survive the alignment
  EXPECT_LT(share(audit[1]), 0.05);
  EXPECT_LT(share(audit[1]), 0.25 * share(audit[0]));
}

// room_orbit's first second faces one wall: every pair is a planar tie. The camera moves
// nearly along a line, so the twin explains the frames in between as well as the truth: by
// default the window does not decide ties, and no start comes from them.
TEST(Initializer, WallTiesWaitForParallax) {
  constexpr int kFrames = 30;
  InitRig rig(SensorMode::kMono);
  int ties = 0;
  for (int i = 0; i < kFrames; ++i) {
    const SE3d T = rig.cam->sample_at(i / kFps).T_w_c;
    rig.render(static_cast<std::uint64_t>(i), T, static_cast<std::uint64_t>(i));
    const InitDecision d = rig.decide();
    ASSERT_FALSE(d.started) << "frame " << i;
    if (d.refusal == InitRefusal::kTwoView && d.two_view == geometry::TwoViewRefusal::kAmbiguous) {
      ++ties;
    }
  }
  EXPECT_GE(ties, kFrames / 2);
}

}  // namespace
}  // namespace mer::frontend
