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
  ReprojectionCost(double u_px, double v_px, double inv_sigma_px, const geometry::Pinhole& K)
      : u_(u_px), v_(v_px), inv_sigma_(inv_sigma_px), K_(K) {}
  bool Evaluate(double const* const* parameters, double* residuals,
                double** jacobians) const override;

 private:
  double u_;          // observed column, px
  double v_;          // observed row, px
  double inv_sigma_;  // 1 / keypoint sigma, 1/px
  geometry::Pinhole K_;
};

/// 3D-3D edge along the viewing ray: camera z of world point X minus the keyframe's local
/// depth d times its depth scale s, divided by the edge sigma. Blocks: q (4), t (3), X (3),
/// s (1).
class DepthCost final : public ceres::SizedCostFunction<1, 4, 3, 3, 1> {
 public:
  DepthCost(double depth, double inv_sigma_m) : d_(depth), inv_sigma_(inv_sigma_m) {}
  bool Evaluate(double const* const* parameters, double* residuals,
                double** jacobians) const override;

 private:
  double d_;          // local depth, keyframe depth units
  double inv_sigma_;  // 1 / edge sigma
};

}  // namespace mer::backend
