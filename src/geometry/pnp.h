#pragma once
/// @file pnp.h
/// Robust absolute pose (PnP) for the tracking thread: P3P-RANSAC with local optimisation
/// (LO-RANSAC, MSAC scoring) and a final Huber-robust Levenberg-Marquardt refinement; an
/// optional variant also estimates the focal length (fx = fy = f, principal point fixed).
///
/// Conventions
///  - Poses are world-to-camera, T_c_w (p_c = T_c_w * X_w), camera looking along +z.
///  - Residuals are uv_pred - uv in level-0 pixels.
///  - Pose perturbations are **left** perturbations with the twist ordered [omega; v]
///    (see lie.h):  T_c_w <- se3_exp(xi) * T_c_w,  so  d p_c / d xi = [-hat(p_c), I].
///  - Observation i has noise scale sigma_i (pyramid level scale; 1 when the span is empty):
///    it is an inlier when |r_i| <= inlier_threshold_px * sigma_i and it is weighted by
///    1 / sigma_i^2 in the refinement (the Huber width applies to |r_i| / sigma_i).
///  - Points with depth <= 0 in the camera (behind it) are outliers and never used.
///
/// Real-time contract: PnpRansac preallocates every buffer in its constructor for up to
/// `max_correspondences` correspondences; solve() / solve_with_focal() / refine_pose() do
/// not allocate. Inputs larger than that capacity are rejected (ok = false).

#include <cstddef>
#include <cstdint>
#include <limits>
#include <span>
#include <vector>

#include <Eigen/Core>

#include "core/options.h"
#include "core/pose.h"
#include "geometry/camera_model.h"
#include "geometry/lie.h"
#include "geometry/random.h"

namespace mer::geometry {

/// Options of the robust PnP (config section `tracking.pnp`).
struct PnpOptions {
  int max_iterations = 200;
  double confidence = 0.999;
  double inlier_threshold_px = 2.5;
  int min_inliers = 15;
  int lo_min_inliers = 10;
  int refine_iterations = 10;
  double huber_px = 2.0;
  std::uint64_t seed = 1;

  template <class V>
  void visit(V& v) {
    v.field("max_iterations", max_iterations, "RANSAC iteration (minimal sample) cap",
            options::Range<int>{1, 100000});
    v.field("confidence", confidence,
            "RANSAC early-stop confidence of having drawn one all-inlier sample",
            options::Range<double>{0.5, 0.999999});
    v.field("inlier_threshold_px", inlier_threshold_px,
            "inlier reprojection error, px at pyramid level 0 (scaled by the observation sigma)",
            options::Range<double>{0.1, 100.0});
    v.field("min_inliers", min_inliers, "minimum final inliers for a successful pose",
            options::Range<int>{3, 100000});
    v.field("lo_min_inliers", lo_min_inliers,
            "local optimisation: a new best RANSAC model with at least this many inliers is "
            "refit on them (LO-RANSAC)",
            options::Range<int>{6, 100000});
    v.field("refine_iterations", refine_iterations,
            "Levenberg-Marquardt iterations of the final robust refinement (0 = none)",
            options::Range<int>{0, 1000});
    v.field("huber_px", huber_px, "Huber kernel width of the refinement, px (scaled by sigma)",
            options::Range<double>{0.01, 100.0});
    // The YAML layer reads signed 64-bit integers: go through one (seeds are small).
    auto seed_value = static_cast<std::int64_t>(seed);
    v.field("seed", seed_value, "RANSAC sampler seed (same seed and input -> same result)",
            options::Range<std::int64_t>{0, std::numeric_limits<std::int64_t>::max()});
    seed = static_cast<std::uint64_t>(seed_value);
  }
};

/// Correspondences of one PnP problem (views into the caller's arrays, same length n).
struct PnpInput {
  // NOLINTNEXTLINE(readability-identifier-naming): math name, as in the tracker's calls
  std::span<const Eigen::Vector3d> X_w;  ///< world points
  std::span<const Eigen::Vector2d> uv;   ///< pixel observations (level-0 px)
  std::span<const float> sigma;          ///< per-observation noise scale (> 0); empty = all 1
  Pinhole K;                             ///< intrinsics (fx is the focal guess for *_with_focal)
};

/// Outcome of a PnP solve.
struct PnpResult {
  bool ok = false;                ///< a pose with >= min_inliers inliers was found
  SE3d T_c_w = SE3d::Identity();  ///< world-to-camera pose (best found, also when !ok)
  double focal = 0;               ///< focal length used / estimated, px
  int num_inliers = 0;            ///< inliers of the final pose
  int iterations = 0;             ///< RANSAC samples drawn
  double rms_px = 0;              ///< RMS reprojection error of the inliers, px (not / sigma)
};

/// Options of refine_pose().
struct RefineOptions {
  int iterations = 10;          ///< LM iterations (accepted or rejected steps)
  double huber_px = 2.0;        ///< Huber width on |r| / sigma, px; <= 0 = plain least squares
  bool estimate_focal = false;  ///< also estimate f (fx = fy = f), needs `focal` != null
};

/// Outcome of refine_pose().
struct RefineResult {
  int iterations = 0;       ///< LM iterations run
  double initial_cost = 0;  ///< robust cost before (sum of Huber rho of |r| / sigma), px^2
  double final_cost = 0;    ///< robust cost after
  int num_used = 0;         ///< masked correspondences in front of the camera at the end
};

/// Robust (Huber) Levenberg-Marquardt on the masked correspondences (empty mask = all;
/// otherwise mask[i] != 0 selects i). Updates T_c_w, and *focal when o.estimate_focal
/// (then fx = fy = *focal; otherwise in.K is used as is and `focal` may be null).
/// Correspondences behind the camera are left out of the normal equations and charged a
/// constant penalty in the cost (so a step cannot win by pushing points behind the
/// camera). Steps that do not lower the cost are rejected: final_cost <= initial_cost.
/// Sigma entries must be > 0 (not checked here). No allocation.
RefineResult refine_pose(const PnpInput& in, std::span<const std::uint8_t> mask, SE3d& T_c_w,
                         double* focal, const RefineOptions& o);

/// Reprojection residual uv_pred - uv (px) of point_w under T_c_w and K. Optional Jacobians:
/// d_r_d_xi w.r.t. the left perturbation T_c_w <- se3_exp(xi) * T_c_w, xi = [omega; v];
/// d_r_d_f w.r.t. the focal length f with fx = fy = f. Precondition: the point is in front
/// of the camera ((T_c_w * point_w).z() > 0); otherwise the values are meaningless.
Eigen::Vector2d reprojection_residual(const SE3d& T_c_w, const Eigen::Vector3d& point_w,
                                      const Eigen::Vector2d& uv, const Pinhole& K,
                                      Eigen::Matrix<double, 2, 6>* d_r_d_xi,
                                      Eigen::Vector2d* d_r_d_f);

/// P3P-RANSAC (LO-RANSAC with MSAC scoring) + robust refinement. One instance per thread;
/// not thread-safe (holds scratch buffers).
class PnpRansac {
 public:
  /// Preallocates all scratch for up to `max_correspondences` correspondences.
  PnpRansac(const PnpOptions& opts, std::size_t max_correspondences);

