// Keypoint alignment in keyframe creation (depth.align_keypoints): a second keyframe's
// detections of the first one's points, each off by a known amount, are moved onto the
// points' true projections.
#include <cmath>
#include <functional>
#include <vector>

#include <gtest/gtest.h>
#include <opencv2/core.hpp>

#include "depth/keyframe_builder.h"
#include "features/extractor.h"
#include "hal/synthetic/synthetic_camera.h"
#include "map/map.h"

namespace mer::depth {
namespace {

constexpr double kDetectionOffsetPx = 0.6;  // per axis, of each fake detection in view B

struct Views {
  hal::SyntheticOptions cam_opts;
  std::unique_ptr<hal::SyntheticCamera> cam;
  geometry::Pinhole K;
  SE3d T_w_a, T_w_b;
  cv::Mat gray_a, gray_b, depth_a, depth_b;

  Views() {
    cam = std::make_unique<hal::SyntheticCamera>("room_orbit", cam_opts, false);
    EXPECT_TRUE(cam->open(2).is_ok());
    const auto& in = cam->intrinsics();
    K = {in.fx, in.fy, in.cx, in.cy};
    T_w_a = cam->sample_at(10.0).T_w_c;
    T_w_b = cam->sample_at(10.6).T_w_c;
    gray_a.create(in.height, in.width, CV_8UC1);
    gray_b.create(in.height, in.width, CV_8UC1);
    depth_a.create(in.height, in.width, CV_32FC1);
    depth_b.create(in.height, in.width, CV_32FC1);
    cam->render(T_w_a, gray_a, &depth_a, 1);
    cam->render(T_w_b, gray_b, &depth_b, 2);
  }
};

// Depth at the pixel nearest (x, y) where the 5x5 neighbourhood is one surface (0 otherwise).
float smooth_depth(const cv::Mat& d, float x, float y) {
  const int u = static_cast<int>(std::lround(x));
  const int v = static_cast<int>(std::lround(y));
  if (u < 2 || v < 2 || u >= d.cols - 2 || v >= d.rows - 2) return 0.0F;
  float lo = d.at<float>(v, u);
  float hi = lo;
  for (int dv = -2; dv <= 2; ++dv) {
    for (int du = -2; du <= 2; ++du) {
      lo = std::min(lo, d.at<float>(v + dv, u + du));
      hi = std::max(hi, d.at<float>(v + dv, u + du));
    }
  }
  return hi > 1.01F * lo ? 0.0F : d.at<float>(v, u);
}

struct Outcome {
  int checked = 0;          // keypoints of view B compared with their truth
  double median_error = 0;  // px, level 0, over them
  std::uint64_t aligned = 0;
  std::uint64_t refused = 0;
  std::uint64_t refused_residual = 0;
  std::uint64_t refused_shift = 0;
  int anchored_a = 0;  // keypoints of keyframe A marked anchored (the anchors' own)
  int anchored_b = 0;  // of keyframe B (aligned to an anchor)
};

Outcome run(bool align, const std::function<void(DepthOptions&)>& tweak = {}) {
  Views v;
  map::MapOptions mo;
  mo.max_points = 4000;
  mo.max_keyframes = 8;
  map::Map map(mo);
  features::ExtractorOptions eo;
  auto ex = features::make_extractor(eo, v.gray_a.cols, v.gray_a.rows);
  EXPECT_TRUE(ex.is_ok());
  std::vector<float> sigma2;
  for (int l = 0; l < ex.value()->num_levels(); ++l) sigma2.push_back(ex.value()->level_sigma2(l));
  DepthOptions opts;
  opts.align_keypoints = align;
  if (tweak) tweak(opts);
  KeyframeBuilder builder(opts, SensorMode::kRgbd, map, sigma2);
  EXPECT_TRUE(builder.init().is_ok());

  // Keyframe A: its detections become points at their true (sensor) depth.
  map::KeyframeJob job;
  job.reserve(mo.max_keypoints_per_keyframe, v.gray_a.cols, v.gray_a.rows);
  const int n = std::min(ex.value()->extract(v.gray_a), mo.max_keypoints_per_keyframe);
  const auto kps = ex.value()->keypoints();
  const auto descs = ex.value()->descriptors();
  job.seq = 1;
  job.t_ns = 1;
  job.T_w_c = v.T_w_a;
  job.K = v.K;
  job.num_keypoints = n;
  job.has_sensor_depth = true;
  for (int i = 0; i < n; ++i) {
    const auto k = static_cast<std::size_t>(i);
    job.keypoints[k] = kps[k];
    job.descriptors[k] = descs[k];
    job.point_ids[k] = map::kNoId;
    job.point_gens[k] = map::kNoGeneration;
    job.sensor_depth[k] = smooth_depth(v.depth_a, kps[k].x, kps[k].y);
  }
  v.gray_a.copyTo(job.gray);
  const KeyframeBuildReport ra = builder.spin_once(job);
  EXPECT_TRUE(ra.ok);
  EXPECT_GT(ra.new_points, 100);

  // Keyframe B: each point of A "detected" at its true projection + a fixed offset.
  std::vector<Eigen::Vector2d> truth;
  int m = 0;
  const SE3d T_b_w = v.T_w_b.inverse();
  for (int i = 0; i < n; ++i) {
    const map::PointId p = map.keyframe_point(ra.keyframe, static_cast<std::uint32_t>(i));
    map::PointView pv;
    if (p == map::kNoId || !map.read_point(p, pv)) continue;
    const Eigen::Vector3d X = T_b_w * pv.p_w;
    if (X.z() <= 0.0) continue;
    const Eigen::Vector2d uv = v.K.project(X);
    if (smooth_depth(v.depth_b, static_cast<float>(uv.x()), static_cast<float>(uv.y())) <= 0.0F ||
        std::abs(v.depth_b.at<float>(static_cast<int>(std::lround(uv.y())),
                                     static_cast<int>(std::lround(uv.x()))) -
                 X.z()) > 0.01 * X.z()) {
      continue;  // outside B or hidden there
    }
    const auto k = static_cast<std::size_t>(m++);
    job.keypoints[k] = kps[static_cast<std::size_t>(i)];
    job.keypoints[k].x = static_cast<float>(uv.x() + kDetectionOffsetPx);
    job.keypoints[k].y = static_cast<float>(uv.y() - kDetectionOffsetPx);
    job.descriptors[k] = descs[static_cast<std::size_t>(i)];
    job.point_ids[k] = p;
    job.point_gens[k] = pv.generation;
    job.sensor_depth[k] = 0.0F;
    truth.push_back(uv);
  }
  job.seq = 2;
  job.t_ns = 2;
  job.T_w_c = v.T_w_b;
  job.num_keypoints = m;
  v.gray_b.copyTo(job.gray);
  const KeyframeBuildReport rb = builder.spin_once(job);
  EXPECT_TRUE(rb.ok);
  Outcome out;
  out.aligned = builder.totals().aligned_keypoints;
  out.refused = builder.totals().align_refused;
  out.refused_residual = builder.totals().align_refused_residual;
  out.refused_shift = builder.totals().align_refused_shift;
  std::vector<double> err;
  const auto stored = map.keyframe_keypoints(rb.keyframe);
  for (int k = 0; k < m; ++k) {
    const features::Keypoint& kp = stored[static_cast<std::size_t>(k)];
    err.push_back(std::hypot(kp.x - truth[static_cast<std::size_t>(k)].x(),
                             kp.y - truth[static_cast<std::size_t>(k)].y()));
  }
  out.checked = m;
  for (const features::Keypoint& kp : map.keyframe_keypoints(ra.keyframe))
    out.anchored_a += kp.anchored;
  for (const features::Keypoint& kp : stored) out.anchored_b += kp.anchored;
  if (!err.empty()) {
    std::nth_element(err.begin(), err.begin() + static_cast<std::ptrdiff_t>(err.size() / 2),
                     err.end());
    out.median_error = err[err.size() / 2];
  }
  return out;
}

TEST(KeyframeBuilderAlign, MovesDetectionsOntoTheAnchoredPoints) {
  const Outcome off = run(false);
  const Outcome on = run(true);
  ASSERT_GT(on.checked, 100);
  // Off: the detections stay where they were given.
  EXPECT_EQ(off.aligned, 0U);
  EXPECT_EQ(off.anchored_a + off.anchored_b, 0);
  EXPECT_NEAR(off.median_error, kDetectionOffsetPx * std::sqrt(2.0), 1e-3);
  // On: most are aligned (the residual gate, depth.align_max_rms, refuses some where the
  // views differ most), and the median keypoint lands within a fifth of a pixel of the truth
  // (it was 0.85 px off).
  EXPECT_GT(on.aligned, static_cast<std::uint64_t>(on.checked) * 2 / 3);
  EXPECT_LT(on.median_error, 0.2) << "aligned " << on.aligned << " of " << on.checked;
  // The anchors' own keypoints (A) and the aligned ones (B) are marked for the BA's weight
  // (backend.anchored_sigma_scale); B's refused ones stay detections.
  EXPECT_GT(on.anchored_a, 100);
  EXPECT_EQ(static_cast<std::uint64_t>(on.anchored_b), on.aligned);
  // A warp may not stretch one direction at all more than the other: nothing is aligned.
  const Outcome strict = run(true, [](DepthOptions& o) { o.align_max_anisotropy = 1.0; });
  EXPECT_EQ(strict.aligned, 0U);
  EXPECT_GT(strict.refused, static_cast<std::uint64_t>(strict.checked) / 2);
  EXPECT_EQ(strict.refused_residual + strict.refused_shift, 0U);  // all by the geometry
  EXPECT_NEAR(strict.median_error, kDetectionOffsetPx * std::sqrt(2.0), 1e-3);
}

TEST(KeyframeBuilderAlign, CountsEachGateItsRefusals) {
  // A residual gate no real patch pair passes: every refusal past the geometry is residual.
  const Outcome rms = run(true, [](DepthOptions& o) { o.align_max_rms = 1e-3; });
  ASSERT_GT(rms.checked, 100);
  EXPECT_EQ(rms.aligned, 0U);
  EXPECT_GT(rms.refused_residual, static_cast<std::uint64_t>(rms.checked) * 2 / 3);
  EXPECT_EQ(rms.refused_shift, 0U);
  // A shift limit below the detections' 1.2 px offset (0.3 px x the level's scale): most
  // converged alignments are refused by it, the few left moved less than it allows.
  const Outcome shift = run(true, [](DepthOptions& o) { o.align_max_shift_px = 0.3; });
  EXPECT_GT(shift.refused_shift, static_cast<std::uint64_t>(shift.checked) / 2);
  EXPECT_LT(shift.aligned, shift.refused_shift / 4);
  EXPECT_LE(shift.refused_residual + shift.refused_shift, shift.refused);
}

}  // namespace
}  // namespace mer::depth
