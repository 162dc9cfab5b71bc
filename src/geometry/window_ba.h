#pragma once
/// @file window_ba.h
/// Structure and motion over a short window of frames that all see keypoints of one
/// reference frame: a small bundle adjustment for the monocular start
/// (frontend/initializer.h). Every point is an inverse depth along the ray of its reference
/// keypoint (the inverse-depth parametrization of Civera et al., anchored in one host frame
/// as DSO anchors its points): a point at inverse depth 0 is at infinity and still
/// constrains the views' rotations.
///
/// Gauge: the reference camera is the world frame and is not a parameter. One view, the
/// scale view, keeps a unit translation (its translation moves on the unit sphere): the
/// window's scale is fixed without fixing a point.
///
/// Observation (v, i) is the pixel of point i in view v. With f_i = (x, y, 1) the reference
/// ray and (R_v, t_v) the view's camera-from-reference pose, the point in the view is
/// q = R_v f_i + rho_i t_v up to the positive factor 1 / rho_i, so its projection is defined
/// at rho = 0 too. Residual: (project(q) - uv) / sigma_px, Huber-weighted at sqrt(huber_chi2).
/// A point behind a view (q_z <= 0) costs huber(kBehindChi2) and gives no gradient.
///
/// Levenberg-Marquardt; the points are eliminated by the Schur complement (one parameter
/// each), leaving the 6V x 6V reduced camera system. Updates: R_v <- Exp(w) R_v,
/// t_v <- t_v + dt. The information matrix of the last solve gives the scale view's rotation
/// and translation-direction uncertainty.
///
/// reserve() allocates; set-up, solve and the covariance do not. Not thread-safe.

#include <cstdint>
#include <vector>

#include <Eigen/Cholesky>
#include <Eigen/Core>

#include "core/pose.h"
#include "geometry/camera_model.h"

namespace mer::geometry {

/// Cost of a point behind a view, as a squared normalized error (before the Huber kernel).
inline constexpr double kWindowBaBehindChi2 = 100.0;

/// Residual of one observation and its Jacobians (exposed for the tests): `r` = (project(q) -
/// uv) / sigma_px with q = R f + rho t. `d_r_d_pose` (2x6: rotation vector of the left update,
/// then translation) and `d_r_d_rho` may be null. Returns false (nothing written) when q is
/// behind the camera.
bool window_ba_residual(const Pinhole& K, const Eigen::Matrix3d& R, const Eigen::Vector3d& t,
                        const Eigen::Vector3d& f, double rho, const Eigen::Vector2d& uv,
                        double inv_sigma, Eigen::Vector2d& r,
                        Eigen::Matrix<double, 2, 6>* d_r_d_pose, Eigen::Vector2d* d_r_d_rho);

/// What a solve did.
struct WindowBaSummary {
  double initial_cost = 0.0;  ///< Huber cost before the solve (sum over observations)
  double final_cost = 0.0;    ///< and after
  int iterations = 0;         ///< iterations run (accepted or not)
  int observations = 0;       ///< observations in front of their view at the end
  int behind = 0;             ///< observations behind their view at the end
};

/// 1-sigma uncertainty of a view's pose (from the Schur complement of the information).
struct WindowBaSigma {
  bool ok = false;                   ///< the reduced system was positive definite
  double rotation_deg = 0.0;         ///< largest rotation sigma
  double translation_dir_deg = 0.0;  ///< largest sigma of the translation direction
                                     ///< (scale view: its unit translation's tangent)
};

/// Bundle adjustment of views and inverse-depth points anchored in a reference frame.
class WindowBundleAdjuster {
 public:
  /// Sizes the problem: at most `max_views` views besides the reference, `max_points`
  /// points (allocates).
  void reserve(int max_views, int max_points);

  /// Starts a new problem (no views, no points).
  void reset(const Pinhole& K, double huber_chi2);

