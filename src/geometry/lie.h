#pragma once
/// @file lie.h
/// SO(3) / SE(3) exponential and logarithm maps (header-only, no allocation).
///
/// Tangent-vector convention: a 6-vector twist is ordered **[omega; v]** (rotation first,
/// then translation), xi = (wx, wy, wz, vx, vy, vz). Perturbations in this code base are
/// applied on the **left**: T <- se3_exp(xi) * T (see pnp.h), so for a point p = T * X the
/// first-order change is dp = omega x p + v, i.e. dp/dxi = [-hat(p), I].
///
/// Every function is safe at and near zero angle: below kSmallAngle the closed forms are
/// replaced by their Taylor series.

#include <algorithm>
#include <cmath>
#include <numbers>

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <Eigen/SVD>

#include "core/pose.h"

namespace mer::geometry {

/// 6-vector twist [omega; v].
using Vector6d = Eigen::Matrix<double, 6, 1>;

namespace lie_detail {
/// Angles (rad) below this use Taylor expansions: at 1e-4 rad the first dropped term of
/// each series is ~theta^4 / 120 ~ 1e-18, well below double precision.
inline constexpr double kSmallAngle = 1e-4;
/// Within this of pi the log map extracts the axis from the symmetric part of R, where the
/// generic sin(theta) division loses precision.
inline constexpr double kNearPi = 1e-6;
}  // namespace lie_detail

/// Skew-symmetric matrix of w: hat(w) * x = w x x.
inline Eigen::Matrix3d hat(const Eigen::Vector3d& w) {
  Eigen::Matrix3d W;
  W << 0.0, -w.z(), w.y(),  //
      w.z(), 0.0, -w.x(),   //
      -w.y(), w.x(), 0.0;
  return W;
}

/// Inverse of hat() (reads the off-diagonal entries, averaging each pair).
inline Eigen::Vector3d vee(const Eigen::Matrix3d& W) {
  return {0.5 * (W(2, 1) - W(1, 2)), 0.5 * (W(0, 2) - W(2, 0)), 0.5 * (W(1, 0) - W(0, 1))};
}

/// Rodrigues: rotation matrix of the rotation vector w (axis * angle, rad).
inline Eigen::Matrix3d so3_exp(const Eigen::Vector3d& w) {
  const double theta2 = w.squaredNorm();
  const double theta = std::sqrt(theta2);
  double a = 0.0;  // sin(theta) / theta
  double b = 0.0;  // (1 - cos(theta)) / theta^2
  if (theta < lie_detail::kSmallAngle) {
    a = 1.0 - theta2 / 6.0;
    b = 0.5 - theta2 / 24.0;
  } else {
    a = std::sin(theta) / theta;
    b = (1.0 - std::cos(theta)) / theta2;
  }
  const Eigen::Matrix3d W = hat(w);
  return Eigen::Matrix3d::Identity() + a * W + b * W * W;
}

/// Rotation vector (axis * angle, angle in [0, pi]) of a rotation matrix.
inline Eigen::Vector3d so3_log(const Eigen::Matrix3d& R) {
  const double cos_theta = 0.5 * (R.trace() - 1.0);
  const Eigen::Vector3d v = vee(R);  // = sin(theta) * axis
  const double sin_theta = v.norm();
  // atan2 keeps full precision near 0 and pi, where acos(cos_theta) does not.
  const double theta = std::atan2(sin_theta, cos_theta);
  if (theta < lie_detail::kSmallAngle) {
    // theta / sin(theta) ~ 1 + theta^2 / 6
    return (1.0 + theta * theta / 6.0) * v;
  }
  if (std::numbers::pi - theta < lie_detail::kNearPi) {
    // sym(R) = cos(theta) I + (1 - cos(theta)) a a^T, so (sym(R) + I) / 2 ~ a a^T: the axis
    // is its dominant column (the antisymmetric part, ~ pi - theta, is left out).
    const Eigen::Matrix3d S = 0.25 * (R + R.transpose()) + 0.5 * Eigen::Matrix3d::Identity();
    Eigen::Index k = 0;
    S.diagonal().maxCoeff(&k);
    Eigen::Vector3d axis = S.col(k) / std::sqrt(std::max(S(k, k), 0.0));
    axis.normalize();
    if (axis.dot(v) < 0.0) axis = -axis;  // keep the sign given by the (tiny) sine part
    return theta * axis;
  }
  return (theta / sin_theta) * v;
}

/// Left Jacobian of SO(3): V(w) = I + (1 - cos)/theta^2 hat(w) + (theta - sin)/theta^3 hat(w)^2.
/// Maps the translational part of a twist to the translation of se3_exp().
inline Eigen::Matrix3d so3_left_jacobian(const Eigen::Vector3d& w) {
  const double theta2 = w.squaredNorm();
  const double theta = std::sqrt(theta2);
  double b = 0.0;  // (1 - cos(theta)) / theta^2
  double c = 0.0;  // (theta - sin(theta)) / theta^3
  if (theta < lie_detail::kSmallAngle) {
    b = 0.5 - theta2 / 24.0;
    c = 1.0 / 6.0 - theta2 / 120.0;
  } else {
    b = (1.0 - std::cos(theta)) / theta2;
    c = (theta - std::sin(theta)) / (theta2 * theta);
  }
  const Eigen::Matrix3d W = hat(w);
  return Eigen::Matrix3d::Identity() + b * W + c * W * W;
}

/// SE(3) exponential of the twist xi = [omega; v].
inline SE3d se3_exp(const Vector6d& xi) {
  const Eigen::Vector3d w = xi.head<3>();
  SE3d T = SE3d::Identity();
  T.linear() = so3_exp(w);
  T.translation() = so3_left_jacobian(w) * xi.tail<3>();
  return T;
}

/// SE(3) logarithm: the twist [omega; v] with se3_exp(se3_log(T)) == T.
inline Vector6d se3_log(const SE3d& T) {
  const Eigen::Vector3d w = so3_log(T.linear());
  Vector6d xi;
  xi.head<3>() = w;
  // V is invertible for |w| < 2 pi (always true for the principal log).
  xi.tail<3>() = so3_left_jacobian(w).inverse() * T.translation();
  return xi;
}

/// The rotation nearest to M in the Frobenius norm (orthogonal Procrustes: M = U S V^T gives
/// U diag(1, 1, det(U V^T)) V^T), e.g. for M = sum of b_i a_i^T over pairs of unit vectors,
/// the rotation that best maps a_i onto b_i.
inline Eigen::Matrix3d nearest_rotation(const Eigen::Matrix3d& M) {
  const Eigen::JacobiSVD<Eigen::Matrix3d> svd(M, Eigen::ComputeFullU | Eigen::ComputeFullV);
  const Eigen::Vector3d diag(1.0, 1.0, (svd.matrixU() * svd.matrixV().transpose()).determinant());
  return svd.matrixU() * diag.asDiagonal() * svd.matrixV().transpose();
}

/// Rotation angle (rad, in [0, pi]) between two rotation matrices.
inline double rotation_angle(const Eigen::Matrix3d& R1, const Eigen::Matrix3d& R2) {
  return so3_log(R1.transpose() * R2).norm();
}

}  // namespace mer::geometry
