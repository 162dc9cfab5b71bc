#include "geometry/window_ba.h"

#include <cmath>
#include <numbers>
#include <random>
#include <vector>

#include <Eigen/Geometry>
#include <gtest/gtest.h>

#include "geometry/lie.h"

namespace mer::geometry {
namespace {

constexpr double kF = 500.0;
constexpr double kDeg = std::numbers::pi / 180.0;
constexpr int kViews = 6;  // besides the reference

Pinhole camera() {
  return {kF, kF, 320.0, 240.0};
}

// A wall 2.5 m ahead with boxes in front of it, seen from the reference camera (world frame).
std::vector<Eigen::Vector3d> scene(std::mt19937& rng) {
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  std::vector<Eigen::Vector3d> pts;
  for (int i = 0; i < 200; ++i) pts.emplace_back(1.2 * u(rng), 0.9 * u(rng), 2.5);
  for (int i = 0; i < 80; ++i) pts.emplace_back(0.8 * u(rng), 0.6 * u(rng), 1.6 + 0.3 * u(rng));
  return pts;
}

// Views along a curve: sideways and forward, turning slowly (camera from reference).
SE3d true_view(int k) {
  const double s = static_cast<double>(k + 1) / kViews;
  SE3d T_w_c = SE3d::Identity();
  T_w_c.linear() = Eigen::AngleAxisd(4.0 * s * kDeg, Eigen::Vector3d(0.1, 1.0, 0.2).normalized())
                       .toRotationMatrix();
  T_w_c.translation() = Eigen::Vector3d(0.12 * s, 0.02 * s * s, 0.05 * s * s);
  return T_w_c.inverse();
}

struct Rig {
  WindowBundleAdjuster ba;
  std::vector<Eigen::Vector3d> pts;
  std::vector<SE3d> truth;  // scaled so the scale view (the last) has a unit translation
  double scale = 1.0;       // truth units -> window units
};

// Sets up the window from the truth with pixel noise `noise_px`; views and points start at
// the truth or, perturbed, away from it.
void build(Rig& rig, double noise_px, bool perturb_views, bool perturb_points, std::uint32_t seed) {
  std::mt19937 rng(seed);
  rig.pts = scene(rng);
  std::normal_distribution<double> n(0.0, 1.0);
  const Pinhole K = camera();
  rig.ba.reserve(kViews, static_cast<int>(rig.pts.size()));
  rig.ba.reset(K, 5.991);
  rig.truth.clear();
  for (int k = 0; k < kViews; ++k) rig.truth.push_back(true_view(k));
  rig.scale = 1.0 / rig.truth.back().translation().norm();
  for (auto& T : rig.truth) T.translation() *= rig.scale;
  for (const Eigen::Vector3d& X : rig.pts) {
    const Eigen::Vector2d uv = K.project(X);
    const double rho = perturb_points ? 1.0 / (2.2 * rig.scale) : 1.0 / (X.z() * rig.scale);
    rig.ba.add_point(uv, rho, 1.0);
  }
  for (int k = 0; k < kViews; ++k) {
    SE3d T = rig.truth[static_cast<std::size_t>(k)];
    if (perturb_views) {
      T.linear() = so3_exp(Eigen::Vector3d(0.01, -0.015, 0.008)) * T.linear();
      T.translation() += 0.2 * Eigen::Vector3d(0.3, -0.2, 0.4) * T.translation().norm();
    }
    rig.ba.add_view(T);
  }
  rig.ba.set_scale_view(kViews - 1);
  std::mt19937 noise_rng(seed + 1000);
  for (int k = 0; k < kViews; ++k) {
    const SE3d T = true_view(k);
    for (std::size_t i = 0; i < rig.pts.size(); ++i) {
      const Eigen::Vector2d uv =
          K.project(T * rig.pts[i]) + noise_px * Eigen::Vector2d(n(noise_rng), n(noise_rng));
      rig.ba.observe(k, static_cast<int>(i), uv);
    }
  }
}

double direction_error_deg(const Eigen::Vector3d& a, const Eigen::Vector3d& b) {
  return std::acos(std::clamp(a.normalized().dot(b.normalized()), -1.0, 1.0)) / kDeg;
}

TEST(WindowBa, JacobiansMatchNumericOnes) {
  const Pinhole K = camera();
  const Eigen::Matrix3d R = so3_exp(Eigen::Vector3d(0.05, -0.1, 0.03));
  const Eigen::Vector3d t(0.3, -0.1, 0.2);
  const Eigen::Vector3d f = K.unproject({250.0, 300.0});
  const double rho = 0.4;
  const Eigen::Vector2d uv(260.0, 310.0);
  Eigen::Vector2d r;
  Eigen::Matrix<double, 2, 6> J;
  Eigen::Vector2d Jr;
  ASSERT_TRUE(window_ba_residual(K, R, t, f, rho, uv, 0.5, r, &J, &Jr));
  constexpr double kH = 1e-7;
  for (int k = 0; k < 6; ++k) {
    Eigen::Matrix<double, 6, 1> d = Eigen::Matrix<double, 6, 1>::Zero();
    d(k) = kH;
    Eigen::Vector2d rp;
    Eigen::Vector2d rm;
    ASSERT_TRUE(window_ba_residual(K, so3_exp(d.head<3>()) * R, t + d.tail<3>(), f, rho, uv, 0.5,
                                   rp, nullptr, nullptr));
    ASSERT_TRUE(window_ba_residual(K, so3_exp(-d.head<3>()) * R, t - d.tail<3>(), f, rho, uv, 0.5,
                                   rm, nullptr, nullptr));
    const Eigen::Vector2d numeric = (rp - rm) / (2.0 * kH);
    EXPECT_NEAR((numeric - J.col(k)).norm(), 0.0, 1e-4 * (1.0 + numeric.norm())) << "column " << k;
  }
  Eigen::Vector2d rp;
  Eigen::Vector2d rm;
  ASSERT_TRUE(window_ba_residual(K, R, t, f, rho + kH, uv, 0.5, rp, nullptr, nullptr));
  ASSERT_TRUE(window_ba_residual(K, R, t, f, rho - kH, uv, 0.5, rm, nullptr, nullptr));
  EXPECT_NEAR(((rp - rm) / (2.0 * kH) - Jr).norm(), 0.0, 1e-4 * (1.0 + Jr.norm()));
  // Behind the camera: refused.
  EXPECT_FALSE(window_ba_residual(K, Eigen::Matrix3d::Identity(), Eigen::Vector3d(0, 0, -5.0), f,
                                  1.0, uv, 1.0, r, nullptr, nullptr));
}

TEST(WindowBa, RecoversViewsAndDepthsFromAPerturbedStart) {
  Rig rig;
  build(rig, 0.5, true, true, 7);
  const double before = rig.ba.cost();
  const WindowBaSummary s = rig.ba.solve(30, false);
  EXPECT_LT(s.final_cost, 0.05 * before);
  EXPECT_EQ(s.behind, 0);
  // About chi2 with 2 per observation minus the parameters: 0.25 x that at 0.5 px noise.
  const double dof = 2.0 * kViews * static_cast<double>(rig.pts.size());
  EXPECT_LT(s.final_cost, 0.25 * dof * 1.3);
  for (int k = 0; k < kViews; ++k) {
    const SE3d& T = rig.ba.pose(k);
    const SE3d& G = rig.truth[static_cast<std::size_t>(k)];
    EXPECT_LT(rotation_angle(T.linear(), G.linear()) / kDeg, 0.05) << "view " << k;
    EXPECT_LT((T.translation() - G.translation()).norm(), 0.02) << "view " << k;
  }
  EXPECT_NEAR(rig.ba.pose(kViews - 1).translation().norm(), 1.0, 1e-9);
  double worst = 0.0;
  for (std::size_t i = 0; i < rig.pts.size(); ++i) {
    const double z = 1.0 / rig.ba.inv_depth(static_cast<int>(i));
    worst = std::max(worst, std::abs(z / (rig.pts[i].z() * rig.scale) - 1.0));
  }
  EXPECT_LT(worst, 0.1);
}

TEST(WindowBa, ViewsAloneMoveWhenThePointsAreFixed) {
  Rig rig;
  build(rig, 0.0, true, false, 3);
  WindowBundleAdjuster& ba = rig.ba;
  const double rho0 = ba.inv_depth(5);
  const WindowBaSummary s = ba.solve(10, true);
  EXPECT_GT(s.initial_cost, 1000.0);
  EXPECT_EQ(ba.inv_depth(5), rho0);
  EXPECT_LT(s.final_cost, 1e-6);
  for (int k = 0; k < kViews; ++k) {
    EXPECT_LT(rotation_angle(ba.pose(k).linear(), rig.truth[static_cast<std::size_t>(k)].linear()),
              1e-6);
  }
}

TEST(WindowBa, SigmaOfTheTranslationDirectionMatchesItsSpreadOverNoiseDraws) {
  constexpr int kDraws = 40;
  constexpr double kNoisePx = 1.0;
  double sum_sq = 0.0;
  double predicted = 0.0;
  for (int d = 0; d < kDraws; ++d) {
    Rig rig;
    build(rig, kNoisePx, false, false, 100 + static_cast<std::uint32_t>(d));
    rig.ba.solve(20, false);
    const double e =
        direction_error_deg(rig.ba.pose(kViews - 1).translation(), rig.truth.back().translation());
    sum_sq += e * e;
    const WindowBaSigma sg = rig.ba.sigma(kViews - 1);
    ASSERT_TRUE(sg.ok);
    predicted += sg.translation_dir_deg / kDraws;
  }
  // The largest sigma bounds a 2D error: its RMS over draws is at most sqrt(2) x it, and at
  // least the largest axis's spread alone (about 1 x it when one axis dominates).
  const double rms = std::sqrt(sum_sq / kDraws);
  RecordProperty("rms_deg", std::to_string(rms));
  RecordProperty("predicted_deg", std::to_string(predicted));
  EXPECT_GT(predicted, 0.0);
  EXPECT_GT(rms, 0.5 * predicted);
  EXPECT_LT(rms, 2.0 * predicted);
}

TEST(WindowBa, APointBehindAViewCostsTheBehindPenalty) {
  WindowBundleAdjuster ba;
  ba.reserve(1, 1);
  ba.reset(camera(), 5.991);
  ba.add_point({320.0, 240.0}, 1.0, 1.0);
  SE3d T = SE3d::Identity();
  T.translation() = Eigen::Vector3d(0.0, 0.0, -3.0);  // the point at z = 1 is behind
  ba.add_view(T);
  ba.observe(0, 0, {320.0, 240.0});
  EXPECT_EQ(ba.chi2(0, 0), kWindowBaBehindChi2);
  const double k = std::sqrt(5.991);
  EXPECT_NEAR(ba.cost(), 2.0 * k * std::sqrt(kWindowBaBehindChi2) - 5.991, 1e-9);
}

}  // namespace
}  // namespace mer::geometry
