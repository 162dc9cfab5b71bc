// The plane_sweep depth-inference backend: depth at the keypoints of a rendered room
// keyframe, swept against recent frames with their true poses, must match the renderer's
// depth; without recent frames, a depth range or a long enough baseline it gives no depth.
#include "depth/plane_sweep_depth.h"

#include <algorithm>
#include <cmath>
#include <vector>

#include <gtest/gtest.h>

#include "features/extractor.h"
#include "hal/synthetic/synthetic_camera.h"

namespace mer::depth {
namespace {

constexpr double kFps = 30.0;

struct Frame {
  SE3d T_w_c;
  cv::Mat gray;
  cv::Mat depth;
};

class PlaneSweepDepthTest : public ::testing::Test {
 protected:
  void SetUp() override {
    cam_ = std::make_unique<hal::SyntheticCamera>("room_orbit", hal::SyntheticOptions{}, false);
    ASSERT_TRUE(cam_->open(4).is_ok());
    const auto& k = cam_->intrinsics();
    K_ = {k.fx, k.fy, k.cx, k.cy};
  }
  Frame render(double t_s) {
    Frame f;
    f.T_w_c = cam_->sample_at(t_s).T_w_c;
    const auto& k = cam_->intrinsics();
    f.gray.create(k.height, k.width, CV_8UC1);
    f.depth.create(k.height, k.width, CV_32FC1);
    cam_->render(f.T_w_c, f.gray, &f.depth, static_cast<std::uint64_t>(std::lround(t_s * kFps)));
    return f;
  }
  std::unique_ptr<hal::SyntheticCamera> cam_;
  geometry::Pinhole K_;
};

TEST_F(PlaneSweepDepthTest, KeypointDepthMatchesRenderedDepth) {
  const Frame key = render(4.0);
  std::vector<Frame> past;
  for (int i = 1; i <= 4; ++i) past.push_back(render(4.0 - 0.1 * i));
  auto ex = features::make_extractor(features::ExtractorOptions{}, key.gray.cols, key.gray.rows);
  ASSERT_TRUE(ex.is_ok());
  ex.value()->extract(key.gray);
  const auto kps = ex.value()->keypoints();
  const std::size_t n = kps.size();
  // Depth range as the keyframe builder would give it (quantiles of the true depth here).
  std::vector<float> z;
  for (const auto& kp : kps) {
    const float d = key.depth.at<float>(static_cast<int>(std::lround(kp.y)),
                                        static_cast<int>(std::lround(kp.x)));
    if (d > 0.0F) z.push_back(d);
  }
  std::sort(z.begin(), z.end());
  std::vector<RecentView> recent;
  for (const Frame& f : past) recent.push_back({&f.gray, f.T_w_c});
  DepthRequest req;
  req.T_w_c = key.T_w_c;
  req.K = K_;
  req.keypoints = kps;
  req.gray = &key.gray;
  req.recent = recent;
  req.depth_hint_min = z[z.size() / 20];
  req.depth_hint_max = z[z.size() * 19 / 20];
  std::vector<float> depth(n), conf(n);
  std::vector<std::uint32_t> sv(n), sk(n);
  DepthResult out{depth, conf, sv, sk, 0, {}, false, {}};
  PlaneSweepDepth backend(PlaneSweepDepthOptions{});
  ASSERT_TRUE(backend.infer(req, out).is_ok());
  std::vector<double> err;
  for (std::size_t i = 0; i < n; ++i) {
    if (depth[i] <= 0.0F) continue;
    EXPECT_GT(conf[i], 0.0F);
    const int u = static_cast<int>(std::lround(kps[i].x));
    const int v = static_cast<int>(std::lround(kps[i].y));
    // Interior pixels only: a corner on an occlusion boundary has no single true depth.
    float lo = 1e9F;
    float hi = 0.0F;
    for (int dv = -2; dv <= 2; ++dv) {
      for (int du = -2; du <= 2; ++du) {
        const float d = key.depth.at<float>(std::clamp(v + dv, 0, key.depth.rows - 1),
                                            std::clamp(u + du, 0, key.depth.cols - 1));
        lo = std::min(lo, d);
        hi = std::max(hi, d);
      }
    }
    if (hi > 1.05F * lo) continue;
    err.push_back(std::abs(depth[i] - lo) / lo);
  }
  ASSERT_GT(err.size(), n / 4) << "too few keypoints got a depth";
  std::nth_element(err.begin(), err.begin() + static_cast<std::ptrdiff_t>(err.size() / 2),
                   err.end());
  const double median = err[err.size() / 2];
  std::printf("plane_sweep at keypoints: %zu of %zu, median relative error %.2f %%\n", err.size(),
              n, 100.0 * median);
  EXPECT_LT(median, 0.03);
  EXPECT_EQ(out.num_valid, static_cast<int>(std::count_if(depth.begin(), depth.end(),
                                                          [](float d) { return d > 0.0F; })));

  // No depth without recent frames, without a depth range, or when every recent frame is
  // closer to the keyframe than the baseline the range asks for.
  DepthRequest none = req;
  none.recent = {};
  ASSERT_TRUE(backend.infer(none, out).is_ok());
  EXPECT_EQ(out.num_valid, 0);
  none = req;
  none.depth_hint_min = 0.0;
  ASSERT_TRUE(backend.infer(none, out).is_ok());
  EXPECT_EQ(out.num_valid, 0);
  PlaneSweepDepthOptions strict;
  strict.min_baseline_ratio = 1.0;  // a baseline of the median depth: none of these
  PlaneSweepDepth strict_backend(strict);
  ASSERT_TRUE(strict_backend.infer(req, out).is_ok());
  EXPECT_EQ(out.num_valid, 0);
}

}  // namespace
}  // namespace mer::depth
