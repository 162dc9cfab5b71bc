// Sim(3): composition and inverse against point mapping, and the Umeyama fit recovering a
// known similarity (and a rigid one when the scale is fixed) from noisy correspondences.
#include "geometry/sim3.h"

#include <random>

#include <gtest/gtest.h>

#include "geometry/lie.h"

namespace mer::geometry {
namespace {

Sim3d make(const Eigen::Vector3d& w, const Eigen::Vector3d& t, double s) {
  return Sim3d{so3_exp(w), t, s};
}

TEST(Sim3, CompositionAndInverseMapPointsConsistently) {
  const Sim3d a = make({0.1, -0.2, 0.3}, {1.0, 2.0, -0.5}, 1.3);
  const Sim3d b = make({-0.3, 0.05, 0.2}, {-0.4, 0.1, 0.7}, 0.8);
  const Eigen::Vector3d p(0.3, -1.2, 2.5);
  EXPECT_LT(((a * b) * p - a * (b * p)).norm(), 1e-12);
  EXPECT_LT((a.inverse() * (a * p) - p).norm(), 1e-12);
  const Sim3d id = a * a.inverse();
  EXPECT_NEAR(id.s, 1.0, 1e-12);
  EXPECT_LT((id.R - Eigen::Matrix3d::Identity()).norm(), 1e-12);
  EXPECT_LT(id.t.norm(), 1e-12);
}

TEST(Sim3, AppliedToAPoseKeepsTheCameraRigidAndMovesItsCentre) {
  const Sim3d S = make({0.0, 0.0, 0.4}, {0.5, 0.0, 0.0}, 2.0);
  SE3d T = SE3d::Identity();
  T.linear() = so3_exp(Eigen::Vector3d(0.1, 0.2, 0.0));
  T.translation() = Eigen::Vector3d(1.0, 1.0, 0.0);
  const SE3d T2 = apply_to_pose(S, T);
  EXPECT_LT((T2.translation() - S * T.translation()).norm(), 1e-12);
  EXPECT_LT((T2.linear() - S.R * T.linear()).norm(), 1e-12);
  EXPECT_NEAR(T2.linear().determinant(), 1.0, 1e-12);
}

TEST(Sim3, UmeyamaRecoversAKnownSimilarityFromNoisyPoints) {
  const Sim3d truth = make({0.2, -0.1, 0.5}, {0.3, -0.7, 1.1}, 1.07);
  std::mt19937 rng(3);
  std::uniform_real_distribution<double> u(-2.0, 2.0);
  std::normal_distribution<double> noise(0.0, 1e-3);
  constexpr int kN = 200;
  Eigen::Matrix3Xd src(3, kN);
  Eigen::Matrix3Xd dst(3, kN);
  for (int i = 0; i < kN; ++i) {
    const Eigen::Vector3d p(u(rng), u(rng), 3.0 + u(rng));
    src.col(i) = p;
    dst.col(i) = truth * p + Eigen::Vector3d(noise(rng), noise(rng), noise(rng));
  }
  const Sim3d est = umeyama_sim3(src, dst, true);
  EXPECT_NEAR(est.s, truth.s, 1e-3);
  EXPECT_LT(so3_log(est.R.transpose() * truth.R).norm(), 1e-3);
  EXPECT_LT((est.t - truth.t).norm(), 5e-3);
  // Scale fixed: the rigid part of a scale-1 motion is found exactly as well.
  const Sim3d rigid = make({0.2, -0.1, 0.5}, {0.3, -0.7, 1.1}, 1.0);
  for (int i = 0; i < kN; ++i) dst.col(i) = rigid * src.col(i);
  const Sim3d r = umeyama_sim3(src, dst, false);
  EXPECT_DOUBLE_EQ(r.s, 1.0);
  EXPECT_LT(so3_log(r.R.transpose() * rigid.R).norm(), 1e-9);
  EXPECT_LT((r.t - rigid.t).norm(), 1e-9);
}

}  // namespace
}  // namespace mer::geometry
