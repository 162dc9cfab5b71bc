// Local bundle adjustment on a synthetic covisibility graph with known ground truth: noisy
// keypoints, perturbed poses and points; the optimization must converge back to the truth,
// 3D-3D edges must fix the metric scale, the per-keyframe depth scale of the `scaled` mode
// must be recovered, and a gross depth outlier must be removed rather than bend the map.
#include "backend/local_ba.h"

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <random>
#include <thread>
#include <vector>

#include <gtest/gtest.h>

#include "geometry/lie.h"
#include "platform/pi_mutex.h"

namespace mer::backend {
namespace {

constexpr int kKeyframes = 6;
constexpr int kPoints = 300;
constexpr double kPixelNoise = 0.5;    // px, keypoint noise
constexpr double kDepthNoise = 0.003;  // relative sensor depth noise
const geometry::Pinhole kK{450.0, 450.0, 320.0, 240.0};
constexpr int kWidth = 640;
constexpr int kHeight = 480;

struct Scene {
  std::vector<SE3d> T_w_c;                 // true poses
  std::vector<Eigen::Vector3d> p_w;        // true points
  std::vector<map::PointId> ids;           // map ids of the points
  std::vector<map::KeyframeId> kf;         // map ids of the keyframes
  std::vector<std::vector<int>> kp_point;  // per keyframe: keypoint -> point index
};

// Keyframes on an arc looking at points 2-4 m ahead; the map holds noisy keypoints, depth
// scaled by depth_scale[k] (1: metric), poses and points perturbed (keyframe 0 exact).
Scene build(map::Map& map, const std::vector<double>& depth_scale, double pose_noise_m,
            double pose_noise_rad, double point_noise_m, int depth_outlier_kp = -1,
            int nk = kKeyframes, int np = kPoints) {
  Scene s;
  std::mt19937 rng(7);
  std::normal_distribution<double> n01(0.0, 1.0);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  for (int i = 0; i < np; ++i) {
    s.p_w.emplace_back(1.5 * u(rng), 1.0 * u(rng), 3.0 + u(rng));
  }
  for (int k = 0; k < nk; ++k) {
    SE3d T = SE3d::Identity();
    T.linear() = geometry::so3_exp(Eigen::Vector3d(0.0, -0.04 * k, 0.0));
    T.translation() = Eigen::Vector3d(0.12 * k, 0.01 * k, 0.0);
    s.T_w_c.push_back(T);
  }
  s.ids.assign(np, map::kNoId);
  s.kp_point.resize(nk);
  for (int k = 0; k < nk; ++k) {
    std::vector<features::Keypoint> kps;
    std::vector<features::Descriptor> descs;
    std::vector<float> depth;
    std::vector<float> conf;
    const SE3d T_c_w = s.T_w_c[static_cast<std::size_t>(k)].inverse();
    for (int i = 0; i < np; ++i) {
      const Eigen::Vector3d pc = T_c_w * s.p_w[static_cast<std::size_t>(i)];
      if (pc.z() <= 0.1) continue;
      const Eigen::Vector2d uv = kK.project(pc);
      if (uv.x() < 0 || uv.y() < 0 || uv.x() >= kWidth || uv.y() >= kHeight) continue;
      features::Keypoint kp;
      kp.x = static_cast<float>(uv.x() + kPixelNoise * n01(rng));
      kp.y = static_cast<float>(uv.y() + kPixelNoise * n01(rng));
      kps.push_back(kp);
      descs.push_back({static_cast<std::uint64_t>(rng()), 0, 0, 0});
      double d = pc.z() * (1.0 + kDepthNoise * n01(rng)) * depth_scale[static_cast<std::size_t>(k)];
      if (k == nk - 1 && static_cast<int>(kps.size()) - 1 == depth_outlier_kp) d *= 2.0;
      depth.push_back(static_cast<float>(d));
      conf.push_back(1.0F);
      s.kp_point[static_cast<std::size_t>(k)].push_back(i);
    }
    map::KeyframeInput in;
    in.seq = static_cast<std::uint64_t>(k);
    in.T_w_c = s.T_w_c[static_cast<std::size_t>(k)];
    if (k > 0) {
      in.T_w_c.linear() =
          in.T_w_c.linear() *
          geometry::so3_exp(pose_noise_rad *
                            Eigen::Vector3d(n01(rng), n01(rng), n01(rng)).normalized());
      in.T_w_c.translation() +=
          pose_noise_m * Eigen::Vector3d(n01(rng), n01(rng), n01(rng)).normalized();
    }
    in.keypoints = kps;
    in.descriptors = descs;
    in.depth = depth;
    in.depth_confidence = conf;
    const auto id = map.add_keyframe(in);
    EXPECT_TRUE(id.is_ok());
    s.kf.push_back(id.value());
    for (std::size_t j = 0; j < kps.size(); ++j) {
      const int i = s.kp_point[static_cast<std::size_t>(k)][j];
      auto& pid = s.ids[static_cast<std::size_t>(i)];
      if (pid == map::kNoId) {
        const Eigen::Vector3d noisy = s.p_w[static_cast<std::size_t>(i)] +
                                      point_noise_m * Eigen::Vector3d(n01(rng), n01(rng), n01(rng));
        const auto p = map.add_point(noisy, id.value(), static_cast<std::uint32_t>(j));
        EXPECT_TRUE(p.is_ok());
        pid = p.value();
      } else {
        EXPECT_TRUE(map.add_observation(pid, id.value(), static_cast<std::uint32_t>(j)));
      }
    }
    map.update_covisibility(id.value());
  }
  for (const map::PointId p : s.ids) {
    if (p != map::kNoId) map.update_point(p);
  }
  return s;
}

map::MapOptions small_map(int max_points = 1000) {
  map::MapOptions o;
  o.max_keyframes = 16;
  o.max_points = max_points;
  o.max_keypoints_per_keyframe = max_points;
  o.cell_table_size = 1024;
  return o;
}

struct Errors {
  double max_position_m = 0.0;    // keyframe centres
  double max_rotation_rad = 0.0;  // keyframe orientations
  double rms_point_m = 0.0;
};

Errors errors(const map::Map& map, const Scene& s) {
  Errors e;
  for (int k = 0; k < kKeyframes; ++k) {
    SE3d T;
    EXPECT_TRUE(map.keyframe_pose(s.kf[static_cast<std::size_t>(k)], T));
    const SE3d& G = s.T_w_c[static_cast<std::size_t>(k)];
    e.max_position_m = std::max(e.max_position_m, (T.translation() - G.translation()).norm());
    e.max_rotation_rad =
        std::max(e.max_rotation_rad, geometry::so3_log(G.linear().transpose() * T.linear()).norm());
  }
  double sum = 0.0;
  int n = 0;
  for (std::size_t i = 0; i < s.ids.size(); ++i) {
    map::PointView pv;
    if (s.ids[i] == map::kNoId || !map.read_point(s.ids[i], pv)) continue;
    sum += (pv.p_w - s.p_w[i]).squaredNorm();
    ++n;
  }
  e.rms_point_m = n > 0 ? std::sqrt(sum / n) : 1e9;
  return e;
}

LocalBaOptions opts(DepthEdgeSetting depth_edges) {
  LocalBaOptions o;
  o.max_iterations = 30;
  o.depth_edges = depth_edges;
  o.depth_sigma_rel = kDepthNoise;
  return o;
}

TEST(LocalBa, NoisyGraphConvergesToGroundTruthWithMetricDepth) {
  map::Map map(small_map());
  const Scene s = build(map, std::vector<double>(kKeyframes, 1.0), 0.05, 0.02, 0.05);
  const Errors before = errors(map, s);
  LocalBundleAdjuster ba(opts(DepthEdgeSetting::kAuto), map, {1.0F}, true, /*metric_depth=*/true);
  EXPECT_EQ(ba.depth_edge_mode(), "metric");
  const LocalBaReport rep = ba.spin_once(s.kf.back(), kK);
  ASSERT_TRUE(rep.ran);
  EXPECT_GT(rep.depth_edges, 0);
  const Errors after = errors(map, s);
  // Before: 5 cm / ~1 deg pose errors, 8.7 cm rms points. After: at the noise floor.
  EXPECT_GT(before.max_position_m, 0.04);
  EXPECT_LT(after.max_position_m, 0.005);
  EXPECT_LT(after.max_rotation_rad, 0.001);
  EXPECT_LT(after.rms_point_m, 0.01);
}

// backend.anchored_sigma_scale: keypoints that measure their point's anchor (here: exact, in
// every other keyframe) weigh more than detections (0.5 px noise) when their sigma is scaled
// down, and the map lands closer to the truth; at 1 the flag changes nothing.
TEST(LocalBa, AnchoredKeypointsWeighMoreWhenTheirSigmaIsScaled) {
  auto solve = [](double scale, bool mark, int min_anchored = 1) {
    map::Map map(small_map());
    const Scene s = build(map, std::vector<double>(kKeyframes, 1.0), 0.05, 0.02, 0.05);
    for (int k = 0; k < kKeyframes; k += 2) {
      const auto kf = s.kf[static_cast<std::size_t>(k)];
      const SE3d T_c_w = s.T_w_c[static_cast<std::size_t>(k)].inverse();
      const auto& pts = s.kp_point[static_cast<std::size_t>(k)];
      for (std::size_t j = 0; j < pts.size(); ++j) {
        const Eigen::Vector2d uv = kK.project(T_c_w * s.p_w[static_cast<std::size_t>(pts[j])]);
        const auto kp = static_cast<std::uint32_t>(j);
        EXPECT_TRUE(map.set_keypoint_position(kf, kp, static_cast<float>(uv.x()),
                                              static_cast<float>(uv.y())));
        EXPECT_TRUE(map.set_keypoint_anchored(kf, kp, mark));
      }
    }
    LocalBaOptions o = opts(DepthEdgeSetting::kAuto);
    o.depth_sigma_rel = 0.05;  // weak depth edges: the keypoints decide
    o.anchored_sigma_scale = scale;
    o.anchored_min_observations = min_anchored;
    LocalBundleAdjuster ba(o, map, {1.0F}, true, /*metric_depth=*/true);
    EXPECT_TRUE(ba.spin_once(s.kf.back(), kK).ran);
    return errors(map, s);
  };
  const Errors plain = solve(1.0, true);
  const Errors unmarked = solve(0.25, false);
  const Errors weighted = solve(0.25, true);
  EXPECT_EQ(plain.rms_point_m, unmarked.rms_point_m);  // same problem, bit for bit
  EXPECT_EQ(plain.max_position_m, unmarked.max_position_m);
  EXPECT_LT(weighted.rms_point_m, 0.5 * plain.rms_point_m)
      << weighted.rms_point_m << " m against " << plain.rms_point_m << " m";
  EXPECT_LT(weighted.max_position_m, plain.max_position_m);
  // Every other keyframe is marked (kKeyframes is even): no point has kKeyframes / 2 + 1, so
  // that minimum keeps every sigma; a minimum of 2 (most points have) keeps most of the gain.
  const Errors too_few = solve(0.25, true, kKeyframes / 2 + 1);
  EXPECT_EQ(plain.rms_point_m, too_few.rms_point_m);
  EXPECT_EQ(plain.max_position_m, too_few.max_position_m);
  const Errors two = solve(0.25, true, 2);
  EXPECT_LT(two.rms_point_m, 0.6 * plain.rms_point_m)
      << two.rms_point_m << " m against " << plain.rms_point_m << " m";
}

// A weighted keypoint keeps its level's outlier gate in pixels: every keypoint marked, with
// 0.5 px noise, one of them 1.8 px off and one 5 px off. At the level's sigma (1 px, gate
// sqrt(5.991) = 2.45 px) only the 5 px one is an outlier, weighted or not; a gate that
// followed the scaled sigma (1.22 px) would take the 1.8 px one and about 5 % of the noise.
TEST(LocalBa, AnchoredKeypointsKeepTheirLevelsOutlierGate) {
  auto solve = [](double scale) {
    map::Map map(small_map());
    const Scene s = build(map, std::vector<double>(kKeyframes, 1.0), 0.02, 0.01, 0.02);
    for (int k = 0; k < kKeyframes; ++k) {
      const auto kf = s.kf[static_cast<std::size_t>(k)];
      for (std::size_t j = 0; j < s.kp_point[static_cast<std::size_t>(k)].size(); ++j) {
        EXPECT_TRUE(map.set_keypoint_anchored(kf, static_cast<std::uint32_t>(j), true));
      }
    }
    const auto kf = s.kf[2];
    for (const auto& [kp, shift] : {std::pair<std::uint32_t, float>{10, 1.8F}, {20, 5.0F}}) {
      const features::Keypoint& k = map.keyframe_keypoints(kf)[kp];
      EXPECT_TRUE(map.set_keypoint_position(kf, kp, k.x + shift, k.y));
    }
    LocalBaOptions o = opts(DepthEdgeSetting::kOff);
    o.anchored_sigma_scale = scale;
    LocalBundleAdjuster ba(o, map, {1.0F}, true, /*metric_depth=*/true);
    return ba.spin_once(s.kf.back(), kK);
  };
  const LocalBaReport plain = solve(1.0);
  const LocalBaReport weighted = solve(0.5);
  ASSERT_TRUE(plain.ran && weighted.ran);
  EXPECT_EQ(plain.outliers, 1);
  EXPECT_EQ(weighted.outliers, 1);
  // The weight is in effect: a point seen at least 3 times (most are) costs 4x, inside the
  // kernel and beyond it alike.
  EXPECT_GT(weighted.initial_cost, 3.0 * plain.initial_cost);
  EXPECT_LT(weighted.initial_cost, 4.001 * plain.initial_cost);
}

// summary.json backend.new_keyframe_*: a new keyframe's first run, measured against the pose
// it was inserted with. The newest keyframe is put 30 % of its step back towards the one
// before; the run (metric depth pins the scale) puts it back: step ratio 1 / 0.7, and a move
// of 0.3 steps of the true length, i.e. 0.3 / 0.7 of the step it was inserted with.
// A second run for the same keyframe is not a first run.
TEST(LocalBa, NewKeyframeShiftIsMeasuredAgainstItsInsertedPose) {
  map::Map map(small_map());
  const Scene s = build(map, std::vector<double>(kKeyframes, 1.0), 0.0, 0.0, 0.0);
  LocalBundleAdjuster ba(opts(DepthEdgeSetting::kAuto), map, {1.0F}, true, /*metric_depth=*/true);
  ASSERT_TRUE(ba.spin_once(s.kf[kKeyframes - 2], kK).ran);
  EXPECT_EQ(ba.totals().new_keyframe_runs, 0U);  // no keyframe before it to measure a step from
  const Eigen::Vector3d step =
      s.T_w_c[kKeyframes - 1].translation() - s.T_w_c[kKeyframes - 2].translation();
  SE3d moved = s.T_w_c[kKeyframes - 1];
  moved.translation() -= 0.3 * step;
  map.set_keyframe_pose(s.kf.back(), moved);
  ASSERT_TRUE(ba.spin_once(s.kf.back(), kK).ran);
  const LocalBaTotals& t = ba.totals();
  ASSERT_EQ(t.new_keyframe_runs, 1U);
  EXPECT_NEAR(std::exp(t.sum_log_step_ratio), 1.0 / 0.7, 0.02);
  EXPECT_NEAR(t.sum_shift_fraction, 0.3 / 0.7, 0.02);  // of the step it was inserted with
  EXPECT_LT(t.sum_rotation_deg, 0.1);
  ASSERT_TRUE(ba.spin_once(s.kf.back(), kK).ran);
  EXPECT_EQ(ba.totals().new_keyframe_runs, 1U);
}

// Reprojection alone leaves the scale of the free keyframes and points undetermined except
// through the one fixed keyframe; metric 3D-3D edges pin it. With every point displaced
// along its ray by a common factor the difference shows.
TEST(LocalBa, MetricDepthEdgesFixTheScale) {
  for (DepthEdgeSetting mode : {DepthEdgeSetting::kOff, DepthEdgeSetting::kMetric}) {
    map::Map map(small_map());
    const Scene s = build(map, std::vector<double>(kKeyframes, 1.0), 0.0, 0.0, 0.0);
    // Shrink the map about keyframe 0's centre by 10 %: poses (but keyframe 0) and points.
    for (std::size_t k = 1; k < s.kf.size(); ++k) {
      SE3d T = s.T_w_c[k];
      T.translation() *= 0.9;
      map.set_keyframe_pose(s.kf[k], T);
    }
    for (std::size_t i = 0; i < s.ids.size(); ++i) {
      if (s.ids[i] != map::kNoId) map.set_point_position(s.ids[i], 0.9 * s.p_w[i]);
    }
    LocalBundleAdjuster ba(opts(mode), map, {1.0F}, true, true);
    ASSERT_TRUE(ba.spin_once(s.kf.back(), kK).ran);
    SE3d T_last;
    ASSERT_TRUE(map.keyframe_pose(s.kf.back(), T_last));
    const double scale = T_last.translation().norm() / s.T_w_c.back().translation().norm();
    if (mode == DepthEdgeSetting::kOff) {
      EXPECT_LT(scale, 0.95) << "reprojection alone cannot see the scale";
    } else {
      EXPECT_NEAR(scale, 1.0, 0.01);
    }
  }
}

// Monocular depth: keyframe 3's local depth is 25 % too large. The scaled mode estimates
// that keyframe's depth scale (folded back into its stored depth) and is not bent by it.
TEST(LocalBa, ScaledModeRecoversAKeyframeDepthScale) {
  std::vector<double> scales(kKeyframes, 1.0);
  scales[3] = 1.25;
  map::Map map(small_map());
  const Scene s = build(map, scales, 0.02, 0.01, 0.02);
  LocalBundleAdjuster ba(opts(DepthEdgeSetting::kScaled), map, {1.0F}, true, false);
  ASSERT_TRUE(ba.spin_once(s.kf.back(), kK).ran);
  const Errors after = errors(map, s);
  EXPECT_LT(after.max_position_m, 0.005);
  EXPECT_LT(after.rms_point_m, 0.01);
  // Stored depth of keyframe 3 is back to the true depth.
  const SE3d T_c_w = s.T_w_c[3].inverse();
  double ratio_sum = 0.0;
  const auto& pts = s.kp_point[3];
  for (std::size_t j = 0; j < pts.size(); ++j) {
    const double truth = (T_c_w * s.p_w[static_cast<std::size_t>(pts[j])]).z();
    ratio_sum += map.keyframe_depth(s.kf[3], static_cast<std::uint32_t>(j)) / truth;
  }
  EXPECT_NEAR(ratio_sum / static_cast<double>(pts.size()), 1.0, 0.01);
}

TEST(LocalBa, GrossDepthOutlierIsRemoved) {
  map::Map map(small_map());
  const Scene s =
      build(map, std::vector<double>(kKeyframes, 1.0), 0.02, 0.01, 0.02, /*outlier kp=*/5);
  LocalBaOptions o = opts(DepthEdgeSetting::kMetric);
  o.resolve_without_outliers = true;
  LocalBundleAdjuster ba(o, map, {1.0F}, true, true);
  const LocalBaReport rep = ba.spin_once(s.kf.back(), kK);
  ASSERT_TRUE(rep.ran);
  EXPECT_GE(rep.outliers, 1);
  const Errors after = errors(map, s);
  EXPECT_LT(after.max_position_m, 0.005);
  EXPECT_LT(after.rms_point_m, 0.01);
}

// resolve_without_outliers off: the outliers are still found and counted, but the run ends
// with its one solve, the same as a run in which nothing is an outlier; on (the default), a
// second solve runs (more iterations) and moves the map.
TEST(LocalBa, SecondSolveWithoutTheOutliersIsAnOption) {
  struct Run {
    LocalBaReport rep;
    std::vector<SE3d> poses;
  };
  const auto run = [](bool resolve, double outlier_chi2, bool deterministic = true) {
    map::Map map(small_map());
    const Scene s =
        build(map, std::vector<double>(kKeyframes, 1.0), 0.02, 0.01, 0.02, /*outlier kp=*/5);
    LocalBaOptions o = opts(DepthEdgeSetting::kMetric);
    o.resolve_without_outliers = resolve;
    o.outlier_chi2 = outlier_chi2;
    if (outlier_chi2 > LocalBaOptions{}.outlier_chi2) o.depth_outlier_chi2 = outlier_chi2;
    o.max_time_ms = 1e5;  // budgeted runs: a budget that does not bind
    LocalBundleAdjuster ba(o, map, {1.0F}, deterministic, true);
    Run r;
    r.rep = ba.spin_once(s.kf.back(), kK);
    for (const map::KeyframeId kf : s.kf) {
      SE3d T;
      EXPECT_TRUE(map.keyframe_pose(kf, T));
      r.poses.push_back(T);
    }
    return r;
  };
  const Run one = run(false, LocalBaOptions{}.outlier_chi2);
  const Run none = run(true, 1e9);  // nothing is an outlier: one solve
  const Run two = run(true, LocalBaOptions{}.outlier_chi2);
  ASSERT_TRUE(one.rep.ran && none.rep.ran && two.rep.ran);
  EXPECT_EQ(none.rep.outliers, 0);
  EXPECT_GE(one.rep.outliers, 1);
  EXPECT_EQ(one.rep.outliers, two.rep.outliers);
  EXPECT_EQ(one.rep.iterations, none.rep.iterations);
  EXPECT_GT(two.rep.iterations, one.rep.iterations);
  EXPECT_FALSE(one.rep.resolved || none.rep.resolved);
  EXPECT_TRUE(two.rep.resolved);
  // With the wall-time budget applied (outside lockstep) and ample time, it solves again too.
  const Run budgeted = run(true, LocalBaOptions{}.outlier_chi2, /*deterministic=*/false);
  EXPECT_TRUE(budgeted.rep.resolved);
  EXPECT_FALSE(one.rep.resolve_skipped || two.rep.resolve_skipped || budgeted.rep.resolve_skipped);
  double moved = 0.0;
  for (std::size_t k = 0; k < one.poses.size(); ++k) {
    EXPECT_TRUE(one.poses[k].isApprox(none.poses[k], 0.0)) << "keyframe " << k;
    moved = std::max(moved, (two.poses[k].translation() - one.poses[k].translation()).norm());
  }
  EXPECT_GT(moved, 0.0);
}

// A window big enough that a solve takes many evaluations: 8 keyframes, 3000 points, noisy.
struct BigWindow {
  static constexpr int kBigPoints = 3000;
  map::Map map{small_map(kBigPoints)};
  Scene s = build(map, std::vector<double>(8, 1.0), 0.2, 0.05, 0.2, -1, 8, kBigPoints);
};

// A long local BA run (no iteration or time limit to speak of) on a worker thread, for tests
// that act on it while it solves: start() launches it, wait_for_iterations() returns once it
// has completed `n` iterations (or ended; bounded, so a hung solver fails the test, not CI).
struct BackgroundRun : BigWindow {
  LocalBaOptions o = [] {
    LocalBaOptions v = opts(DepthEdgeSetting::kMetric);
    v.max_iterations = 100000;
    v.window_keyframes = 8;
    v.max_time_ms = 1e5;
    return v;
  }();
  LocalBundleAdjuster ba{o, map, {1.0F}, /*deterministic=*/false, true};
  LocalBaReport rep;
  std::atomic<bool> done{false};
  std::thread worker;

