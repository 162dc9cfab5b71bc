// The external depth-inference backend over an in-memory DepthMapSource: depth at the
// keypoints sampled from the map nearest the keyframe's time (within the tolerance), maps of
// another resolution, depth edges, the depth range, a missing map and a failing read.
#include "depth/external_depth.h"

#include <cmath>
#include <string>
#include <vector>

#include <gtest/gtest.h>
#include <opencv2/core.hpp>

namespace mer::depth {
namespace {

constexpr int kWidth = 64;
constexpr int kHeight = 48;
constexpr std::int64_t kNsPerS = 1'000'000'000;
constexpr std::int64_t kMs = 1'000'000;

/// True depth of the test scene at keyframe pixel (x, y): a smooth tilted plane.
double plane_depth(double x, double y) {
  return 2.0 + 0.005 * x + 0.0025 * y;
}

/// A depth map of the plane at `w` x `h` (a plain resize of the kWidth x kHeight image),
/// offset by `offset` so each map is recognisable.
cv::Mat plane_map(int w, int h, float offset) {
  cv::Mat m(h, w, CV_32FC1);
  const double sx = static_cast<double>(kWidth) / w;
  const double sy = static_cast<double>(kHeight) / h;
  for (int v = 0; v < h; ++v) {
    for (int u = 0; u < w; ++u) {
      // Map pixel centre (u, v) is keyframe pixel ((u + 1/2) sx - 1/2, (v + 1/2) sy - 1/2).
      m.at<float>(v, u) =
          static_cast<float>(plane_depth((u + 0.5) * sx - 0.5, (v + 0.5) * sy - 0.5)) + offset;
    }
  }
  return m;
}

/// Maps held in memory.
class MemoryMaps final : public DepthMapSource {
 public:
  std::string describe() const override { return "/data/maps"; }
  std::span<const std::int64_t> timestamps() const override { return t_ns; }
  Status load(std::size_t index, cv::Mat& depth) override {
    ++loads;
    if (!fail_with.empty()) return input_error(fail_with);
    maps.at(index).copyTo(depth);
    return Status::ok();
  }
  std::vector<std::int64_t> t_ns;
  std::vector<cv::Mat> maps;
  std::string fail_with;
  int loads = 0;
};

class ExternalDepthTest : public ::testing::Test {
 protected:
  void SetUp() override {
    gray_ = cv::Mat(kHeight, kWidth, CV_8UC1, cv::Scalar(128));
    for (const auto& [x, y] :
         {std::pair{10.0F, 10.0F}, {20.5F, 7.25F}, {31.7F, 30.1F}, {50.0F, 40.0F}, {5.5F, 44.5F}}) {
      features::Keypoint kp;
      kp.x = x;
      kp.y = y;
      kps_.push_back(kp);
    }
    const std::size_t n = kps_.size();
    depth_.assign(n, -1.0F);
    conf_.assign(n, -1.0F);
    sv_.assign(n, 0);
    sk_.assign(n, 0);
  }
  DepthRequest request(std::int64_t t_ns) {
    DepthRequest req;
    req.t_ns = t_ns;
    req.keypoints = kps_;
    req.gray = &gray_;
    return req;
  }
  DepthResult result() { return {depth_, conf_, sv_, sk_, 0, {}, false, {}}; }

