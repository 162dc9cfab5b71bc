#pragma once
/// @file patch_align.h
/// View-consistent keypoint positions: a point's appearance is kept as an anchor patch from
/// one view; in another view the anchor is warped by the affine map the two views' geometry
/// predicts and aligned to that view's image (translation and a brightness offset,
/// inverse-compositional Gauss-Newton). Every view then measures the same surface point,
/// where independent detections measure slightly different ones (a corner's position
/// depends on the scale and perspective it is seen at), an error that is correlated across
/// the views of a point and which bundle adjustment cannot average away.
///
/// Coordinates are pixel coordinates of one pyramid level with pixel centres at integers
/// (OpenCV's convention, the one the extractors use). Nothing here allocates.

#include <array>
#include <cstdint>
#include <span>

#include <Eigen/Core>
#include <opencv2/core/mat.hpp>

namespace mer::features {

/// Side of an anchor patch, pixels of its level (room for warps up to ~1.4x scale change).
inline constexpr int kAnchorSide = 16;
/// Side of the aligned patch, pixels of the target level.
inline constexpr int kAlignSide = 8;
/// Side of the warped patch: the aligned patch with a one-pixel border for its gradient.
inline constexpr int kWarpSide = kAlignSide + 2;

using AnchorPixels = std::array<std::uint8_t, kAnchorSide * kAnchorSide>;
using WarpedPatch = std::array<float, kWarpSide * kWarpSide>;

/// Copies the anchor patch around (x, y) of `img` (CV_8UC1): the image's own pixels (no
/// interpolation, which would blur the patch by an amount that depends on the sub-pixel
/// position), pixel (r, c) of the patch being img(round(y) + r - 8, round(x) + c - 8).
/// `centre` receives (x, y) in patch coordinates. False (and `out` unspecified) when the
/// patch does not fit in the image.
bool sample_anchor_patch(const cv::Mat& img, float x, float y, AnchorPixels& out,
                         Eigen::Vector2f& centre);

/// Warps an anchor patch into a target view: pixel (r, c) of `out` is the anchor at
/// `centre` + M (c - 4.5, r - 4.5) (bilinear), M mapping target-level pixel offsets to anchor
/// pixel offsets. False when a sample falls outside the anchor patch.
bool warp_anchor_patch(const AnchorPixels& anchor, const Eigen::Vector2f& centre,
                       const Eigen::Matrix2f& M, WarpedPatch& out);

/// Outcome of align_patch.
struct AlignResult {
  bool converged = false;  ///< the last update was below the tolerance
  int iterations = 0;      ///< Gauss-Newton iterations run
  float rms = 0.0F;        ///< RMS intensity residual at the end (brightness offset removed)
};

/// Moves `uv` (pixels of `img`, CV_8UC1) to where the inner kAlignSide x kAlignSide pixels
/// of `ref` (centred on uv) best match the image: translation and a brightness offset,
/// inverse-compositional Gauss-Newton, at most `max_iterations`, converged when an update
/// is shorter than `tolerance_px`. `uv` is left unchanged when the patch leaves the image
/// or the reference has no texture.
AlignResult align_patch(const cv::Mat& img, const WarpedPatch& ref, int max_iterations,
                        float tolerance_px, Eigen::Vector2f& uv);

}  // namespace mer::features
