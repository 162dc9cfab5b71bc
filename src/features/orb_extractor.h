#pragma once
/// @file orb_extractor.h
/// The `orb` backend: this project's ORB (Rublee et al., 2011), allocation-free per frame.
///
/// Per frame:
/// 1. Pyramid: level l has size round(W / s^l) x round(H / s^l) and is resized bilinearly
///    (fixed point, pixel centres aligned) from level l-1 into preallocated buffers; level
///    0 is the input itself. (cv::resize and cv::GaussianBlur allocate on every call even
///    into a preallocated destination - measured with the allocation counter: 2-4 and 8-9
///    allocations - and may use OpenCV's thread pool, hence our own resize and smoothing.)
/// 2. Detection: FAST-9 (fast_detector.h) with 3x3 non-maximum suppression in the region
///    `edge_threshold` px inside each level; a grid (grid_cols x grid_rows at level 0, fewer
///    cells at coarser levels) over that region, and in every cell where nothing was found,
///    a retry with `min_fast_threshold`. With `subpixel`, each corner moves to the peak of a
///    parabola through its FAST score and its row / column neighbours' (score_peak_offset).
/// 3. Selection: level l gets about N (1 - 1/s) / (1 - 1/s^L) / s^l of the N features (more
///    at fine levels, as in ORB-SLAM); a level with too few corners passes its share to the
///    others. Inside a level, every grid cell gives its strongest corner (FAST score; when
///    the share is smaller than the number of non-empty cells, none is guaranteed), and
///    the rest of the level's share goes to the level's strongest corners with at most
///    twice the average per cell taken from any one cell (raised when too few cells have
///    corners to fill the share). Strict equal shares per cell were measured ~10 points
///    worse in the rotation match rate (weak corners picked in busy cells do not repeat).
/// 4. Orientation: intensity centroid over a radius-15 disc on the level image.
/// 5. Descriptor: 256 binary intensity tests on the level image smoothed by a separable
///    7-tap kernel (1 2 3 4 3 2 1)/16, computed per level right before its descriptors.
///    The point pairs are drawn once, deterministically (fixed seed), from an isotropic
///    Gaussian of sigma 31/5 px restricted to the radius-15 disc inscribed in the 31x31
///    patch, and precomputed rotated for kAngleBins angles.
///
/// Output order: by level, then raster order (y, then x) inside a level. Deterministic for
/// a given image (integer arithmetic except the orientation's atan2). Uses no OpenCV
/// function (so no OpenCV thread pool) in extract(), and no heap allocation after
/// construction. Portable C++ (no intrinsics); the hot loops are written so that GCC/Clang
/// vectorize them at -O3 (Release) with the baseline SSE2 / NEON instruction sets.

#include <array>
#include <cstdint>
#include <span>
#include <vector>

#include "features/extractor.h"

namespace mer::features {

/// The allocation-free ORB extractor. Not thread-safe; one instance per thread.
class OrbExtractor final : public Extractor {
 public:
  /// Rotated copies of the test pattern: one per 2 pi / kAngleBins of keypoint angle.
  static constexpr int kAngleBins = 64;
  /// Binary tests per descriptor (= bits of Descriptor).
  static constexpr int kDescriptorBits = 256;
  /// Radius of the orientation disc and of the test pattern, px (the disc inscribed in
  /// ORB's 31x31 patch).
  static constexpr int kPatchRadius = 15;
  /// Orientation rows are processed kDiscRowWidth pixels wide (u = -15 .. 16, the last one
  /// with weight 0): a whole number of vectors.
  static constexpr int kDiscRowWidth = 32;

  /// Allocates every buffer for `width` x `height` images. `opts` must be valid
  /// (validate_extractor_options); make_extractor() checks before constructing.
  OrbExtractor(const ExtractorOptions& opts, int width, int height);

  int extract(const cv::Mat& gray) override;
  std::span<const Keypoint> keypoints() const override { return {keypoints_.data(), count_}; }
  std::span<const Descriptor> descriptors() const override { return {descriptors_.data(), count_}; }
  const char* name() const override { return "orb"; }
  float level_scale(int level) const override;
  float level_sigma2(int level) const override;
  int num_levels() const override { return static_cast<int>(levels_.size()); }

  /// Width and height of pyramid level `level`, px.
  int level_width(int level) const;
  int level_height(int level) const;

  /// The test pattern at angle 0: kDescriptorBits pairs of (x, y) offsets, px, as
  /// x1, y1, x2, y2 for each test (for tests and documentation).
  std::span<const std::int8_t> test_pattern() const { return pattern_; }

