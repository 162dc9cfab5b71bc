// The inverse-depth filter against synthetic truth: its measurement sigma against a numeric
// re-triangulation, convergence through wrong matches, and what a stream of wrong matches
// alone does to a seed.
#include "geometry/depth_filter.h"

#include <cmath>
#include <numbers>

#include <Eigen/Geometry>
#include <gtest/gtest.h>

#include "geometry/random.h"

namespace mer::geometry {
namespace {

double gaussian(Rng& rng) {  // Box-Muller on the project's generator (portable sequence)
  const double u1 = std::max(rng.uniform01(), 1e-300);
  const double u2 = rng.uniform01();
  return std::sqrt(-2.0 * std::log(u1)) * std::cos(2.0 * std::numbers::pi * u2);
}

// Inverse depth (z) where the reference ray f meets the second camera's ray (centre t,
// bearing b), by least squares on the two rays.
double intersect_inverse_depth(const Eigen::Vector3d& f, const Eigen::Vector3d& t,
                               const Eigen::Vector3d& b) {
  Eigen::Matrix<double, 3, 2> A;
  A.col(0) = f;
  A.col(1) = -b;
  const Eigen::Vector2d s = A.colPivHouseholderQr().solve(t);
  return 1.0 / (s(0) * f.z());
}

TEST(DepthFilter, MeasurementSigmaMatchesARetriangulationOnePixelOff) {
  const double pixel_angle = 1.0 / 500.0;  // 1 px at a 500 px focal length
  struct Case {
    Eigen::Vector3d f;
    double depth;
    Eigen::Vector3d t;
  };
  const Case cases[] = {
      {Eigen::Vector3d(0.1, -0.05, 1.0), 3.0, Eigen::Vector3d(0.2, 0.0, 0.0)},   // sideways
      {Eigen::Vector3d(-0.3, 0.2, 1.0), 2.0, Eigen::Vector3d(0.05, 0.02, 0.3)},  // forward
      {Eigen::Vector3d(0.0, 0.4, 1.0), 10.0, Eigen::Vector3d(0.0, -0.1, 0.02)},  // far, short
  };
  for (const Case& c : cases) {
    const Eigen::Vector3d f = c.f.normalized();
    const Eigen::Vector3d p = f * (c.depth / f.z());
    const Eigen::Vector3d b = (p - c.t).normalized();
    const Eigen::Vector3d axis = c.t.cross(f).normalized();  // normal of the epipolar plane
    const double rho_plus =
        intersect_inverse_depth(f, c.t, Eigen::AngleAxisd(pixel_angle, axis) * b);
    const double rho_minus =
        intersect_inverse_depth(f, c.t, Eigen::AngleAxisd(-pixel_angle, axis) * b);
    const double numeric = 0.5 * std::abs(rho_plus - rho_minus);
    const double sigma = inverse_depth_sigma(f, c.depth, c.t, pixel_angle);
    EXPECT_GT(sigma, 0.0);
    EXPECT_NEAR(sigma, numeric, 1e-9 + 1e-6 * numeric) << "depth " << c.depth;
    // The numeric method itself: the unperturbed rays meet at the point.
    EXPECT_NEAR(intersect_inverse_depth(f, c.t, b), 1.0 / c.depth, 1e-9);
  }
}

TEST(DepthFilter, NoBaselineGivesNoMeasurement) {
  const Eigen::Vector3d f(0.1, 0.2, 1.0);
  EXPECT_EQ(inverse_depth_sigma(f, 2.0, Eigen::Vector3d::Zero(), 0.002), 0.0);
  // The second centre on the reference ray: its ray runs along the baseline.
  EXPECT_EQ(inverse_depth_sigma(f, 2.0, f.normalized() * 0.5, 0.002), 0.0);
}

TEST(DepthFilter, ConvergesOnTheTruthThroughWrongMatches) {
  // Depth 2 m in a scene no nearer than 0.5 m; the seed starts at the scene's median depth
  // (4 m); 30 % of the measurements are wrong matches anywhere along the epipolar segment.
  Rng rng(7);
  const double rho_true = 0.5;
  const double tau = 0.01;
  DepthSeed seed = make_depth_seed(4.0, 0.5);
  EXPECT_FALSE(depth_seed_converged(seed, 200.0));
  int good = 0;
  for (int i = 0; i < 60; ++i) {
    double rho = 0.0;
    if (rng.uniform01() < 0.3) {
      rho = rng.uniform01() * seed.rho_max;
    } else {
      rho = rho_true + tau * gaussian(rng);
      ++good;
    }
    update_depth_seed(seed, rho, tau);
  }
  EXPECT_TRUE(depth_seed_converged(seed, 200.0)) << std::sqrt(seed.sigma2);
  // Within 4 sigma of the mean of the good measurements.
  EXPECT_NEAR(seed.mu, rho_true, 4.0 * tau / std::sqrt(static_cast<double>(good)));
  EXPECT_NEAR(seed.depth(), 2.0, 0.05);
  EXPECT_GT(seed.inlier_ratio(), 0.6);
}

TEST(DepthFilter, WrongMatchesAloneLowerTheInlierRatio) {
  Rng rng(11);
  DepthSeed seed = make_depth_seed(4.0, 0.5);
  for (int i = 0; i < 60; ++i) update_depth_seed(seed, rng.uniform01() * seed.rho_max, 0.01);
  EXPECT_LT(seed.inlier_ratio(), 0.3) << "a seed fed only wrong matches must say so";
}

TEST(DepthFilter, AFarPointConvergesNearZeroInverseDepth) {
  // 50 m in a scene no nearer than 0.5 m: inverse depth 0.02 of a range of 2.
  Rng rng(3);
  DepthSeed seed = make_depth_seed(3.0, 0.5);
  for (int i = 0; i < 40; ++i) update_depth_seed(seed, 0.02 + 0.005 * gaussian(rng), 0.005);
  EXPECT_NEAR(seed.mu, 0.02, 0.004);
  EXPECT_GT(seed.depth(), 35.0);
  EXPECT_TRUE(depth_seed_converged(seed, 200.0));
}

}  // namespace
}  // namespace mer::geometry
