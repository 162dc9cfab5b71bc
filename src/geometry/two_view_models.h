#pragma once
/// @file two_view_models.h
/// Building blocks of the two-view reconstruction (internal to mer_geometry; two_view.h is
/// the interface): the RANSAC fit of the homography and the fundamental matrix with their
/// truncated scores, and the plane-and-parallax fundamental matrix of a dominant plane, each
/// working in buffers reserved once (TwoViewWorkspace).

#include <cstddef>
#include <cstdint>
#include <span>
#include <vector>

#include <Eigen/Core>

#include "core/chi2.h"
#include "geometry/two_view.h"

namespace mer::geometry::two_view_detail {

/// Transfer and epipolar residuals carry the keypoint noise of both images: their variance is
/// about twice the keypoint variance sigma^2.
constexpr double kResidualVarianceFactor = 2.0;
/// Correspondences per RANSAC sample (8-point F); the homography uses the first four.
constexpr int kSampleSize = 8;
constexpr int kHomographySampleSize = 4;

/// ORB-SLAM-style truncated score of F: for each correspondence and each image, the squared
/// distance to the epipolar line over the residual variance (chi2, 1 dof) must pass the 95 %
/// gate; passing ones add an offset minus chi2. Gives up (returns -1, mask incomplete) as soon
/// as `to_beat` is out of reach. `inliers` must hold uv0.size() entries.
double score_fundamental(const Eigen::Matrix3d& F, std::span<const Eigen::Vector2d> uv0,
                         std::span<const Eigen::Vector2d> uv1, double inv_var, double to_beat,
                         std::vector<std::uint8_t>& inliers, int& count);

/// Buffers of fit_models (capacity: the correspondences).
struct FitScratch {
  std::vector<Eigen::Vector2d> p0;
  std::vector<Eigen::Vector2d> p1;
  std::vector<std::uint8_t> mask;
  void reserve(std::size_t n, TwoViewModelFit& fit) {
    p0.reserve(n);
    p1.reserve(n);
    mask.reserve(n);
    fit.inliers_h.reserve(n);
    fit.inliers_f.reserve(n);
  }
};

/// fit_two_view_models into `fit` (every field overwritten) with the buffers of `s`.
void fit_models(std::span<const Eigen::Vector2d> uv0, std::span<const Eigen::Vector2d> uv1,
                int iterations, double sigma_px, std::uint64_t seed, FitScratch& s,
                TwoViewModelFit& fit);

/// Plane and parallax (the idea behind DEGENSAC): when nearly all points lie on the plane of
/// H, an 8-point F drawn mostly from the plane is ill-conditioned, but F = [e1]x H is pinned
/// down by the points off the plane: each one's parallax line x1 x (H x0) passes through the
/// epipole e1 of image 1. RANSAC over pairs of such lines, each epipole scored with F's
/// truncated score over all correspondences, then a least-squares epipole over the inlier
/// lines (plane_and_parallax_fundamental).
struct PlaneParallaxFit {
  Eigen::Matrix3d F = Eigen::Matrix3d::Zero();
  std::vector<std::uint8_t> inliers;
  int num_inliers = 0;
  int num_off_plane_inliers = 0;
};

/// Buffers of plane_and_parallax_fundamental (capacity: the correspondences).
struct ParallaxScratch {
  std::vector<std::size_t> off;
  std::vector<Eigen::Vector3d> lines;  // unit-normal parallax lines of the off-plane points
  std::vector<std::uint8_t> mask;
  void reserve(std::size_t n, PlaneParallaxFit& fit) {
    off.reserve(n);
    lines.reserve(n);
    mask.reserve(n);
    fit.inliers.reserve(n);
  }
};

/// The plane-and-parallax F of homography H (PlaneParallaxFit) into `out`, with the buffers
/// of `s`. False when fewer than 40 points lie off the plane or agree on the epipole.
bool plane_and_parallax_fundamental(const Eigen::Matrix3d& H, std::span<const Eigen::Vector2d> uv0,
                                    std::span<const Eigen::Vector2d> uv1, double sigma_px,
                                    int iterations, std::uint64_t seed, ParallaxScratch& s,
                                    PlaneParallaxFit& out);

}  // namespace mer::geometry::two_view_detail