  /// Adds a point on the reference ray through `uv_ref` at inverse depth `inv_depth` (in the
  /// units of the scale view's unit baseline), seen with pixel noise `sigma_px` in every view.
  /// Returns its index, or -1 when full.
  int add_point(const Eigen::Vector2d& uv_ref, double inv_depth, double sigma_px);
  /// Sets point `i`'s inverse depth.
  void set_inv_depth(int i, double inv_depth) { rho_[static_cast<std::size_t>(i)] = inv_depth; }
  /// Adds a view at `T_c_ref` (camera from reference). Returns its index, or -1 when full.
  int add_view(const SE3d& T_c_ref);
  /// Makes view `v` the scale view: its translation is scaled to unit length and kept there.
  void set_scale_view(int v);
  /// Holds view `v` where it is (a hypothesis to test; it also fixes the scale).
  void fix_view(int v) { fixed_view_ = v; }
  /// Point `i` is seen at pixel `uv` in view `v`.
  void observe(int v, int i, const Eigen::Vector2d& uv);
  /// Observations whose squared normalized error exceeds `chi2_gate` no longer count in the
  /// solve (they still count in truncated_cost). Returns how many were dropped.
  int drop_outliers(double chi2_gate);
  /// Sum over every observation, dropped ones included, of min(squared normalized error,
  /// `chi2_gate`): the score (as in MSAC) by which solutions of one window compare.
  double truncated_cost(double chi2_gate) const;
  /// truncated_cost of point i's observations alone.
  double point_truncated_cost(int i, double chi2_gate) const;
  /// Observations (dropped ones included).
  int num_observations() const;

  /// Up to `iterations` Levenberg-Marquardt iterations; with `points_fixed` only the views
  /// move (each on its own).
  WindowBaSummary solve(int iterations, bool points_fixed);

  /// Uncertainty of view `v`'s pose at the current estimate (the points marginalized).
  WindowBaSigma sigma(int v);

  int num_views() const { return num_views_; }
  int num_points() const { return num_points_; }
  const SE3d& pose(int v) const { return T_[static_cast<std::size_t>(v)]; }
  double inv_depth(int i) const { return rho_[static_cast<std::size_t>(i)]; }
  /// Reference ray (x, y, 1) of point i.
  const Eigen::Vector3d& ray(int i) const { return f_[static_cast<std::size_t>(i)]; }
  bool observed(int v, int i) const { return obs_valid_[index(v, i)] == kActive; }
  /// Squared normalized error of observation (v, i) at the current estimate
  /// (kWindowBaBehindChi2 behind the view; 0 when not observed).
  double chi2(int v, int i) const;
  /// Huber cost of all observations at the current estimate.
  double cost() const;

 private:
  std::size_t index(int v, int i) const {
    return static_cast<std::size_t>(v) * static_cast<std::size_t>(max_points_) +
           static_cast<std::size_t>(i);
  }
  static constexpr std::uint8_t kNone = 0;     // not observed
  static constexpr std::uint8_t kActive = 1;   // observed, in the solve
  static constexpr std::uint8_t kDropped = 2;  // observed, dropped as an outlier
  double huber(double s) const;
  /// Linearizes at the current estimate into h_cc_, b_c_, h_cp_, h_pp_, b_p_; returns the cost.
  double linearize();
  /// Reduced camera system with damping `lambda` into S_ / b_s_.
  void reduce(double lambda, bool points_fixed);

  Pinhole K_;
  double huber_k_ = 1.0;  // sqrt(huber_chi2)
  int max_views_ = 0;
  int max_points_ = 0;
  int num_views_ = 0;
  int num_points_ = 0;
  int scale_view_ = -1;
  int fixed_view_ = -1;

  std::vector<SE3d> T_;
  std::vector<SE3d> saved_T_;
  std::vector<double> rho_;
  std::vector<double> rho_saved_;
  std::vector<Eigen::Vector3d> f_;
  std::vector<double> inv_sigma_;        // per point, 1/px
  std::vector<Eigen::Vector2d> obs_uv_;  // view-major, max_points_ per view
  std::vector<std::uint8_t> obs_valid_;  // kNone, kActive or kDropped
  // Linearization.
  Eigen::MatrixXd h_cc_;  // 6 max_views square
  Eigen::VectorXd b_c_;
  std::vector<Eigen::Matrix<double, 6, 1>> h_cp_;  // per observation
  std::vector<double> h_pp_;
  std::vector<double> b_p_;
  // Reduced system and its solution.
  Eigen::MatrixXd S_;
  Eigen::VectorXd b_s_;
  Eigen::VectorXd dc_;
  Eigen::LDLT<Eigen::MatrixXd> ldlt_;
  Eigen::MatrixXd cov_rhs_;  // 6 max_views x 6
};

}  // namespace mer::geometry
