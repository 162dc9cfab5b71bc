#include "features/patch_align.h"

#include <cmath>

#include <Eigen/Dense>
#include <gtest/gtest.h>
#include <opencv2/core.hpp>

namespace mer::features {
namespace {

// A smooth, aperiodic-looking texture (sum of sinusoids), intensity in [20, 235].
double texture(double x, double y) {
  return 128.0 + 40.0 * std::sin(0.71 * x + 0.33 * y) + 30.0 * std::sin(0.27 * x - 0.93 * y + 1.0) +
         25.0 * std::sin(0.52 * x + 0.61 * y + 2.0) + 12.0 * std::cos(1.13 * x - 0.21 * y);
}

// Image whose pixel (column c, row r) shows the texture at L ((c, r) - at_img) + at_tex: the
// texture point at_tex is seen at at_img, through the affine map L.
cv::Mat render(const Eigen::Matrix2d& L, const Eigen::Vector2d& at_img,
               const Eigen::Vector2d& at_tex, double offset = 0.0) {
  cv::Mat img(120, 160, CV_8UC1);
  for (int r = 0; r < img.rows; ++r) {
    for (int c = 0; c < img.cols; ++c) {
      const Eigen::Vector2d t = L * (Eigen::Vector2d(c, r) - at_img) + at_tex;
      img.at<std::uint8_t>(r, c) = static_cast<std::uint8_t>(
          std::lround(std::clamp(texture(t.x(), t.y()) + offset, 0.0, 255.0)));
    }
  }
  return img;
}

TEST(PatchAlign, RecoversASubPixelShift) {
  const Eigen::Vector2d tex(40.0, 30.0);
  const cv::Mat a = render(Eigen::Matrix2d::Identity(), {60.3, 49.8}, tex);
  // The same surface point sits at (81.37, 62.71) in the second image.
  const Eigen::Vector2d truth(81.37, 62.71);
  const cv::Mat b = render(Eigen::Matrix2d::Identity(), truth, tex, 9.0);
  AnchorPixels anchor{};
  Eigen::Vector2f centre;
  ASSERT_TRUE(sample_anchor_patch(a, 60.3F, 49.8F, anchor, centre));
  WarpedPatch ref{};
  ASSERT_TRUE(warp_anchor_patch(anchor, centre, Eigen::Matrix2f::Identity(), ref));
  Eigen::Vector2f uv(81.0F, 63.0F);  // a detection 0.37 px off
  const AlignResult r = align_patch(b, ref, 20, 0.01F, uv);
  ASSERT_TRUE(r.converged);
  EXPECT_NEAR(uv.x(), truth.x(), 0.05);
  EXPECT_NEAR(uv.y(), truth.y(), 0.05);
  EXPECT_LT(r.rms, 2.0F);  // the brightness offset (9) is absorbed
}

TEST(PatchAlign, WarpingTheAnchorFollowsScaleAndRotation) {
  const Eigen::Vector2d tex(40.0, 30.0);
  const cv::Mat a = render(Eigen::Matrix2d::Identity(), {60.3, 49.8}, tex);
  // Second view: the texture 1.25x larger and rotated by 25 degrees.
  const double th = 25.0 * M_PI / 180.0;
  Eigen::Matrix2d A;  // anchor px offsets -> target px offsets
  A << std::cos(th), -std::sin(th), std::sin(th), std::cos(th);
  A *= 1.25;
  const Eigen::Vector2d truth(90.6, 55.2);
  const cv::Mat b = render(A.inverse(), truth, tex);
  AnchorPixels anchor{};
  Eigen::Vector2f centre;
  ASSERT_TRUE(sample_anchor_patch(a, 60.3F, 49.8F, anchor, centre));
  const Eigen::Vector2f start(91.2F, 54.7F);
  // With the predicted warp the alignment lands on the point.
  WarpedPatch warped{};
  ASSERT_TRUE(warp_anchor_patch(anchor, centre, A.inverse().cast<float>(), warped));
  Eigen::Vector2f uv = start;
  ASSERT_TRUE(align_patch(b, warped, 30, 0.01F, uv).converged);
  EXPECT_NEAR(uv.x(), truth.x(), 0.08);
  EXPECT_NEAR(uv.y(), truth.y(), 0.08);
  // Without it the same alignment misses by more (the patches do not correspond).
  WarpedPatch plain{};
  ASSERT_TRUE(warp_anchor_patch(anchor, centre, Eigen::Matrix2f::Identity(), plain));
  Eigen::Vector2f uv_plain = start;
  const AlignResult rp = align_patch(b, plain, 30, 0.01F, uv_plain);
  const double err_plain = rp.converged ? (uv_plain.cast<double>() - truth).norm() : 1e9;
  EXPECT_GT(err_plain, 3.0 * (uv.cast<double>() - truth).norm());
}

TEST(PatchAlign, RefusesWhatItCannotDo) {
  const cv::Mat a = render(Eigen::Matrix2d::Identity(), {60.0, 50.0}, {0.0, 0.0});
  AnchorPixels anchor{};
  Eigen::Vector2f centre;
  EXPECT_FALSE(sample_anchor_patch(a, 5.0F, 50.0F, anchor, centre));    // leaves the image
  EXPECT_FALSE(sample_anchor_patch(a, 60.0F, 113.0F, anchor, centre));  // leaves the image
  ASSERT_TRUE(sample_anchor_patch(a, 60.3F, 49.8F, anchor, centre));
  WarpedPatch w{};
  EXPECT_FALSE(
      warp_anchor_patch(anchor, centre, 2.0F * Eigen::Matrix2f::Identity(), w));  // too large
  // A flat reference has nothing to align: not converged, uv unchanged.
  WarpedPatch flat{};
  flat.fill(100.0F);
  Eigen::Vector2f uv(80.0F, 60.0F);
  EXPECT_FALSE(align_patch(a, flat, 10, 0.01F, uv).converged);
  EXPECT_EQ(uv, Eigen::Vector2f(80.0F, 60.0F));
  // Near the border the patch leaves the image: unchanged.
  ASSERT_TRUE(warp_anchor_patch(anchor, centre, Eigen::Matrix2f::Identity(), w));
  uv = Eigen::Vector2f(2.0F, 60.0F);
  EXPECT_FALSE(align_patch(a, w, 10, 0.01F, uv).converged);
  EXPECT_EQ(uv, Eigen::Vector2f(2.0F, 60.0F));
}

}  // namespace
}  // namespace mer::features
