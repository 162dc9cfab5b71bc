#include "geometry/triangulation.h"

#include <array>
#include <cmath>
#include <numbers>

#include <Eigen/SVD>

namespace mer::geometry {
namespace {

/// |w| of the unit homogeneous solution below this means the point lies farther than
/// 1 / kMinHomogeneousScale (in world units) from the first camera centre: at infinity.
constexpr double kMinHomogeneousScale = 1e-10;
/// Degrees per radian.
constexpr double kRadToDeg = 180.0 / std::numbers::pi;

/// Upper-triangular factor R of a tall matrix A (R^T R = A^T A), built one row at a time
/// with Givens rotations so the stacked DLT matrix never has to be stored.
class IncrementalQr4 {
 public:
  void add_row(Eigen::Vector4d row) {
    for (int j = 0; j < 4; ++j) {
      if (row(j) == 0.0) continue;
      const double a = upper_(j, j);
      const double b = row(j);
      const double rho = std::hypot(a, b);
      const double c = a / rho;
      const double s = b / rho;
      for (int k = j; k < 4; ++k) {
        const double r_jk = upper_(j, k);
        upper_(j, k) = c * r_jk + s * row(k);
        row(k) = -s * r_jk + c * row(k);
      }
    }
  }
  const Eigen::Matrix4d& r() const { return upper_; }

 private:
  Eigen::Matrix4d upper_ = Eigen::Matrix4d::Zero();
};

/// Shared DLT solve over `n` views given as accessors; see the file comment.
template <typename PoseAt, typename PointAt>
bool triangulate_dlt(std::size_t n, PoseAt pose_at, PointAt point_at, Eigen::Vector3d& out) {
  if (n < 2) return false;
  const SE3d& T_c0_w = pose_at(0);
  // First camera centre: the local origin that keeps the homogeneous system well scaled.
  const Eigen::Vector3d c0_w = -(T_c0_w.linear().transpose() * T_c0_w.translation());
  IncrementalQr4 qr;
  for (std::size_t i = 0; i < n; ++i) {
    const SE3d& T_c_w = pose_at(i);
    const Eigen::Vector3d& x = point_at(i);
    Eigen::Matrix<double, 3, 4> P;
    P.leftCols<3>() = T_c_w.linear();
    P.col(3) = T_c_w.linear() * c0_w + T_c_w.translation();
    qr.add_row((x.x() * P.row(2) - P.row(0)).transpose());
    qr.add_row((x.y() * P.row(2) - P.row(1)).transpose());
  }
  const Eigen::JacobiSVD<Eigen::Matrix4d> svd(qr.r(), Eigen::ComputeFullV);
  const Eigen::Vector4d Xh = svd.matrixV().col(3);
  if (!(std::abs(Xh(3)) > kMinHomogeneousScale)) return false;  // also rejects NaN
  const Eigen::Vector3d X = c0_w + Xh.head<3>() / Xh(3);
  for (std::size_t i = 0; i < n; ++i) {
    const SE3d& T_c_w = pose_at(i);
    const double depth = T_c_w.linear().row(2).dot(X) + T_c_w.translation().z();
    if (!(depth > 0.0)) return false;
  }
  out = X;
  return true;
}

}  // namespace

bool triangulate_two_view(const SE3d& T_c0_w, const SE3d& T_c1_w, const Eigen::Vector3d& x0,
                          const Eigen::Vector3d& x1, Eigen::Vector3d& X_w) {
  const std::array<const SE3d*, 2> poses{&T_c0_w, &T_c1_w};
  const std::array<const Eigen::Vector3d*, 2> points{&x0, &x1};
  return triangulate_dlt(
      2, [&](std::size_t i) -> const SE3d& { return *poses[i]; },
      [&](std::size_t i) -> const Eigen::Vector3d& { return *points[i]; }, X_w);
}

bool triangulate_multi_view(std::span<const SE3d> T_c_w, std::span<const Eigen::Vector3d> x_norm,
                            Eigen::Vector3d& X_w) {
  if (T_c_w.size() != x_norm.size()) return false;
  return triangulate_dlt(
      T_c_w.size(), [&](std::size_t i) -> const SE3d& { return T_c_w[i]; },
      [&](std::size_t i) -> const Eigen::Vector3d& { return x_norm[i]; }, X_w);
}

double parallax_deg(const Eigen::Vector3d& X_w, const Eigen::Vector3d& c0_w,
                    const Eigen::Vector3d& c1_w) {
  const Eigen::Vector3d r0 = X_w - c0_w;
  const Eigen::Vector3d r1 = X_w - c1_w;
  // atan2(|a x b|, a . b) stays accurate for the tiny angles that matter here (acos does not).
  const double angle = std::atan2(r0.cross(r1).norm(), r0.dot(r1));
  return angle * kRadToDeg;
}

}  // namespace mer::geometry
