#include "features/fast_detector.h"

#include <algorithm>
#include <cstdlib>
#include <cstring>

#include "core/assert.h"

namespace mer::features {
namespace {
// Bresenham circle of radius 3, clockwise from 12 o'clock.
constexpr int kCircleX[16] = {0, 1, 2, 3, 3, 3, 2, 1, 0, -1, -2, -3, -3, -3, -2, -1};
constexpr int kCircleY[16] = {-3, -3, -2, -1, 0, 1, 2, 3, 3, 3, 2, 1, 0, -1, -2, -3};
constexpr int kBorder = 3;     // circle radius: no test closer to the edge
constexpr int kArcLength = 9;  // FAST-9

// True when the 16-bit circular mask has a run of at least kArcLength set bits.
inline bool has_arc(std::uint32_t mask) {
  std::uint32_t m = mask | (mask << 16U);
  std::uint32_t run = m;
  for (int i = 1; i < kArcLength; ++i) run &= m >> static_cast<unsigned>(i);
  return run != 0U;
}
}  // namespace

FastDetector::FastDetector(const FastOptions& opts, int width, int height)
    : opts_(opts), width_(width), height_(height) {
  MER_ASSERT(width > 2 * kBorder && height > 2 * kBorder, "image too small for FAST");
  score_.assign(static_cast<std::size_t>(width) * static_cast<std::size_t>(height), 0);
  candidates_.reserve(static_cast<std::size_t>(opts.max_candidates));
  kept_.reserve(static_cast<std::size_t>(opts.max_corners));
}

std::span<const Corner> FastDetector::detect(const cv::Mat& gray) {
  MER_ASSERT(gray.type() == CV_8UC1 && gray.cols == width_ && gray.rows == height_,
             "FastDetector::detect: image type or size differs from construction");
  const int t = opts_.threshold;
  const auto stride = static_cast<int>(gray.step[0]);
  int off[16];
  for (int i = 0; i < 16; ++i) off[i] = kCircleY[i] * stride + kCircleX[i];

  std::fill(score_.begin(), score_.end(), 0);
  // Segment test; the score image holds the corner strength of every passing pixel.
  for (int y = kBorder; y < height_ - kBorder; ++y) {
    const std::uint8_t* row = gray.ptr<std::uint8_t>(y);
    std::int32_t* srow = score_.data() + static_cast<std::ptrdiff_t>(y) * width_;
    for (int x = kBorder; x < width_ - kBorder; ++x) {
      const std::uint8_t* p = row + x;
      const int c = p[0];
      const int hi = c + t;
      const int lo = c - t;
      // Quick rejection on the four compass points: a 9-arc covers at least two of them.
      const int n0 = p[off[0]], n4 = p[off[4]], n8 = p[off[8]], n12 = p[off[12]];
      const int bright4 = (n0 > hi) + (n4 > hi) + (n8 > hi) + (n12 > hi);
      const int dark4 = (n0 < lo) + (n4 < lo) + (n8 < lo) + (n12 < lo);
      if (bright4 < 2 && dark4 < 2) continue;
      std::uint32_t bright = 0;
      std::uint32_t dark = 0;
      int sb = 0;
      int sd = 0;
      for (int i = 0; i < 16; ++i) {
        const int v = p[off[i]];
        if (v > hi) {
          bright |= 1U << static_cast<unsigned>(i);
          sb += v - hi;
        } else if (v < lo) {
          dark |= 1U << static_cast<unsigned>(i);
          sd += lo - v;
        }
      }
      if (has_arc(bright)) {
        srow[x] = sb;
      } else if (has_arc(dark)) {
        srow[x] = sd;
      }
    }
  }

  // 3x3 non-maximum suppression (ties broken towards the earlier pixel) and bucketing.
  candidates_.clear();
  dropped_ = 0;
  const int cell_w = (width_ + opts_.grid_cols - 1) / opts_.grid_cols;
  const int cell_h = (height_ + opts_.grid_rows - 1) / opts_.grid_rows;
  for (int y = kBorder; y < height_ - kBorder; ++y) {
    const std::int32_t* s = score_.data() + static_cast<std::ptrdiff_t>(y) * width_;
    for (int x = kBorder; x < width_ - kBorder; ++x) {
      const std::int32_t v = s[x];
      if (v == 0) continue;
      const std::int32_t* up = s - width_;
      const std::int32_t* dn = s + width_;
      if (v < s[x + 1] || v <= s[x - 1] || v <= up[x - 1] || v <= up[x] || v <= up[x + 1] ||
          v < dn[x - 1] || v < dn[x] || v < dn[x + 1]) {
        continue;
      }
      if (candidates_.size() == candidates_.capacity()) {
        ++dropped_;
        continue;
      }
      candidates_.push_back(Corner{static_cast<std::int16_t>(x), static_cast<std::int16_t>(y), v,
                                   (y / cell_h) * opts_.grid_cols + (x / cell_w)});
    }
  }
  std::sort(candidates_.begin(), candidates_.end(), [](const Corner& a, const Corner& b) {
    if (a.cell != b.cell) return a.cell < b.cell;
    if (a.score != b.score) return a.score > b.score;
    if (a.y != b.y) return a.y < b.y;
    return a.x < b.x;
  });
  // Keep up to an equal share per cell.
  const int cells = opts_.grid_cols * opts_.grid_rows;
  const int per_cell = std::max(1, opts_.max_corners / cells);
  kept_.clear();
  int run_cell = -1;
  int in_cell = 0;
  for (const Corner& c : candidates_) {
    if (c.cell != run_cell) {
      run_cell = c.cell;
      in_cell = 0;
    }
    if (in_cell < per_cell && kept_.size() < kept_.capacity()) {
      kept_.push_back(c);
      ++in_cell;
    }
  }
  return {kept_.data(), kept_.size()};
}

}  // namespace mer::features