  /// Pose with fixed intrinsics in.K. inlier_mask.size() >= n receives 1 (inlier) / 0 for
  /// the first n entries, for the returned T_c_w (also when !ok; all 0 on invalid input:
  /// size mismatch, n > capacity(), n < max(3, min_inliers), sigma <= 0, fx or fy <= 0). `prior`
  /// (may be null): a predicted T_c_w scored as the first hypothesis (when it explains the data,
  /// RANSAC stops after very few samples). No heap allocation.
  PnpResult solve(const PnpInput& in, std::span<std::uint8_t> inlier_mask,
                  const SE3d* prior = nullptr);

  /// Pose and focal length (fx = fy = f, principal point fixed), starting from the guess
  /// in.K.fx (in.K.fy is ignored; the result has fx = fy = focal): P3P-RANSAC at a
  /// geometric sweep of focal candidates (the guess first, then x 1.125^k up to
  /// x 0.55 .. 1.8) scored with a 4x widened threshold, local optimisation of pose + f on
  /// every new best, then joint LM while the threshold is brought down to
  /// inlier_threshold_px. The sweep stops as soon as a model explains half of the
  /// correspondences at the real threshold: ~1 solve() when the guess is close (tracking),
  /// up to ~11 when it is far off. Needs metric, accurate 3D points with some depth
  /// variation (f and depth trade off for flat or distant scenes). No heap allocation.
  PnpResult solve_with_focal(const PnpInput& in, std::span<std::uint8_t> inlier_mask,
                             const SE3d* prior = nullptr);

  /// Options in use.
  const PnpOptions& options() const { return opts_; }
  /// Largest number of correspondences accepted.
  std::size_t capacity() const { return capacity_; }

 private:
  /// A pose hypothesis with the intrinsics it was scored with and its MSAC cost.
  struct Hypothesis {
    SE3d T_c_w = SE3d::Identity();
    Pinhole K;
    double cost = std::numeric_limits<double>::infinity();
    int num_inliers = 0;
  };
  bool prepare(const PnpInput& in, std::span<std::uint8_t> inlier_mask);
  double score(const PnpInput& in, const SE3d& T_c_w, const Pinhole& K, double thr2,
               double bail_cost, int& num_inliers) const;
  int mark_inliers(const PnpInput& in, const SE3d& T_c_w, const Pinhole& K, double thr2,
                   std::span<std::uint8_t> mask) const;
  void ransac(const PnpInput& in, const Pinhole& K, double thr2, const SE3d* prior,
              bool estimate_focal, Hypothesis& best, int& iterations);
  void local_optimize(const PnpInput& in, double thr2, bool estimate_focal, Hypothesis& h);
  PnpResult finish(const PnpInput& in, const Hypothesis& best, std::span<std::uint8_t> inlier_mask,
                   bool estimate_focal, int iterations);

  PnpOptions opts_;
  std::size_t capacity_ = 0;
  Rng rng_;
  std::vector<double> inv_sigma2_;  ///< 1 / sigma_i^2 of the current problem
  std::vector<std::uint8_t> mask_;  ///< scratch inlier mask (local optimisation)
};

}  // namespace mer::geometry
