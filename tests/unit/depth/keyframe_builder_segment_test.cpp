// Keyframe creation stays inside the keyframe's map segment: a later segment's keyframe is in
// its own world frame, so an earlier segment's keyframes are neither its neighbours (for
// triangulation) nor sources of points to fuse, even when they are the map's newest keyframe
// and their points project onto its keypoints.
#include <memory>
#include <set>
#include <vector>

#include <gtest/gtest.h>
#include <opencv2/core.hpp>

#include "depth/keyframe_builder.h"
#include "features/extractor.h"
#include "hal/synthetic/synthetic_camera.h"
#include "map/map.h"

namespace mer::depth {
namespace {

TEST(KeyframeBuilderSegments, AnotherSegmentsKeyframesAreNotFusedOrUsedAsNeighbours) {
  hal::SyntheticOptions cam_opts;
  hal::SyntheticCamera cam("room_orbit", cam_opts, false);
  ASSERT_TRUE(cam.open(2).is_ok());
  const auto& in = cam.intrinsics();
  const geometry::Pinhole K{in.fx, in.fy, in.cx, in.cy};
  const SE3d T_w_c = cam.sample_at(10.0).T_w_c;
  cv::Mat gray(in.height, in.width, CV_8UC1);
  cv::Mat depth(in.height, in.width, CV_32FC1);
  cam.render(T_w_c, gray, &depth, 1);

  map::MapOptions mo;
  mo.max_points = 4000;
  mo.max_keyframes = 8;
  map::Map map(mo);
  features::ExtractorOptions eo;
  auto ex = features::make_extractor(eo, gray.cols, gray.rows);
  ASSERT_TRUE(ex.is_ok());
  std::vector<float> sigma2;
  for (int l = 0; l < ex.value()->num_levels(); ++l) sigma2.push_back(ex.value()->level_sigma2(l));
  KeyframeBuilder builder(DepthOptions{}, SensorMode::kRgbd, map, sigma2);
  ASSERT_TRUE(builder.init().is_ok());

  map::KeyframeJob job;
  job.reserve(mo.max_keypoints_per_keyframe, gray.cols, gray.rows);
  const int n = std::min(ex.value()->extract(gray), mo.max_keypoints_per_keyframe);
  const auto kps = ex.value()->keypoints();
  const auto descs = ex.value()->descriptors();
  auto fill = [&](std::uint64_t seq, std::uint16_t segment) {
    job.seq = seq;
    job.t_ns = static_cast<std::int64_t>(seq);
    job.T_w_c = T_w_c;
    job.K = K;
    job.segment = segment;
    job.num_keypoints = n;
    job.has_sensor_depth = true;
    for (int i = 0; i < n; ++i) {
      const auto k = static_cast<std::size_t>(i);
      job.keypoints[k] = kps[k];
      job.descriptors[k] = descs[k];
      job.point_ids[k] = map::kNoId;
      job.point_gens[k] = map::kNoGeneration;
      const int u = static_cast<int>(kps[k].x + 0.5F);
      const int v = static_cast<int>(kps[k].y + 0.5F);
      job.sensor_depth[k] = depth.at<float>(v, u);
    }
    gray.copyTo(job.gray);
  };

  // Segment 0's keyframe, then segment 1's first one with the same numbers for its pose (in
  // its own, unrelated world frame) and the same image: every segment-0 point projects onto
  // one of its keypoints.
  fill(1, 0);
  const KeyframeBuildReport a = builder.spin_once(job);
  ASSERT_TRUE(a.ok);
  ASSERT_GT(a.new_points, 100);
  std::set<map::PointId> points_a;
  for (std::uint32_t k = 0; k < map.keyframe_num_keypoints(a.keyframe); ++k) {
    if (const map::PointId p = map.keyframe_point(a.keyframe, k); p != map::kNoId) {
      points_a.insert(p);
    }
  }
  fill(2, 1);
  const KeyframeBuildReport b = builder.spin_once(job);
  ASSERT_TRUE(b.ok);
  EXPECT_EQ(map.keyframe_segment(b.keyframe), 1U);
  EXPECT_EQ(b.fused_observations, 0);
  EXPECT_EQ(b.merged_points, 0);
  int shared = 0;
  for (std::uint32_t k = 0; k < map.keyframe_num_keypoints(b.keyframe); ++k) {
    shared += points_a.count(map.keyframe_point(b.keyframe, k)) > 0 ? 1 : 0;
  }
  EXPECT_EQ(shared, 0) << "segment 1's keyframe observes segment 0's points";
  EXPECT_EQ(map.covisibility_weight(b.keyframe, a.keyframe), 0U);
}

}  // namespace
}  // namespace mer::depth
