#pragma once
/// @file fast_detector.h
/// FAST-9 corner detector (Rosten & Drummond, 2006) with 3x3 non-maximum suppression and
/// grid bucketing, written to run without heap allocation after construction: every
/// buffer is sized for the image at construction. (cv::FAST allocates per call, which the
/// tracking thread must not do.)
///
/// A pixel p is a corner when 9 contiguous pixels of the 16-pixel Bresenham circle of
/// radius 3 are all brighter than I(p) + t or all darker than I(p) - t. Score = sum over
/// the circle of max(0, |I(x) - I(p)| - t), used for suppression and bucketing.

#include <algorithm>
#include <cstdint>
#include <span>
#include <vector>

#include <opencv2/core/mat.hpp>

#include "core/options.h"

namespace mer::features {

/// Options of the corner detector (config section `tracking.fast`).
struct FastOptions {
  int threshold = 20;
  int max_corners = 1000;
  int grid_cols = 8;
  int grid_rows = 6;
  int max_candidates = 20000;

  template <class V>
  void visit(V& v) {
    v.field("threshold", threshold, "FAST intensity threshold, grey levels",
            options::Range<int>{1, 254});
    v.field("max_corners", max_corners, "corners kept after grid bucketing",
            options::Range<int>{1, 100000});
    v.field("grid_cols", grid_cols, "bucketing grid columns", options::Range<int>{1, 64});
    v.field("grid_rows", grid_rows, "bucketing grid rows", options::Range<int>{1, 64});
    v.field("max_candidates", max_candidates, "corner candidates kept before bucketing",
            options::Range<int>{1, 1000000});
  }
};

/// Low-level FAST-9 kernel shared by FastDetector and the ORB extractor (orb_extractor.cpp).
///
/// Tests the pixels x in [x0, x1) of one image row at threshold `threshold` (1..254).
/// `row` points at pixel (0, y) of an 8-bit image with row pitch `stride` bytes; rows
/// y-3..y+3 and columns x0-3..x1+2 must exist. For every corner found, its score (> 0, see
/// the file comment) is written to `score_row[x]` and x is appended to `xs` (room for
/// x1 - x0 entries); other entries of `score_row` are not touched. Returns the number of
/// corners. No allocation.
///
/// Speed: 16 pixels at a time in portable 8-bit code that the compiler vectorizes (SSE2,
/// NEON): a pre-test on the two compass pairs (a 9-arc holds one pixel of every opposite
/// pair of the circle) rejects most blocks, then the full segment test of the block
/// (runs of 9 by doubling: 2, 4, 8, 8 + 1), then the score of each corner. About as fast
/// as cv::FAST without suppression on a 640x480 frame.
int fast_row(const std::uint8_t* row, std::ptrdiff_t stride, int x0, int x1, int threshold,
             std::uint16_t* score_row, std::int32_t* xs);

/// True when pixel x of `score_row` (score of row y; `up`/`down` are rows y-1 and y+1)
/// survives FAST's 3x3 non-maximum suppression. Ties go to the earlier pixel in raster
/// order, so of two equal neighbours exactly one survives.
inline bool fast_is_local_max(const std::uint16_t* up, const std::uint16_t* score_row,
                              const std::uint16_t* down, int x) {
  const int v = score_row[x];
  return v >= score_row[x + 1] && v > score_row[x - 1] && v > up[x - 1] && v > up[x] &&
         v > up[x + 1] && v >= down[x - 1] && v >= down[x] && v >= down[x + 1];
}

/// Sub-pixel offset of a score peak along one axis: the vertex of the parabola through the
/// scores before (`before`), at (`at`) and after (`after`) a local maximum, in pixels of its
/// level, clamped to [-0.5, 0.5] (the maximum is the pixel nearest to the peak); 0 when the
/// three do not bend down. A neighbour below the FAST threshold counts with score 0. The FAST
/// score moves with the image, so its peak follows a corner between pixels (a quadratic fit
/// of FAST scores, as BRISK does across scales) and is repeatable from view to view where the
/// integer maximum jumps by up to half a pixel.
inline float score_peak_offset(float before, float at, float after) {
  const float bend = before - 2.0F * at + after;
  if (!(bend < 0.0F)) return 0.0F;
  return std::clamp(0.5F * (before - after) / bend, -0.5F, 0.5F);
}

/// A detected corner.
struct Corner {
  std::int16_t x = 0;      ///< column, px
  std::int16_t y = 0;      ///< row, px
  std::int32_t score = 0;  ///< FAST score (higher is stronger)
  std::int32_t cell = 0;   ///< bucketing cell index (row-major)
};

/// Allocation-free FAST-9 detector for images of one fixed size.
class FastDetector {
 public:
  /// Allocates buffers for `width` x `height` images.
  FastDetector(const FastOptions& opts, int width, int height);

  /// Detects corners in `gray` (CV_8UC1 of the constructed size). The returned span
  /// points into the detector's buffer and is valid until the next call. Sorted by cell,
  /// then by decreasing score, then by position (deterministic).
  std::span<const Corner> detect(const cv::Mat& gray);

  /// Candidates dropped in the last call because max_candidates was reached.
  std::uint64_t candidates_dropped() const { return dropped_; }

 private:
  FastOptions opts_;
  int width_;
  int height_;
  std::vector<std::uint16_t> score_;  // per pixel, 0 = not a corner
  std::vector<std::int32_t> xs_;      // fast_row output, one row
  std::vector<Corner> candidates_;    // capacity max_candidates
  std::vector<Corner> kept_;          // capacity max_corners
  std::uint64_t dropped_ = 0;
};

}  // namespace mer::features
