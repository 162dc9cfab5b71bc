#include "features/fast_detector.h"

#include <gtest/gtest.h>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include "platform/alloc_counter.h"

namespace mer::features {
namespace {

// Bright squares on a dark background: each square has four corners.
cv::Mat squares_image(int w, int h, std::vector<cv::Point>& corners) {
  cv::Mat img(h, w, CV_8UC1, cv::Scalar(30));
  for (int y = 40; y + 30 < h; y += 60) {
    for (int x = 40; x + 30 < w; x += 60) {
      cv::rectangle(img, cv::Rect(x, y, 30, 30), cv::Scalar(220), cv::FILLED);
      corners.push_back({x, y});
      corners.push_back({x + 29, y});
      corners.push_back({x, y + 29});
      corners.push_back({x + 29, y + 29});
    }
  }
  return img;
}

TEST(FastDetector, FindsEverySquareCornerAndNothingElse) {
  std::vector<cv::Point> truth;
  const cv::Mat img = squares_image(320, 240, truth);
  FastOptions o;
  o.max_corners = 1000;
  FastDetector det(o, img.cols, img.rows);
  const auto corners = det.detect(img);
  int matched = 0;
  for (const auto& t : truth) {
    for (const auto& c : corners) {
      if (std::abs(c.x - t.x) <= 2 && std::abs(c.y - t.y) <= 2) {
        ++matched;
        break;
      }
    }
  }
  EXPECT_EQ(matched, static_cast<int>(truth.size()));
  for (const auto& c : corners) {
    bool near = false;
    for (const auto& t : truth) near |= std::abs(c.x - t.x) <= 3 && std::abs(c.y - t.y) <= 3;
    EXPECT_TRUE(near) << "spurious corner at " << c.x << "," << c.y;
  }
}

TEST(FastDetector, FlatImageHasNoCorners) {
  cv::Mat img(100, 100, CV_8UC1, cv::Scalar(128));
  FastDetector det(FastOptions{}, 100, 100);
  EXPECT_TRUE(det.detect(img).empty());
}

TEST(FastDetector, BucketingCapsCornersPerCell) {
  std::vector<cv::Point> truth;
  const cv::Mat img = squares_image(320, 240, truth);
  FastOptions o;
  o.grid_cols = 1;
  o.grid_rows = 1;
  o.max_corners = 5;
  FastDetector det(o, img.cols, img.rows);
  const auto corners = det.detect(img);
  ASSERT_EQ(corners.size(), 5U);
  for (std::size_t i = 1; i < corners.size(); ++i)
    EXPECT_GE(corners[i - 1].score, corners[i].score);
}

TEST(FastDetector, DetectDoesNotAllocate) {
  std::vector<cv::Point> truth;
  const cv::Mat img = squares_image(320, 240, truth);
  FastDetector det(FastOptions{}, img.cols, img.rows);
  (void)det.detect(img);
  const auto before = platform::alloc::thread_allocations();
  for (int i = 0; i < 3; ++i) (void)det.detect(img);
  EXPECT_EQ(platform::alloc::thread_allocations() - before, 0U);
}

}  // namespace
}  // namespace mer::features