  cv::Mat gray_;
  std::vector<features::Keypoint> kps_;
  std::vector<float> depth_, conf_;
  std::vector<std::uint32_t> sv_, sk_;
};

TEST_F(ExternalDepthTest, DepthAtKeypointsComesFromTheNearestMap) {
  MemoryMaps maps;
  // Three maps 100 ms apart, each offset by its index so the one used is visible.
  for (int i = 0; i < 3; ++i) {
    maps.t_ns.push_back(i * 100 * kMs);
    maps.maps.push_back(plane_map(kWidth, kHeight, static_cast<float>(i)));
  }
  ExternalDepthOptions opts;
  opts.max_time_diff_s = 0.03;
  opts.confidence = 0.7;
  ExternalDepth backend(opts, maps);
  EXPECT_EQ(backend.name(), "external");
  DepthResult out = result();
  ASSERT_TRUE(backend.infer(request(110 * kMs), out).is_ok());  // 10 ms from map 1
  EXPECT_FALSE(out.input_missing);
  EXPECT_EQ(out.num_valid, static_cast<int>(kps_.size()));
  for (std::size_t i = 0; i < kps_.size(); ++i) {
    EXPECT_NEAR(depth_[i], plane_depth(kps_[i].x, kps_[i].y) + 1.0, 1e-4) << i;
    EXPECT_FLOAT_EQ(conf_[i], 0.7F);
    EXPECT_EQ(sv_[i], kNoSupport);
    EXPECT_EQ(sk_[i], kNoSupport);
  }
  out = result();
  ASSERT_TRUE(backend.infer(request(175 * kMs), out).is_ok());  // nearer map 2
  EXPECT_NEAR(depth_[0], plane_depth(kps_[0].x, kps_[0].y) + 2.0, 1e-4);
}

TEST_F(ExternalDepthTest, NearestHonoursTheToleranceAtBothEnds) {
  MemoryMaps maps;
  maps.t_ns = {1 * kNsPerS, 2 * kNsPerS, 3 * kNsPerS};
  ExternalDepthOptions opts;
  opts.max_time_diff_s = 0.02;
  const ExternalDepth backend(opts, maps);
  EXPECT_EQ(backend.nearest(1 * kNsPerS), 0U);
  EXPECT_EQ(backend.nearest(1 * kNsPerS - 20 * kMs), 0U) << "exactly the tolerance";
  EXPECT_FALSE(backend.nearest(1 * kNsPerS - 21 * kMs)) << "before the first map";
  EXPECT_EQ(backend.nearest(2 * kNsPerS + 19 * kMs), 1U);
  EXPECT_EQ(backend.nearest(2 * kNsPerS - 19 * kMs), 1U);
  EXPECT_FALSE(backend.nearest(2 * kNsPerS + 500 * kMs)) << "between two maps, far from both";
  EXPECT_EQ(backend.nearest(3 * kNsPerS + 20 * kMs), 2U);
  EXPECT_FALSE(backend.nearest(3 * kNsPerS + 21 * kMs)) << "after the last map";
  ExternalDepthOptions wide = opts;
  wide.max_time_diff_s = 1.0;
  const ExternalDepth loose(wide, maps);
  EXPECT_EQ(loose.nearest(2 * kNsPerS + 500 * kMs), 1U) << "a tie goes to the earlier map";
  EXPECT_EQ(loose.nearest(2 * kNsPerS + 501 * kMs), 2U);
}

TEST_F(ExternalDepthTest, AMissingMapIsFlaggedAndNamesTheTimeAndTheFolder) {
  MemoryMaps maps;
  maps.t_ns = {1 * kNsPerS};
  maps.maps = {plane_map(kWidth, kHeight, 0.0F)};
  ExternalDepth backend(ExternalDepthOptions{}, maps);
  DepthResult out = result();
  const Status s = backend.infer(request(2 * kNsPerS + 250 * kMs), out);
  ASSERT_FALSE(s.is_ok());
  EXPECT_TRUE(out.input_missing);
  EXPECT_EQ(out.num_valid, 0);
  EXPECT_NE(s.message().find("2.250000"), std::string::npos) << s.message();
  EXPECT_NE(s.message().find("/data/maps"), std::string::npos) << s.message();
  EXPECT_EQ(maps.loads, 0) << "nothing to read";
  for (const float d : depth_) EXPECT_EQ(d, 0.0F);
}

TEST_F(ExternalDepthTest, AFailedReadIsAnErrorNotAMissingMap) {
  MemoryMaps maps;
  maps.t_ns = {0};
  maps.maps = {plane_map(kWidth, kHeight, 0.0F)};
  maps.fail_with = "depth map '/data/maps/0.pfm': truncated";
  ExternalDepth backend(ExternalDepthOptions{}, maps);
  DepthResult out = result();
  const Status s = backend.infer(request(0), out);
  ASSERT_FALSE(s.is_ok());
  EXPECT_FALSE(out.input_missing);
  EXPECT_NE(s.message().find("0.pfm"), std::string::npos) << s.message();
  EXPECT_EQ(out.num_valid, 0);
}

TEST_F(ExternalDepthTest, AMapOfAnotherResolutionIsScaledToTheImage) {
  // A half- and a quarter-resolution map (a learned model's output size), and a map with
  // another aspect ratio: keypoints read the same plane depth.
  for (const auto& [w, h] : {std::pair{kWidth / 2, kHeight / 2},
                             {kWidth / 4, kHeight / 4},
                             {kWidth * 3 / 4, kHeight / 3},
                             {kWidth * 2, kHeight * 2}}) {
    MemoryMaps maps;
    maps.t_ns = {0};
    maps.maps = {plane_map(w, h, 0.0F)};
    ExternalDepth backend(ExternalDepthOptions{}, maps);
    DepthResult out = result();
    ASSERT_TRUE(backend.infer(request(0), out).is_ok());
    int valid = 0;
    for (std::size_t i = 0; i < kps_.size(); ++i) {
      if (depth_[i] == 0.0F) continue;  // within half a map pixel of the border
      ++valid;
      EXPECT_NEAR(depth_[i], plane_depth(kps_[i].x, kps_[i].y), 1e-4) << w << "x" << h << " " << i;
    }
    EXPECT_EQ(valid, out.num_valid);
    EXPECT_GE(valid, 4) << w << "x" << h;
  }
}

TEST_F(ExternalDepthTest, DepthEdgesAndTheDepthRangeAreRefused) {
  MemoryMaps maps;
  maps.t_ns = {0};
  cv::Mat m = plane_map(kWidth, kHeight, 0.0F);
  m.colRange(21, kWidth) += cv::Scalar(3.0);  // an occlusion boundary between columns 20 and 21
  maps.maps = {m};
  ExternalDepthOptions opts;
  opts.max_depth = 4.0;
  ExternalDepth backend(opts, maps);
  DepthResult out = result();
  ASSERT_TRUE(backend.infer(request(0), out).is_ok());
  EXPECT_GT(depth_[0], 0.0F) << "(10, 10): smooth, near";
  EXPECT_EQ(depth_[1], 0.0F) << "(20.5, 7.25): straddles the edge";
  EXPECT_EQ(depth_[2], 0.0F) << "(31.7, 30.1): beyond max_depth";
  EXPECT_EQ(conf_[1], 0.0F);
  EXPECT_EQ(out.num_valid, 2) << "(10, 10) and (5.5, 44.5)";
}

TEST_F(ExternalDepthTest, ScaleFollowsTheOption) {
  MemoryMaps maps;
  ExternalDepthOptions opts;
  EXPECT_EQ(ExternalDepth(opts, maps).scale(), DepthScale::kUnknown);
  opts.scale = ExternalDepthScale::kMetric;
  EXPECT_EQ(ExternalDepth(opts, maps).scale(), DepthScale::kMetric);
}

TEST_F(ExternalDepthTest, NoKeyframeImageIsAnError) {
  MemoryMaps maps;
  maps.t_ns = {0};
  maps.maps = {plane_map(kWidth, kHeight, 0.0F)};
  ExternalDepth backend(ExternalDepthOptions{}, maps);
  DepthRequest req = request(0);
  req.gray = nullptr;
  DepthResult out = result();
  EXPECT_FALSE(backend.infer(req, out).is_ok());
  EXPECT_FALSE(out.input_missing);
}

}  // namespace
}  // namespace mer::depth
