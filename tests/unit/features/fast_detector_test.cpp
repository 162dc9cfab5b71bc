#include "features/fast_detector.h"

#include <algorithm>
#include <utility>
#include <vector>

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

// Straightforward FAST-9 (segment test + score) of one pixel, the reference for fast_row.
int reference_score(const cv::Mat& img, int x, int y, int t) {
  static const int kDx[16] = {0, 1, 2, 3, 3, 3, 2, 1, 0, -1, -2, -3, -3, -3, -2, -1};
  static const int kDy[16] = {-3, -3, -2, -1, 0, 1, 2, 3, 3, 3, 2, 1, 0, -1, -2, -3};
  const int c = img.at<std::uint8_t>(y, x);
  for (int sign : {1, -1}) {
    int best_run = 0;
    int run = 0;
    for (int i = 0; i < 32; ++i) {  // twice around the circle for wrapping runs
      const int v = img.at<std::uint8_t>(y + kDy[i % 16], x + kDx[i % 16]);
      run = sign * (v - c) > t ? run + 1 : 0;
      best_run = std::max(best_run, std::min(run, 16));
    }
    if (best_run >= 9) {
      int score = 0;
      for (int i = 0; i < 16; ++i) {
        const int v = img.at<std::uint8_t>(y + kDy[i], x + kDx[i]);
        score += std::max(0, sign * (v - c) - t);
      }
      return score;
    }
  }
  return 0;
}

TEST(FastRow, MatchesTheReferenceOnEveryPixel) {
  // Noise (many corners of both polarities, values near 0 and 255 for the saturating
  // arithmetic) and squares; full rows (16-pixel blocks plus a shifted last block) and
  // short ranges (scalar path).
  cv::Mat noise(64, 203, CV_8UC1);
  cv::RNG rng(5);
  rng.fill(noise, cv::RNG::UNIFORM, 0, 256);
  std::vector<cv::Point> unused;
  const cv::Mat squares = squares_image(203, 64, unused);
  std::vector<std::uint16_t> score_row(203, 0);
  std::vector<std::int32_t> xs(203);
  int corners = 0;
  for (const cv::Mat* img : {static_cast<const cv::Mat*>(&noise), &squares}) {
    for (int t : {1, 7, 20, 60, 254}) {
      for (auto [x0, x1] : {std::pair{3, 200}, std::pair{3, 19}, std::pair{40, 45},
                            std::pair{10, 26}, std::pair{150, 151}}) {
        for (int y = 3; y < img->rows - 3; ++y) {
          const int n =
              fast_row(img->ptr<std::uint8_t>(y), static_cast<std::ptrdiff_t>(img->step[0]), x0, x1,
                       t, score_row.data(), xs.data());
          int k = 0;
          for (int x = x0; x < x1; ++x) {
            const int ref = reference_score(*img, x, y, t);
            if (ref == 0) continue;
            ASSERT_LT(k, n) << "missed corner at " << x << "," << y << " t=" << t;
            ASSERT_EQ(xs[static_cast<std::size_t>(k)], x) << "y=" << y << " t=" << t;
            ASSERT_EQ(score_row[static_cast<std::size_t>(x)], ref) << x << "," << y;
            score_row[static_cast<std::size_t>(x)] = 0;
            ++k;
          }
          ASSERT_EQ(k, n) << "spurious corners in row " << y << " t=" << t;
          corners += n;
          for (std::uint16_t s : score_row) ASSERT_EQ(s, 0) << "score written outside corners";
        }
      }
    }
  }
  EXPECT_GT(corners, 1000);
}

}  // namespace
}  // namespace mer::features
