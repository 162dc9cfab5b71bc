// Triangulation depth inference on rendered views with exact poses: the depth at the
// keypoints must match the renderer's depth.
#include "depth/triangulation_depth.h"

#include <algorithm>
#include <vector>

#include <gtest/gtest.h>

#include "depth/rgbd_depth.h"
#include "features/extractor.h"
#include "hal/synthetic/synthetic_camera.h"

namespace mer::depth {
namespace {

struct View {
  SE3d T_w_c;
  cv::Mat gray;
  cv::Mat depth;
  std::vector<features::Keypoint> kps;
  std::vector<features::Descriptor> descs;
  std::vector<std::uint32_t> ids;
};

class TriangulationDepthTest : public ::testing::Test {
 protected:
  void SetUp() override {
    cam_ = std::make_unique<hal::SyntheticCamera>("room_orbit", hal::SyntheticOptions{}, false);
    ASSERT_TRUE(cam_->open(4).is_ok());
    const auto& k = cam_->intrinsics();
    K_ = {k.fx, k.fy, k.cx, k.cy};
    auto ex = features::make_extractor(features::ExtractorOptions{}, k.width, k.height);
    ASSERT_TRUE(ex.is_ok());
    extractor_ = std::move(ex.value());
    for (int l = 0; l < extractor_->num_levels(); ++l)
      sigma2_.push_back(extractor_->level_sigma2(l));
  }
  View render(double t_s) {
    View v;
    v.T_w_c = cam_->sample_at(t_s).T_w_c;
    const auto& k = cam_->intrinsics();
    v.gray.create(k.height, k.width, CV_8UC1);
    v.depth.create(k.height, k.width, CV_32FC1);
    cam_->render(v.T_w_c, v.gray, &v.depth, static_cast<std::uint64_t>(t_s * 1000));
    extractor_->extract(v.gray);
    v.kps.assign(extractor_->keypoints().begin(), extractor_->keypoints().end());
    v.descs.assign(extractor_->descriptors().begin(), extractor_->descriptors().end());
    v.ids.assign(v.kps.size(), 0xFFFFFFFFu);
    return v;
  }
  // Relative depth errors of the keypoints that got a depth (interior pixels only: a corner
  // on an occlusion boundary has no single true depth).
  std::vector<double> errors(const View& key, const DepthResult& out, int* boundary) const {
    std::vector<double> e;
    for (std::size_t i = 0; i < key.kps.size(); ++i) {
      if (out.depth[i] <= 0.0F) continue;
      const int u = static_cast<int>(std::lround(key.kps[i].x));
      const int v = static_cast<int>(std::lround(key.kps[i].y));
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
      if (hi > 1.05F * lo) {
        ++*boundary;
        continue;
      }
      e.push_back((out.depth[i] - key.depth.at<float>(v, u)) / key.depth.at<float>(v, u));
    }
    return e;
  }

  std::unique_ptr<hal::SyntheticCamera> cam_;
  geometry::Pinhole K_;
  std::unique_ptr<features::Extractor> extractor_;
  std::vector<float> sigma2_;
};

TEST_F(TriangulationDepthTest, DepthAtKeypointsMatchesRenderedDepth) {
  const View key = render(2.0);
  std::vector<View> others = {render(1.4), render(1.6), render(1.8)};
  std::vector<DepthView> views;
  for (std::size_t i = 0; i < others.size(); ++i) {
    views.push_back(DepthView{static_cast<std::uint32_t>(i), others[i].T_w_c, others[i].kps,
                              others[i].descs, others[i].ids, &others[i].gray});
  }
  DepthRequest req;
  req.T_w_c = key.T_w_c;
  req.K = K_;
  req.keypoints = key.kps;
  req.descriptors = key.descs;
  req.point_ids = key.ids;
  req.level_sigma2 = sigma2_;
  req.gray = &key.gray;
  req.views = views;
  const std::size_t n = key.kps.size();
  std::vector<float> depth(n);
  std::vector<float> conf(n);
  std::vector<std::uint32_t> sv(n);
  std::vector<std::uint32_t> sk(n);
  DepthResult out{depth, conf, sv, sk};
  TriangulationDepth tri(TriangulationOptions{});
  ASSERT_TRUE(tri.infer(req, out).is_ok());
  // With 1 px keypoint noise at f = 457 px, the relative depth error of a point seen under
  // parallax theta is about 1 / (f theta): 12 % at the 1 degree minimum, 4 % at 3 degrees.
  // All points: no bias, median within 5 %. The tail is reported, not asserted: about 10 %
  // of the points have errors above 15 % (wrong epipolar matches on repetitive texture;
  // bundle adjustment and culling have to deal with them).
  int boundary = 0;
  std::vector<double> e = errors(key, out, &boundary);
  ASSERT_GT(e.size(), 100U) << "keypoints with depth: " << out.num_valid;
  std::sort(e.begin(), e.end());
  const double median = e[e.size() / 2];
  std::vector<double> abs_e;
  for (const double x : e) abs_e.push_back(std::abs(x));
  std::sort(abs_e.begin(), abs_e.end());
  const double abs_median = abs_e[abs_e.size() / 2];
  EXPECT_LT(std::abs(median), 0.02) << "depth bias";
  EXPECT_LT(abs_median, 0.05);
  const double p90 = abs_e[abs_e.size() * 9 / 10];
  std::printf("triangulated %zu, bias %.4f, |err| median %.4f p90 %.4f\n", e.size(), median,
              abs_median, p90);
}

TEST(RgbdDepth, PassesSensorDepthWithinRange) {
  const std::vector<features::Keypoint> kps(4);
  const std::vector<float> sensor = {0.05F, 1.5F, 3.0F, 20.0F};
  DepthRequest req;
  req.keypoints = kps;
  req.sensor_depth = sensor;
  std::vector<float> depth(4);
  std::vector<float> conf(4);
  std::vector<std::uint32_t> sv(4);
  std::vector<std::uint32_t> sk(4);
  DepthResult out{depth, conf, sv, sk};
  RgbdDepth rgbd(RgbdDepthOptions{});
  ASSERT_TRUE(rgbd.infer(req, out).is_ok());
  EXPECT_EQ(out.num_valid, 2);
  EXPECT_EQ(depth[0], 0.0F);
  EXPECT_EQ(depth[1], 1.5F);
  EXPECT_EQ(depth[2], 3.0F);
  EXPECT_EQ(depth[3], 0.0F);
  RgbdDepth no_sensor(RgbdDepthOptions{});
  req.sensor_depth = {};
  EXPECT_FALSE(no_sensor.infer(req, out).is_ok());
}

}  // namespace
}  // namespace mer::depth
