#pragma once
/// @file self_calibration.h
/// Focal length from two views of a general (non-planar) scene with a known principal point,
/// for `focal: auto` start-up when the calibration guess may be ~30 % off.
///
/// With K = [f 0 cx; 0 f cy; 0 0 1], E(f) = K^T F K is an essential matrix (two equal
/// singular values, one zero) only for the true f. Mendonca & Cipolla (CVPR 1999) minimize
/// the relative gap (s1 - s2) / s2 of E's two largest singular values over f.
///
/// The uncertainty of f is measured by refitting F (least-squares 8-point) on bootstrap
/// resamples of the RANSAC inliers: the estimate is accepted only if the RMS spread of the
/// resulting minimizers is <= 0.6 % of f.
///
/// Not observable (refused):
/// - pure rotation and dominant planes: F is not unique (any F = [e]x H fits), so E(f) is
///   meaningless (detected: a homography has >= 80 % of F's inliers);
/// - pure translation: E(f) = K^T [e]x K is a valid essential matrix for every f (flat cost,
///   minimum on the border of the range);
/// - optical axes meeting at a point equidistant from both centres (orbiting an object):
///   Sturm's degeneracy for a constant focal length; near it, and for small rotations (< ~10
///   deg), f is weakly determined (bootstrap spread too large).

#include <cstdint>
#include <span>

#include <Eigen/Core>

namespace mer::geometry {

/// Result of estimate_focal_two_view.
struct FocalEstimate {
  bool ok = false;      ///< false: refused (see the function comment); other fields informative
  double focal = 0;     ///< estimated f = fx = fy, px
  int num_inliers = 0;  ///< inliers of the robust fundamental matrix
  double cost = 0;      ///< (s1 - s2) / s2 of K^T F K at `focal` (0 for a perfect fit)
  double relative_sigma = 0;  ///< bootstrap RMS spread of the estimate / focal (uncertainty)
};

/// Robust fundamental matrix on pixel coords (RANSAC, 8-point, Hartley normalization, refit
/// on the inliers), then the focal f (fx = fy = f, principal point (cx, cy) known) that makes
/// E = K^T F K closest to a valid essential matrix (Mendonca-Cipolla cost), searched over
/// [f_guess / 2, 2 f_guess] (log-spaced scan + golden-section refinement). Refuses
/// (ok = false) when: fewer than 50 matches / F inliers; a homography explains >= 80 % of F's
/// inliers (pure rotation or a dominant plane: F ill-conditioned); the minimum is on the
/// border of the search range (true f outside it, or pure translation); or the bootstrap
/// spread of f exceeds 0.6 % (focal not observable enough for this motion). Assumes ~1 px
/// keypoint noise. Deterministic for a given seed; allocates; ~4 ms CPU for 1000 matches.
FocalEstimate estimate_focal_two_view(std::span<const Eigen::Vector2d> uv0,
                                      std::span<const Eigen::Vector2d> uv1, double cx, double cy,
                                      double f_guess, std::uint64_t seed = 1);

/// Combines several pairwise estimates robustly (median; non-finite and non-positive values
/// are ignored; 0 when none is left). Helper for the caller.
double median_focal(std::span<const double> estimates);

}  // namespace mer::geometry