  void start() {
    worker = std::thread([this] {
      rep = ba.spin_once(s.kf.back(), kK);
      done.store(true);
    });
  }
  void wait_for_iterations(int n) {
    const auto give_up = std::chrono::steady_clock::now() + std::chrono::seconds(60);
    while (ba.iterations_in_run() < n && !done.load() &&
           std::chrono::steady_clock::now() < give_up) {
      std::this_thread::sleep_for(std::chrono::microseconds(100));
    }
  }
  ~BackgroundRun() {  // a test that failed before stopping the run
    if (worker.joinable()) {
      ba.request_abort();
      worker.join();
    }
  }
};

// A request from another thread stops a run after the solver iteration in progress: at
// most one more iteration, the progress made is kept (not discarded, not classified into
// outliers), and the run reports it. How long one iteration takes, i.e. the latency of an
// abort in ms, is measured by mer_bench_backend (Release), not asserted here.
TEST(LocalBa, AbortRequestStopsTheRunAfterTheIterationInProgress) {
  BackgroundRun run;
  LocalBundleAdjuster& ba = run.ba;
  const LocalBaReport& rep = run.rep;
  run.start();
  run.wait_for_iterations(2);
  const int at_request = ba.iterations_in_run();
  ba.request_abort();
  run.worker.join();
  ASSERT_GE(at_request, 2) << "the solve ended before two iterations: make the problem harder";
  EXPECT_TRUE(rep.ran);
  EXPECT_TRUE(rep.aborted) << "the solve converged before the request was seen";
  EXPECT_FALSE(rep.timed_out);
  EXPECT_LE(rep.iterations, at_request + 1);
  EXPECT_EQ(rep.culled_points, 0);
  EXPECT_EQ(ba.totals().aborted, 1U);
  std::printf("abort requested after %d iterations, run stopped after %d (%.1f ms)\n", at_request,
              rep.iterations, rep.ms);
}

// Abort latency, in terms of polls: a request is seen by the very next poll, wherever the run
// is. Polls are every kBuildPollEvery residual blocks while building the problem, at the start
// of every solver evaluation (the cost functions poll the flag on every residual block) and
// between iterations; no uninterrupted stretch of work is left but Ceres' preprocessing and one
// linear solve (the figures in ms: mer_bench_frontend, bm_local_ba_abort).
struct PollLog {
  std::vector<LocalBaPoll> polls;
  int request_at = -1;  // index in polls of the poll whose observer made the request
};

struct AbortFixture : BigWindow {
  LocalBaOptions o = [] {
    LocalBaOptions v = opts(DepthEdgeSetting::kMetric);
    v.max_iterations = 50;
    v.window_keyframes = 8;
    v.outlier_chi2 = 1e9;  // no outliers: one solve, comparable to an aborted run
    v.depth_outlier_chi2 = 1e9;
    return v;
  }();
  std::vector<SE3d> poses() const {
    std::vector<SE3d> out;
    for (const map::KeyframeId k : s.kf) {
      SE3d T;
      EXPECT_TRUE(map.keyframe_pose(k, T));
      out.push_back(T);
    }
    return out;
  }
};

// Runs with an observer that requests an abort at the `nth` poll of kind `where`.
LocalBaReport run_aborting_at(AbortFixture& f, LocalBaPoll where, int nth, PollLog& log) {
  LocalBundleAdjuster ba(f.o, f.map, {1.0F}, /*deterministic=*/true, true);
  int seen = 0;
  ba.set_poll_observer([&](LocalBaPoll p) {
    log.polls.push_back(p);
    if (p == where && ++seen == nth && log.request_at < 0) {
      log.request_at = static_cast<int>(log.polls.size()) - 1;
      ba.request_abort();
    }
  });
  return ba.spin_once(f.s.kf.back(), kK);
}

// Expects the poses of `f` to equal those of a plain run (no abort) of `iterations` solver
// iterations on a fresh copy of the fixture.
void expect_state_of_a_run_of(const AbortFixture& f, int iterations) {
  AbortFixture g;
  g.o.max_iterations = iterations;
  LocalBundleAdjuster ref(g.o, g.map, {1.0F}, true, true);
  ASSERT_TRUE(ref.spin_once(g.s.kf.back(), kK).ran);
  const std::vector<SE3d> a = f.poses();
  const std::vector<SE3d> b = g.poses();
  for (std::size_t k = 0; k < a.size(); ++k) {
    EXPECT_LT((a[k].matrix() - b[k].matrix()).norm(), 1e-9) << "keyframe " << k;
  }
}

// A keyframe that another writer moves while the solve runs without the lock (the loop
// thread's correction, merge or full BA) keeps that writer's pose: the run's result for it
// is in the frame from before. The other keyframes get the run's result.
TEST(LocalBa, KeyframeMovedDuringTheSolveKeepsItsNewPose) {
  AbortFixture f;
  const std::vector<SE3d> before = f.poses();
  const map::KeyframeId moved_kf = f.s.kf.back();
  SE3d moved = before.back();
  moved.translation() += Eigen::Vector3d(0.5, -0.25, 0.125);
  LocalBundleAdjuster ba(f.o, f.map, {1.0F}, /*deterministic=*/true, true);
  bool done = false;
  bool locked = false;
  ba.set_poll_observer([&](LocalBaPoll p) {
    if (p != LocalBaPoll::kIteration || done) return;
    done = true;
    std::unique_lock<platform::PiMutex> lock(f.map.writer_lock(), std::try_to_lock);
    locked = lock.owns_lock();  // the solve runs without the writer lock
    if (locked) f.map.set_keyframe_pose(moved_kf, moved);
  });
  const LocalBaReport rep = ba.spin_once(moved_kf, kK);
  ASSERT_TRUE(done) << "the solve made no iteration";
  ASSERT_TRUE(locked) << "the writer lock was held while Ceres solved";
  EXPECT_GE(rep.stale_writes, 1);
  const std::vector<SE3d> after = f.poses();
  EXPECT_TRUE(after.back().matrix() == moved.matrix());
  int optimized = 0;
  for (std::size_t k = 0; k + 1 < after.size(); ++k) {
    optimized += after[k].matrix() != before[k].matrix() ? 1 : 0;
  }
  EXPECT_GT(optimized, 0) << "the other keyframes were not written";
}

TEST(LocalBa, AbortDuringProblemConstructionEndsTheRunAtThatPoll) {
  AbortFixture f;
  const std::vector<SE3d> before = f.poses();
  PollLog log;
  const LocalBaReport rep = run_aborting_at(f, LocalBaPoll::kBuild, 2, log);
  ASSERT_GE(log.request_at, 0) << "the problem was built in fewer than two polls";
  EXPECT_TRUE(rep.ran);
  EXPECT_TRUE(rep.aborted);
  EXPECT_EQ(rep.iterations, 0);
  // No poll (no further work) after the one that saw the request.
  EXPECT_EQ(static_cast<int>(log.polls.size()), log.request_at + 1);
  // Nothing was optimized: the map is untouched.
  const std::vector<SE3d> after = f.poses();
  for (std::size_t k = 0; k < before.size(); ++k) {
    EXPECT_TRUE(after[k].matrix() == before[k].matrix()) << "keyframe " << k;
  }
}

// A request at the start of a cost-only evaluation (a candidate step) fails that evaluation:
// the step is rejected and the next poll is the end of the iteration, which ends the run
// (no Jacobian evaluation, no further linear solve); the last accepted point is kept.
TEST(LocalBa, AbortDuringACostEvaluationRejectsTheStepAndEndsTheRun) {
  AbortFixture f;
  PollLog log;
  const LocalBaReport rep = run_aborting_at(f, LocalBaPoll::kCostEvaluation, 3, log);
  ASSERT_GE(log.request_at, 0) << "the solve converged in fewer than three steps";
  EXPECT_TRUE(rep.aborted);
  ASSERT_EQ(static_cast<int>(log.polls.size()), log.request_at + 3);
  EXPECT_EQ(log.polls[static_cast<std::size_t>(log.request_at) + 1], LocalBaPoll::kIteration);
  EXPECT_EQ(log.polls[static_cast<std::size_t>(log.request_at) + 2], LocalBaPoll::kSolve);
  EXPECT_EQ(rep.culled_points, 0);
  EXPECT_EQ(rep.outliers, 0);
  // The run kept the two accepted steps: the same state as a run of as many iterations
  // (the aborted iteration made no progress).
  expect_state_of_a_run_of(f, rep.iterations - 1);
}

// A request at the start of a Jacobian evaluation (after an accepted step) cuts it short; the
// iteration ends at once and the accepted step is kept: the same state as a run that stopped
// after that iteration.
TEST(LocalBa, AbortDuringAJacobianEvaluationKeepsTheAcceptedStep) {
  AbortFixture f;
  PollLog log;
  const LocalBaReport rep = run_aborting_at(f, LocalBaPoll::kJacobianEvaluation, 3, log);
  ASSERT_GE(log.request_at, 0) << "the solve converged in fewer than two accepted steps";
  EXPECT_TRUE(rep.aborted);
  ASSERT_EQ(static_cast<int>(log.polls.size()), log.request_at + 3);
  EXPECT_EQ(log.polls[static_cast<std::size_t>(log.request_at) + 1], LocalBaPoll::kIteration);
  expect_state_of_a_run_of(f, rep.iterations);
}

// A request at the first evaluation (Ceres' iteration zero) ends the solve before any step:
// the map keeps its poses.
TEST(LocalBa, AbortDuringTheFirstEvaluationLeavesThePosesUnchanged) {
  AbortFixture f;
  const std::vector<SE3d> before = f.poses();
  PollLog log;
  const LocalBaReport rep = run_aborting_at(f, LocalBaPoll::kJacobianEvaluation, 1, log);
  EXPECT_TRUE(rep.aborted);
  EXPECT_EQ(rep.iterations, 0);
  const std::vector<SE3d> after = f.poses();
  for (std::size_t k = 0; k < before.size(); ++k) {
    EXPECT_LT((after[k].matrix() - before[k].matrix()).norm(), 1e-12) << "keyframe " << k;
  }
}

// The writer lock is free while Ceres solves, and the write-back respects what another
// writer (the keyframe builder) did meanwhile: a point it freed stays freed, a point it moved
// keeps its new position, a keyframe it removed is not written; the rest is written back.
TEST(LocalBa, WriteBackRespectsAConcurrentWriter) {
  BackgroundRun run;
  map::Map& map = run.map;
  const Scene& s = run.s;
  LocalBundleAdjuster& ba = run.ba;
  const LocalBaReport& rep = run.rep;
  SE3d T_newest_before;
  ASSERT_TRUE(map.keyframe_pose(s.kf.back(), T_newest_before));
  run.start();
  run.wait_for_iterations(2);
  // Points observed by the removed keyframe 2 lose an observation; pick the freed and the
  // moved point among those keyframe 2 does not see, so each is stale for one reason only.
  const map::KeyframeId removed_kf = s.kf[2];
  map::PointId freed = map::kNoId;
  map::PointId moved = map::kNoId;
  for (const map::PointId p : s.ids) {
    if (p == map::kNoId) continue;
    std::pair<map::KeyframeId, std::uint32_t> obs[16];
    const std::size_t n = map.point_observations(p, obs);
    bool seen_by_removed = false;
    for (std::size_t i = 0; i < n; ++i) seen_by_removed |= obs[i].first == removed_kf;
    if (seen_by_removed || n < 2) continue;
    if (freed == map::kNoId) {
      freed = p;
    } else {
      moved = p;
      break;
    }
  }
  ASSERT_NE(moved, map::kNoId);
  const Eigen::Vector3d moved_to(0.25, -0.5, 3.5);
  {
    ASSERT_GE(ba.iterations_in_run(), 2) << "the solve ended too early: make it harder";
    ASSERT_TRUE(map.writer_lock().try_lock()) << "the lock must be free while Ceres solves";
    map.set_point_bad(freed);
    map.set_point_position(moved, moved_to);
    ASSERT_TRUE(map.remove_keyframe(removed_kf, 1));
    map.writer_lock().unlock();
  }
  ba.request_abort();
  run.worker.join();
  ASSERT_TRUE(rep.ran);
  EXPECT_TRUE(map.point_is_bad(freed)) << "a freed point must not be written back";
  map::PointView pv;
  ASSERT_TRUE(map.read_point(moved, pv));
  EXPECT_EQ(pv.p_w, moved_to) << "the other writer's newer position is kept";
  EXPECT_FALSE(map.keyframe_is_live(removed_kf));
  EXPECT_GE(rep.stale_writes, 3);  // the freed point, the moved point, the removed keyframe
  EXPECT_EQ(ba.totals().stale_writes, static_cast<std::uint64_t>(rep.stale_writes));
  SE3d T_newest_after;
  ASSERT_TRUE(map.keyframe_pose(s.kf.back(), T_newest_after));
  EXPECT_GT((T_newest_after.translation() - T_newest_before.translation()).norm(), 1e-4)
      << "the rest is written back";
}

// Outside lockstep a run stops at the first iteration boundary past its wall-time budget
// (here the problem is built so large that setup alone exceeds it) and says so.
TEST(LocalBa, WallTimeBudgetBoundsTheRun) {
  constexpr int kBigPoints = 3000;
  map::Map map(small_map(kBigPoints));
  const Scene s = build(map, std::vector<double>(8, 1.0), 0.05, 0.02, 0.05, -1, 8, kBigPoints);
  LocalBaOptions o = opts(DepthEdgeSetting::kMetric);
  o.max_iterations = 100000;
  o.window_keyframes = 8;
  o.max_time_ms = 30.0;
  LocalBundleAdjuster ba(o, map, {1.0F}, /*deterministic=*/false, true);
  const LocalBaReport rep = ba.spin_once(s.kf.back(), kK);
  EXPECT_TRUE(rep.ran);
  EXPECT_TRUE(rep.timed_out);
  EXPECT_FALSE(rep.aborted);
  std::printf("budget 30 ms: run took %.1f ms\n", rep.ms);
  EXPECT_EQ(ba.totals().timed_out, 1U);
}

}  // namespace
}  // namespace mer::backend
