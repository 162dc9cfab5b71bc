#include "geometry/sim3.h"

#include <algorithm>

#include <Eigen/SVD>

namespace mer::geometry {

Sim3d fit_similarity_to_poses(std::span<const SE3d> from, std::span<const SE3d> to,
                              bool with_scale) {
  Eigen::Matrix3d sum = Eigen::Matrix3d::Zero();
  Eigen::Vector3d p_mean = Eigen::Vector3d::Zero();
  Eigen::Vector3d q_mean = Eigen::Vector3d::Zero();
  const std::size_t n = std::min(from.size(), to.size());
  if (n == 0) return Sim3d{};
  for (std::size_t i = 0; i < n; ++i) {
    sum += to[i].linear() * from[i].linear().transpose();
    p_mean += from[i].translation();
    q_mean += to[i].translation();
  }
  p_mean /= static_cast<double>(n);
  q_mean /= static_cast<double>(n);
  const Eigen::JacobiSVD<Eigen::Matrix3d> svd(sum, Eigen::ComputeFullU | Eigen::ComputeFullV);
  Eigen::Matrix3d D = Eigen::Matrix3d::Identity();
  D(2, 2) = (svd.matrixU() * svd.matrixV().transpose()).determinant() < 0.0 ? -1.0 : 1.0;
  Sim3d S;
  S.R = svd.matrixU() * D * svd.matrixV().transpose();
  double num = 0.0;
  double den = 0.0;
  for (std::size_t i = 0; i < n; ++i) {
    const Eigen::Vector3d p = S.R * (from[i].translation() - p_mean);
    num += p.dot(to[i].translation() - q_mean);
    den += p.squaredNorm();
  }
  S.s = with_scale && den > 0.0 && num > 0.0 ? num / den : 1.0;
  S.t = q_mean - S.s * S.R * p_mean;
  return S;
}

}  // namespace mer::geometry
