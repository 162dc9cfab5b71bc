// geometry::sample_depth: bilinear depth at sub-pixel positions, refused outside the image,
// where a pixel has no depth and across a depth edge.
#include "geometry/depth_sampling.h"

#include <cmath>
#include <limits>
#include <vector>

#include <gtest/gtest.h>

namespace mer::geometry {
namespace {

constexpr int kWidth = 8;
constexpr int kHeight = 6;
constexpr double kNoEdge = 1e9;  // max_step that never refuses

/// A depth map z = 2 + 0.01 u + 0.02 v (a tilted plane: bilinear is exact on it).
std::vector<float> plane() {
  std::vector<float> d(static_cast<std::size_t>(kWidth * kHeight));
  for (int v = 0; v < kHeight; ++v) {
    for (int u = 0; u < kWidth; ++u) {
      d[static_cast<std::size_t>(v * kWidth + u)] = 2.0F + 0.01F * u + 0.02F * v;
    }
  }
  return d;
}

DepthImageView view_of(const std::vector<float>& d) {
  return {d.data(), kWidth, kHeight, static_cast<std::size_t>(kWidth)};
}

TEST(DepthSampling, BilinearIsExactOnAPlane) {
  const auto d = plane();
  for (const auto& [x, y] : {std::pair{0.0F, 0.0F}, {3.25F, 2.5F}, {6.9F, 4.99F}, {1.0F, 4.0F}}) {
    EXPECT_NEAR(sample_depth(view_of(d), x, y, kNoEdge), 2.0F + 0.01F * x + 0.02F * y, 1e-5F)
        << x << "," << y;
  }
}

TEST(DepthSampling, OutsideTheImageOrNoMapGivesNoDepth) {
  const auto d = plane();
  EXPECT_EQ(sample_depth(view_of(d), -0.5F, 2.0F, kNoEdge), 0.0F);
  EXPECT_EQ(sample_depth(view_of(d), 2.0F, -0.1F, kNoEdge), 0.0F);
  EXPECT_EQ(sample_depth(view_of(d), kWidth - 1.0F, 2.0F, kNoEdge), 0.0F);  // no right neighbour
  EXPECT_EQ(sample_depth(view_of(d), 2.0F, kHeight - 0.5F, kNoEdge), 0.0F);
  EXPECT_EQ(sample_depth(view_of(d), std::numeric_limits<float>::quiet_NaN(), 2.0F, kNoEdge), 0.0F);
  EXPECT_EQ(sample_depth(DepthImageView{}, 2.0F, 2.0F, kNoEdge), 0.0F);
}

TEST(DepthSampling, AMissingOrInvalidPixelAmongTheFourGivesNoDepth) {
  for (const float bad : {0.0F, -1.0F, std::numeric_limits<float>::quiet_NaN(),
                          std::numeric_limits<float>::infinity()}) {
    auto d = plane();
    d[static_cast<std::size_t>(3 * kWidth + 4)] = bad;  // pixel (4, 3)
    EXPECT_EQ(sample_depth(view_of(d), 3.5F, 2.5F, kNoEdge), 0.0F) << bad;
    EXPECT_GT(sample_depth(view_of(d), 1.5F, 1.5F, kNoEdge), 0.0F) << "far from it: " << bad;
  }
}

TEST(DepthSampling, ADepthEdgeIsRefusedASmoothSlopeIsNot) {
  auto d = plane();
  for (int v = 0; v < kHeight; ++v) {
    for (int u = 4; u < kWidth; ++u) d[static_cast<std::size_t>(v * kWidth + u)] += 1.0F;
  }
  EXPECT_EQ(sample_depth(view_of(d), 3.5F, 2.0F, 0.03), 0.0F) << "straddles the 1 m step";
  EXPECT_GT(sample_depth(view_of(d), 1.5F, 2.0F, 0.03), 0.0F) << "0.5 % slope only";
  EXPECT_GT(sample_depth(view_of(d), 3.5F, 2.0F, 1.0), 0.0F) << "a looser bound accepts it";
}

TEST(DepthSampling, HonoursTheRowStride) {
  // The plane inside a wider buffer (a sub-image): the stride, not the width, steps rows.
  constexpr int kStride = kWidth + 3;
  const auto p = plane();
  std::vector<float> d(static_cast<std::size_t>(kStride * kHeight), -1.0F);
  for (int v = 0; v < kHeight; ++v) {
    for (int u = 0; u < kWidth; ++u) {
      d[static_cast<std::size_t>(v * kStride + u)] = p[static_cast<std::size_t>(v * kWidth + u)];
    }
  }
  const DepthImageView view{d.data(), kWidth, kHeight, static_cast<std::size_t>(kStride)};
  EXPECT_NEAR(sample_depth(view, 5.5F, 3.5F, kNoEdge), 2.0F + 0.055F + 0.07F, 1e-5F);
}

}  // namespace
}  // namespace mer::geometry
