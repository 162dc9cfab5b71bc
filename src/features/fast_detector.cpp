#include "features/fast_detector.h"

#include <algorithm>
#include <bit>
#include <cstdlib>
#include <cstring>
#include <utility>

#include "core/assert.h"

namespace mer::features {
namespace {
// Bresenham circle of radius 3, clockwise from 12 o'clock.
constexpr int kCircleX[16] = {0, 1, 2, 3, 3, 3, 2, 1, 0, -1, -2, -3, -3, -3, -2, -1};
constexpr int kCircleY[16] = {-3, -3, -2, -1, 0, 1, 2, 3, 3, 3, 2, 1, 0, -1, -2, -3};
constexpr int kCircleSize = 16;
constexpr int kHalfCircle = kCircleSize / 2;  // index distance of opposite circle pixels
constexpr int kBorder = 3;                    // circle radius: no test closer to the edge
constexpr int kArcLength = 9;                 // FAST-9
constexpr std::uint8_t kMaxByte = 255;
// Pixels pre-tested together: one 16-byte vector. The pre-test writes its verdicts to a
// stack array, which the compiler knows aliases nothing, so its loops vectorize.
constexpr int kBlock = 16;

// 8-bit min / max / saturating arithmetic, written as the value expressions the compiler
// maps to single vector instructions (std::min's reference return gets in the way).
inline std::uint8_t min8(std::uint8_t a, std::uint8_t b) {
  return a < b ? a : b;
}
inline std::uint8_t max8(std::uint8_t a, std::uint8_t b) {
  return a > b ? a : b;
}
inline std::uint8_t sat_sub(std::uint8_t a, std::uint8_t b) {
  return static_cast<std::uint8_t>(max8(a, b) - b);
}

// Pre-test of the kBlock pixels starting at x with the opposite pairs (i, i + 8), i in I:
// a 9-arc of the 16-circle holds one pixel of every opposite pair, so a bright corner
// needs, for every pair, one of the two brighter than c + t, i.e.
//   min over pairs of max(q_i, q_i+8) > c + t,
// and a dark one needs max over pairs of min(q_i, q_i+8) < c - t. 8-bit min/max and
// saturating differences only, pairs unrolled at compile time: one vector per operation.
// Returns true when any of the pixels passes.
template <std::size_t... I>
inline bool pretest(const std::uint8_t* row, const std::uint8_t* const* q, int x, std::uint8_t t,
                    std::index_sequence<I...> /*pairs*/) {
  const std::uint8_t* const c = row + x;
  std::uint8_t out[kBlock];
  for (int k = 0; k < kBlock; ++k) {
    std::uint8_t lowest_max = kMaxByte;
    std::uint8_t highest_min = 0;
    ((lowest_max = min8(lowest_max, max8(q[I][x + k], q[I + kHalfCircle][x + k])),
      highest_min = max8(highest_min, min8(q[I][x + k], q[I + kHalfCircle][x + k]))),
     ...);
    const std::uint8_t excess = max8(sat_sub(lowest_max, c[k]), sat_sub(c[k], highest_min));
    out[k] = static_cast<std::uint8_t>(excess > t);
  }
  std::uint64_t w[2];
  std::memcpy(w, out, sizeof(w));
  return (w[0] | w[1]) != 0U;
}

constexpr std::uint8_t kBrightCorner = 1;  // arc_test verdicts
constexpr std::uint8_t kDarkCorner = 2;

// min(a + b, 255) in 8 bits.
inline std::uint8_t sat_add(std::uint8_t a, std::uint8_t b) {
  return static_cast<std::uint8_t>(min8(a, static_cast<std::uint8_t>(kMaxByte - b)) + b);
}

// Segment test of the kBlock pixels starting at x, all 16 circle pixels unrolled at compile
// time so that the pixel loop vectorizes: per pixel, a byte mask per circle pixel (brighter
// than c + t, darker than c - t), then a run of kArcLength = 9 by doubling (runs of 2, 4, 8,
// then 8 + 1). corner[k] = kBrightCorner or kDarkCorner when pixel x + k is a corner (a
// pixel cannot be both: 9 + 9 > 16), else 0. Returns true when any is.
template <std::size_t... I>
inline bool arc_test(const std::uint8_t* row, const std::uint8_t* const* q, int x, std::uint8_t t,
                     std::uint8_t* corner, std::index_sequence<I...> /*circle*/) {
  constexpr std::size_t kN = sizeof...(I);
  static_assert(kN == kCircleSize && kArcLength == 9, "doubling below assumes FAST-9 on 16");
  std::uint8_t out[kBlock];
  for (int k = 0; k < kBlock; ++k) {
    const std::uint8_t c = row[x + k];
    const std::uint8_t hi = sat_add(c, t);
    const std::uint8_t lo = sat_sub(c, t);
    const std::uint8_t b1[kN] = {static_cast<std::uint8_t>(q[I][x + k] > hi)...};
    const std::uint8_t d1[kN] = {static_cast<std::uint8_t>(q[I][x + k] < lo)...};
    const std::uint8_t b2[kN] = {static_cast<std::uint8_t>(b1[I] & b1[(I + 1) % kN])...};
    const std::uint8_t d2[kN] = {static_cast<std::uint8_t>(d1[I] & d1[(I + 1) % kN])...};
    const std::uint8_t b4[kN] = {static_cast<std::uint8_t>(b2[I] & b2[(I + 2) % kN])...};
    const std::uint8_t d4[kN] = {static_cast<std::uint8_t>(d2[I] & d2[(I + 2) % kN])...};
    const std::uint8_t b8[kN] = {static_cast<std::uint8_t>(b4[I] & b4[(I + 4) % kN])...};
    const std::uint8_t d8[kN] = {static_cast<std::uint8_t>(d4[I] & d4[(I + 4) % kN])...};
    const auto bright = static_cast<std::uint8_t>(((b8[I] & b1[(I + 8) % kN]) | ...));
    const auto dark = static_cast<std::uint8_t>(((d8[I] & d1[(I + 8) % kN]) | ...));
    out[k] = static_cast<std::uint8_t>(bright | (dark << 1U));
  }
  std::uint64_t w[2];
  std::memcpy(w, out, sizeof(w));
  std::memcpy(corner, out, sizeof(out));
  return (w[0] | w[1]) != 0U;
}

// Compass pairs (N-S, E-W): a cheap first filter that rejects most 16-pixel blocks.
using CompassPairs = std::index_sequence<0, kHalfCircle / 2>;
using Circle = std::make_index_sequence<kCircleSize>;

// True when the 16-bit circular mask has a run of at least kArcLength set bits.
inline bool has_arc(std::uint32_t mask) {
  std::uint32_t m = mask | (mask << 16U);
  std::uint32_t run = m;
  for (int i = 1; i < kArcLength; ++i) run &= m >> static_cast<unsigned>(i);
  return run != 0U;
}

// Scalar segment test of pixel x (rows shorter than a block): kBrightCorner, kDarkCorner
// or 0.
inline std::uint8_t segment_test(const std::uint8_t* row, const std::uint8_t* const* q, int x,
                                 int t) {
  const int c = row[x];
  std::uint32_t bright = 0;
  std::uint32_t dark = 0;
  for (int i = 0; i < kCircleSize; ++i) {
    const int v = q[i][x];
    bright |= static_cast<std::uint32_t>(v > c + t) << static_cast<unsigned>(i);
    dark |= static_cast<std::uint32_t>(v < c - t) << static_cast<unsigned>(i);
  }
  if (has_arc(bright)) return kBrightCorner;
  if (has_arc(dark)) return kDarkCorner;
  return 0;
}

// Score of a corner at x (see the file comment): the sum over the circle of how far the
// pixels on the corner's side exceed the threshold.
inline int corner_score(const std::uint8_t* row, const std::uint8_t* const* q, int x, int t,
                        bool bright) {
  const int c = row[x];
  int sum = 0;
  if (bright) {
    const int hi = c + t;
    for (int i = 0; i < kCircleSize; ++i) sum += std::max(q[i][x] - hi, 0);
  } else {
    const int lo = c - t;
    for (int i = 0; i < kCircleSize; ++i) sum += std::max(lo - q[i][x], 0);
  }
  return sum;
}

}  // namespace

int fast_row(const std::uint8_t* row, std::ptrdiff_t stride, int x0, int x1, int threshold,
             std::uint16_t* score_row, std::int32_t* xs) {
  const std::uint8_t* q[kCircleSize];
  for (int i = 0; i < kCircleSize; ++i) q[i] = row + kCircleY[i] * stride + kCircleX[i];
  const auto t8 = static_cast<std::uint8_t>(threshold);
  int found = 0;
  auto keep = [&](int x, std::uint8_t verdict) {
    score_row[x] =
        static_cast<std::uint16_t>(corner_score(row, q, x, threshold, verdict == kBrightCorner));
    xs[found++] = x;
  };
  if (x1 - x0 < kBlock) {  // shorter than a block: scalar
    for (int x = x0; x < x1; ++x) {
      const std::uint8_t v = segment_test(row, q, x, threshold);
      if (v != 0) keep(x, v);
    }
    return found;
  }
  for (int bx = x0; bx < x1; bx += kBlock) {
    // A last partial block is moved back to end at x1; its pixels before `first` were
    // tested by the previous block.
    const int start = std::min(bx, x1 - kBlock);
    const int first = bx - start;
    std::uint8_t verdict[kBlock];
    if (!pretest(row, q, start, t8, CompassPairs{})) continue;
    if (!arc_test(row, q, start, t8, verdict, Circle{})) continue;
    for (int k = first; k < kBlock; ++k) {
      if (verdict[k] != 0) keep(start + k, verdict[k]);
    }
  }
  return found;
}

FastDetector::FastDetector(const FastOptions& opts, int width, int height)
    : opts_(opts), width_(width), height_(height) {
  MER_ASSERT(width > 2 * kBorder && height > 2 * kBorder, "image too small for FAST");
  score_.assign(static_cast<std::size_t>(width) * static_cast<std::size_t>(height), 0);
  xs_.assign(static_cast<std::size_t>(width), 0);
  candidates_.reserve(static_cast<std::size_t>(opts.max_candidates));
  kept_.reserve(static_cast<std::size_t>(opts.max_corners));
}

std::span<const Corner> FastDetector::detect(const cv::Mat& gray) {
  MER_ASSERT(gray.type() == CV_8UC1 && gray.cols == width_ && gray.rows == height_,
             "FastDetector::detect: image type or size differs from construction");
  const auto stride = static_cast<std::ptrdiff_t>(gray.step[0]);

  std::fill(score_.begin(), score_.end(), std::uint16_t{0});
  // Segment test; the score image holds the corner strength of every passing pixel.
  for (int y = kBorder; y < height_ - kBorder; ++y) {
    std::uint16_t* srow = score_.data() + static_cast<std::ptrdiff_t>(y) * width_;
    (void)fast_row(gray.ptr<std::uint8_t>(y), stride, kBorder, width_ - kBorder, opts_.threshold,
                   srow, xs_.data());
  }

  // 3x3 non-maximum suppression (ties broken towards the earlier pixel) and bucketing.
  candidates_.clear();
  dropped_ = 0;
  const int cell_w = (width_ + opts_.grid_cols - 1) / opts_.grid_cols;
  const int cell_h = (height_ + opts_.grid_rows - 1) / opts_.grid_rows;
  for (int y = kBorder; y < height_ - kBorder; ++y) {
    const std::uint16_t* s = score_.data() + static_cast<std::ptrdiff_t>(y) * width_;
    for (int x = kBorder; x < width_ - kBorder; ++x) {
      if (s[x] == 0 || !fast_is_local_max(s - width_, s, s + width_, x)) continue;
      if (candidates_.size() == candidates_.capacity()) {
        ++dropped_;
        continue;
      }
      candidates_.push_back(Corner{static_cast<std::int16_t>(x), static_cast<std::int16_t>(y), s[x],
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
