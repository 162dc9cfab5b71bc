#include "backend/ba_residuals.h"

#include <algorithm>
#include <cstdint>
#include <vector>

#include <Eigen/Geometry>

#include "geometry/lie.h"

namespace mer::backend {
namespace {

using RowMajor23 = Eigen::Matrix<double, 2, 3, Eigen::RowMajor>;
using RowMajor24 = Eigen::Matrix<double, 2, 4, Eigen::RowMajor>;

/// True once the run was asked to stop; a Jacobian evaluation then fills zeros (file comment).
bool aborted(const std::atomic<bool>* abort, int num_residuals,
             const std::vector<int32_t>& block_sizes, double* residuals, double** jacobians) {
  if (abort == nullptr || !abort->load(std::memory_order_relaxed)) return false;
  if (jacobians == nullptr) return true;
  std::fill_n(residuals, num_residuals, 0.0);
  for (std::size_t b = 0; b < block_sizes.size(); ++b) {
    if (jacobians[b] != nullptr) std::fill_n(jacobians[b], num_residuals * block_sizes[b], 0.0);
  }
  return true;
}

Eigen::Matrix3d rotation(const double* q) {
  return Eigen::Map<const Eigen::Quaterniond>(q).normalized().toRotationMatrix();
}

}  // namespace

bool RotationManifold::Plus(const double* x, const double* delta, double* x_plus_delta) const {
  const Eigen::Map<const Eigen::Quaterniond> q(x);
  const Eigen::Quaterniond dq(geometry::so3_exp(Eigen::Vector3d(delta[0], delta[1], delta[2])));
  Eigen::Map<Eigen::Quaterniond> out(x_plus_delta);
  out = (dq * q).normalized();
  return true;
}

bool RotationManifold::PlusJacobian(const double* /*x*/, double* jacobian) const {
  Eigen::Map<Eigen::Matrix<double, 4, 3, Eigen::RowMajor>> J(jacobian);
  J.setZero();
  J.topRows<3>().setIdentity();
  return true;
}

bool RotationManifold::Minus(const double* y, const double* x, double* y_minus_x) const {
  const Eigen::Map<const Eigen::Quaterniond> qy(y);
  const Eigen::Map<const Eigen::Quaterniond> qx(x);
  Eigen::Map<Eigen::Vector3d> out(y_minus_x);
  out = geometry::so3_log((qy * qx.conjugate()).normalized().toRotationMatrix());
  return true;
}

bool RotationManifold::MinusJacobian(const double* /*x*/, double* jacobian) const {
  Eigen::Map<Eigen::Matrix<double, 3, 4, Eigen::RowMajor>> J(jacobian);
  J.setZero();
  J.leftCols<3>().setIdentity();
  return true;
}

bool ReprojectionCost::Evaluate(double const* const* parameters, double* residuals,
                                double** jacobians) const {
  if (aborted(abort_, num_residuals(), parameter_block_sizes(), residuals, jacobians)) {
    return jacobians != nullptr;
  }
  const Eigen::Matrix3d R = rotation(parameters[0]);
  const Eigen::Map<const Eigen::Vector3d> t(parameters[1]);
  const Eigen::Map<const Eigen::Vector3d> X(parameters[2]);
  const Eigen::Vector3d x_rot = R * X;
  const Eigen::Vector3d p = x_rot + t;
  if (p.z() <= 0.0) return false;
  const double iz = 1.0 / p.z();
  residuals[0] = (K_.fx * p.x() * iz + K_.cx - u_) * inv_sigma_;
  residuals[1] = (K_.fy * p.y() * iz + K_.cy - v_) * inv_sigma_;
  if (jacobians == nullptr) return true;
  RowMajor23 d_r_d_p;
  d_r_d_p << K_.fx * iz, 0.0, -K_.fx * p.x() * iz * iz, 0.0, K_.fy * iz, -K_.fy * p.y() * iz * iz;
  d_r_d_p *= inv_sigma_;
  if (jacobians[0] != nullptr) {  // d p / d delta = -[R X]x (left perturbation)
    Eigen::Map<RowMajor24> J(jacobians[0]);
    J.leftCols<3>() = -d_r_d_p * geometry::hat(x_rot);
    J.col(3).setZero();
  }
  if (jacobians[1] != nullptr) {
    Eigen::Map<RowMajor23> J(jacobians[1]);
    J = d_r_d_p;
  }
  if (jacobians[2] != nullptr) {
    Eigen::Map<RowMajor23> J(jacobians[2]);
    J = d_r_d_p * R;
  }
  return true;
}

bool DepthCost::Evaluate(double const* const* parameters, double* residuals,
                         double** jacobians) const {
  if (aborted(abort_, num_residuals(), parameter_block_sizes(), residuals, jacobians)) {
    return jacobians != nullptr;
  }
  const Eigen::Matrix3d R = rotation(parameters[0]);
  const Eigen::Map<const Eigen::Vector3d> t(parameters[1]);
  const Eigen::Map<const Eigen::Vector3d> X(parameters[2]);
  const double s = parameters[3][0];
  const Eigen::Vector3d x_rot = R * X;
  residuals[0] = (x_rot.z() + t.z() - s * d_) * inv_sigma_;
  residuals[1] = 0.0;
  if (jacobians == nullptr) return true;
  // Row 0 (the second row is zero): d r / d delta is row 2 of -[R X]x.
  if (jacobians[0] != nullptr) {
    std::fill_n(jacobians[0], 8, 0.0);
    jacobians[0][0] = x_rot.y() * inv_sigma_;
    jacobians[0][1] = -x_rot.x() * inv_sigma_;
  }
  if (jacobians[1] != nullptr) {
    std::fill_n(jacobians[1], 6, 0.0);
    jacobians[1][2] = inv_sigma_;
  }
  if (jacobians[2] != nullptr) {
    std::fill_n(jacobians[2], 6, 0.0);
    for (int i = 0; i < 3; ++i) jacobians[2][i] = R(2, i) * inv_sigma_;
  }
  if (jacobians[3] != nullptr) {
    jacobians[3][0] = -d_ * inv_sigma_;
    jacobians[3][1] = 0.0;
  }
  return true;
}

}  // namespace mer::backend