 private:
  // A corner found at one level, level pixel coordinates.
  struct Candidate {
    std::int16_t x = 0;
    std::int16_t y = 0;
    std::uint16_t score = 0;
    std::uint16_t cell = 0;
    float dx = 0.0F;  ///< sub-pixel offset of the score peak (subpixel), level px
    float dy = 0.0F;
  };
  struct Level {
    int width = 0;
    int height = 0;
    float scale = 1.0F;    // scale_factor^level
    float to_x0 = 1.0F;    // level-0 px per level px, horizontally (W / width)
    float to_y0 = 1.0F;    // same, vertically
    std::size_t raw = 0;   // offset of the level in raw_ (levels >= 1), bytes
    std::size_t blur = 0;  // offset of the level in blurred_, bytes
    int x0 = 0;            // detection region [x0, x1) x [y0, y1)
    int y0 = 0;
    int x1 = 0;
    int y1 = 0;
    int grid_cols = 1;
    int grid_rows = 1;
    std::size_t cell_begin = 0;  // first entry in cell_count_, cell_start_, cell_x_ ...
    std::size_t col_of_x = 0;    // offset in cell_col_of_x_ (indexed by x - x0)
    std::size_t row_of_y = 0;    // offset in cell_row_of_y_ (indexed by y - y0)
    std::size_t cand_begin = 0;  // first slot in candidates_
    std::size_t cand_capacity = 0;
    std::size_t num_candidates = 0;
    std::size_t xmap = 0;  // offset in resize tables (levels >= 1)
    std::size_t ymap = 0;
    int desired = 0;  // geometric share of num_features
    int quota = 0;    // features taken this frame
  };

  void resize_level(int level, const std::uint8_t* src, std::ptrdiff_t src_stride);
  void detect_level(int level, const std::uint8_t* img, std::ptrdiff_t stride);
  void detect_rect(int level, const std::uint8_t* img, std::ptrdiff_t stride, int rx0, int ry0,
                   int rx1, int ry1, int threshold);
  void assign_quotas();
  void select_level(int level);
  void describe(int level, const std::uint8_t* raw, std::ptrdiff_t raw_stride);
  // Smooths rows [y_begin, y_end) of a width x height level into dst (pitch stride_).
  void blur_level(const std::uint8_t* src, std::ptrdiff_t src_stride, int width, int height,
                  int y_begin, int y_end, std::uint8_t* dst);
  /// Buffer totals of the pyramid (orb_extractor.cpp).
  struct BufferSizes;
  /// Lays out the pyramid's levels (levels_: sizes, regions, grids, buffer offsets, feature
  /// shares) and returns the totals the buffers are sized with.
  BufferSizes plan_levels();
  /// Fills the per-level cell tables and the bilinear resize maps (buffers sized).
  void fill_level_tables();
  /// Fills the orientation disc's rows (disc_mask_, disc_u_).
  void make_disc();
  void make_pattern();

  ExtractorOptions opts_;
  int width_;
  int height_;
  std::vector<Level> levels_;
  std::ptrdiff_t stride_ = 0;              // row pitch of raw_ and blurred_, bytes
  std::vector<std::uint8_t> raw_;          // pyramid levels 1.. (level 0 is the input)
  std::vector<std::uint8_t> blurred_;      // smoothed pyramid levels 0.., for descriptors
  std::vector<std::uint16_t> tmp16_;       // one row of blur / resize intermediate results
  std::vector<std::int32_t> xmap_;         // resize: source column per level column
  std::vector<std::int32_t> xweight_;      // resize: weight of source column + 1 (0..128)
  std::vector<std::int32_t> ymap_;         // resize: source row per level row
  std::vector<std::int32_t> yweight_;      // resize: weight of source row + 1 (0..128)
  std::vector<std::uint16_t> score_rows_;  // 3 rolling rows of FAST scores
  std::vector<std::int32_t> xs_rows_;      // 3 rolling rows of corner columns
  std::vector<Candidate> candidates_;      // per level, raster order (+ retries)
  std::vector<Candidate> sorted_;          // one level's candidates grouped by cell
  std::vector<std::int32_t> cell_count_;   // per level and cell
  std::vector<std::int32_t> cell_start_;   // per level and cell, into sorted_
  std::vector<std::int32_t> cell_rect_;    // per level and cell: x0, y0, x1, y1
  std::vector<std::uint16_t> cell_col_of_x_;
  std::vector<std::uint16_t> cell_row_of_y_;
  std::vector<Candidate> pool_;      // select_level: corners competing level-wide
  std::vector<Candidate> selected_;  // one level's selection (capacity num_features)
  int selected_count_ = 0;
  std::vector<std::int8_t> pattern_;   // kDescriptorBits * 4: x1, y1, x2, y2
  std::vector<std::int32_t> offsets_;  // kAngleBins * kDescriptorBits * 2 byte offsets
  // Orientation disc rows v = 0..15 over u = -15..16: u inside the disc (else 0), and 1/0.
  std::array<std::array<std::int16_t, kDiscRowWidth>, kPatchRadius + 1> disc_u_{};
  std::array<std::array<std::int16_t, kDiscRowWidth>, kPatchRadius + 1> disc_mask_{};
  std::vector<Keypoint> keypoints_;      // capacity num_features
  std::vector<Descriptor> descriptors_;  // capacity num_features
  std::size_t count_ = 0;
};

}  // namespace mer::features
