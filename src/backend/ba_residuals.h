#pragma once
/// @file ba_residuals.h
/// Residuals of the covisibility-graph optimization with analytic Jacobians (checked against
/// numeric ones in tests/unit/backend), and the rotation manifold they are written for.
///
/// Parameter blocks: a keyframe's world-to-camera rotation q_c_w as a unit quaternion
/// (x, y, z, w; Eigen storage order), its translation t_c_w, a map-point's world position X,
/// and a keyframe's depth scale s. Rotation updates are left perturbations by a rotation
/// vector, R <- Exp(delta) R, so every cost function writes its rotation Jacobian with
/// respect to delta into the first three columns of the 4-column ambient block and zero into
/// the fourth, and RotationManifold::PlusJacobian is [I3; 0]: Ceres' chain rule then yields
/// the tangent Jacobian exactly, without a quaternion derivative per residual.
///
/// Every residual block has two rows (the 3D-3D edge's second row is identically zero), so
/// that a window's Jacobian has one row-block size and Ceres' Schur eliminator runs its
/// fixed-size specialization (2, 3, 3) instead of the dynamic one: the linear solve of an
/// iteration is about 2.5x faster, which bounds how long an abort request can wait.
///
/// Abort: a cost function given an abort flag polls it on every evaluation, so that an
/// evaluation (the longest part of an iteration after the linear solve) ends soon after a
/// request. Once the flag is set, a cost-only evaluation (a candidate step) fails: Ceres
/// rejects the step, keeps the last accepted point and calls the iteration callbacks, which
/// stop the solve. A Jacobian evaluation is not failed (Ceres would end the solve with
/// FAILURE, discarding all its progress, and log an error): it returns zero residuals and
/// Jacobians; it is always followed by the iteration callbacks, which stop the solve before
/// anything uses them, and the point it was taken at was accepted on a complete cost-only
/// evaluation (the cost Ceres reports for that iteration is then not meaningful).

#include <atomic>

#include <ceres/cost_function.h>
#include <ceres/manifold.h>
#include <ceres/sized_cost_function.h>

#include "geometry/camera_model.h"

namespace mer::backend {

/// SO(3) as a unit quaternion with left rotation-vector updates (see the file comment).
class RotationManifold final : public ceres::Manifold {
 public:
  int AmbientSize() const override { return 4; }
  int TangentSize() const override { return 3; }
  bool Plus(const double* x, const double* delta, double* x_plus_delta) const override;
  bool PlusJacobian(const double* x, double* jacobian) const override;
  bool Minus(const double* y, const double* x, double* y_minus_x) const override;
  bool MinusJacobian(const double* x, double* jacobian) const override;
};

/// 3D-2D edge: pixel error of world point X seen by keypoint (u, v) from camera (q, t),
/// divided by the keypoint sigma. Blocks: q (4), t (3), X (3).
class ReprojectionCost final : public ceres::SizedCostFunction<2, 4, 3, 3> {
 public:
  /// `abort` (optional, not owned): see the file comment.
  ReprojectionCost(double u_px, double v_px, double inv_sigma_px, const geometry::Pinhole& K,
                   const std::atomic<bool>* abort = nullptr)
      : u_(u_px), v_(v_px), inv_sigma_(inv_sigma_px), K_(K), abort_(abort) {}
  bool Evaluate(double const* const* parameters, double* residuals,
                double** jacobians) const override;

 private:
  double u_;          // observed column, px
  double v_;          // observed row, px
  double inv_sigma_;  // 1 / keypoint sigma, 1/px
  geometry::Pinhole K_;
  const std::atomic<bool>* abort_;
};

/// 3D-3D edge along the viewing ray: camera z of world point X minus the keyframe's local
/// depth d times its depth scale s, divided by the edge sigma; the second row is zero (see
/// the file comment). Blocks: q (4), t (3), X (3), s (1).
class DepthCost final : public ceres::SizedCostFunction<2, 4, 3, 3, 1> {
 public:
  /// `abort` (optional, not owned): see the file comment.
  DepthCost(double depth, double inv_sigma_m, const std::atomic<bool>* abort = nullptr)
      : d_(depth), inv_sigma_(inv_sigma_m), abort_(abort) {}
  bool Evaluate(double const* const* parameters, double* residuals,
                double** jacobians) const override;

 private:
  double d_;          // local depth, keyframe depth units
  double inv_sigma_;  // 1 / edge sigma
  const std::atomic<bool>* abort_;
};

}  // namespace mer::backend
