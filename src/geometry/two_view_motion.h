#pragma once
/// @file two_view_motion.h
/// Building blocks of the two-view reconstruction (internal to mer_geometry; two_view.h is
/// the interface): the motion candidates of a homography or essential matrix, their
/// cheirality / reprojection / parallax vote, the plane-hint tie break and the Sampson
/// refinement of the essential model's motion.

#include <array>
#include <cstddef>
#include <cstdint>
#include <limits>
#include <optional>
#include <span>
#include <vector>

#include <Eigen/Core>

#include "geometry/camera_model.h"
#include "geometry/lie.h"
#include "geometry/two_view.h"

namespace mer::geometry::two_view_detail {

/// Intrinsics as a 3x3 matrix.
inline Eigen::Matrix3d k_matrix(const Pinhole& K) {
  Eigen::Matrix3d M;
  M << K.fx, 0.0, K.cx, 0.0, K.fy, K.cy, 0.0, 0.0, 1.0;
  return M;
}

/// Motion hypothesis: x_c1 = R x_c0 + t (t of arbitrary positive scale).
struct Motion {
  Eigen::Matrix3d R;
  Eigen::Vector3d t;
  Eigen::Vector3d n = Eigen::Vector3d::Zero();  ///< homography candidates: unit plane normal,
                                                ///< camera 0, z >= 0
};

/// Camera 1 from camera 0 with a unit translation.
SE3d unit_motion(const Motion& m);

/// The tied homography candidate the plane hints single out: the only one whose normal is
/// within plane_hint_agree_deg of a hint while every other is at least plane_hint_refute_deg
/// from all hints. nullopt without hints or without such a candidate.
std::optional<std::size_t> tie_broken_by_plane_hints(std::span<const Motion> candidates,
                                                     std::span<const std::size_t> tied,
                                                     std::span<const Eigen::Vector3d> hints,
                                                     const TwoViewOptions& o);

/// Motion candidates of one model: at most the eight of a homography.
struct MotionList {
  static constexpr std::size_t kCapacity = kMaxPlaneNormals;
  std::array<Motion, kCapacity> m;
  std::size_t size = 0;
  void push_back(const Motion& x) { m[size++] = x; }
  Motion& operator[](std::size_t k) { return m[k]; }
  const Motion& operator[](std::size_t k) const { return m[k]; }
  std::span<const Motion> span() const { return {m.data(), size}; }
};

/// The four (R, t) factorizations of an essential matrix (Hartley & Zisserman, result 9.19).
void decompose_essential(const Eigen::Matrix3d& E, MotionList& out);

/// The eight (R, t) factorizations of a calibrated homography Hn ~ R + t n^T / d
/// (Faugeras & Lustman 1988, SVD method): with Hn = U diag(d1, d2, d3) V^T and
/// s = det(U) det(V), R = s U R' V^T and t = U t', where (R', t') solve the diagonal problem
/// for d' = +d2 (rotation about y by theta) and d' = -d2 (reflection-like case), each with
/// the four sign choices (e1, e3) of the normal's components. Empty when two singular values
/// coincide (rotation-only or degenerate homography).
void decompose_homography(const Eigen::Matrix3d& Hn, MotionList& out);

/// What triangulating a model's inliers with one motion candidate gives.
struct CandidateCheck {
  int good = 0;        ///< consistent and seen under >= min_point_parallax_deg
  int consistent = 0;  ///< in front of both cameras with reprojection chi2 below the gate
  std::vector<double> parallax_deg;  ///< of the consistent points
  std::vector<std::uint8_t> status;  ///< per correspondence: kConsistent | kGood, or kUndecided
};

inline constexpr std::uint8_t kConsistent = 1;  ///< CandidateCheck::status bit
inline constexpr std::uint8_t kGood = 2;        ///< CandidateCheck::status bit
/// CandidateCheck::status bit: the point moved too little once the candidate's rotation is
/// taken out (it lies near the epipole) to say anything about the translation. Its ray pair
/// is nearly parallel to the baseline, so noise alone puts its triangulation behind a camera
/// or far off its pixels: it neither supports nor refutes the candidate.
inline constexpr std::uint8_t kUndecided = 4;

/// Triangulates the inliers with candidate `m` (midpoint for the vote; DLT, as in the map,
/// when `points`/`flags` are given) and applies the cheirality, reprojection and parallax
/// tests.
void check_candidate(const Motion& m, std::span<const Eigen::Vector2d> uv0,
                     std::span<const Eigen::Vector2d> uv1, std::span<const std::uint8_t> inliers,
                     const Pinhole& K, const TwoViewOptions& o,
                     std::vector<Eigen::Vector3d>* points, std::vector<std::uint8_t>* flags,
                     CandidateCheck& c);

/// Pixel fundamental matrix K^-T [t]x R K^-1 of a motion.
Eigen::Matrix3d fundamental_from_motion(const Motion& m, const Eigen::Matrix3d& K);

/// 1-sigma uncertainty of a refined motion (from the Gauss-Newton normal matrix).
struct MotionSigma {
  double rotation_deg = std::numeric_limits<double>::infinity();
  double translation_dir_deg = std::numeric_limits<double>::infinity();
};

/// Buffers of refine_motion (capacity: the correspondences).
struct RefineScratch {
  std::vector<std::size_t> idx;
  std::vector<double> r;
  std::vector<double> r_try;
  std::vector<double> J;
  void reserve(std::size_t n) {
    idx.reserve(n);
    r.reserve(n);
    r_try.reserve(n);
    J.reserve(5 * n);
  }
};

/// Levenberg-Marquardt on the Sampson error of the inliers over the 5-dof motion (the linear
/// 8-point F minimizes an algebraic error, biased with noise; this is close to the
/// maximum-likelihood estimate). Forward-difference Jacobian: 5 extra residual passes per
/// iteration, cheap next to RANSAC. Refines `m` in place.
MotionSigma refine_motion(Motion& m, std::span<const Eigen::Vector2d> uv0,
                          std::span<const Eigen::Vector2d> uv1,
                          std::span<const std::uint8_t> inliers, const Pinhole& K, double sigma_px,
                          RefineScratch& s);

}  // namespace mer::geometry::two_view_detail
