// P3P minimal solver, plus the small helpers it relies on (lie.h, random.h).
#include "geometry/p3p.h"

#include <array>
#include <cmath>
#include <limits>
#include <random>

#include <gtest/gtest.h>

#include "geometry/lie.h"
#include "geometry/random.h"

namespace mer::geometry {
namespace {

constexpr double kRadToDeg = 180.0 / 3.141592653589793;

Eigen::Matrix3d random_rotation(std::mt19937_64& gen) {
  std::normal_distribution<double> n01(0.0, 1.0);
  return Eigen::Quaterniond(n01(gen), n01(gen), n01(gen), n01(gen)).normalized().toRotationMatrix();
}

SE3d random_pose(std::mt19937_64& gen, double max_translation) {
  std::uniform_real_distribution<double> u(-max_translation, max_translation);
  SE3d T = SE3d::Identity();
  T.linear() = random_rotation(gen);
  T.translation() = Eigen::Vector3d(u(gen), u(gen), u(gen));
  return T;
}

/// Three points in front of the camera T_c_w, inside a ~100 degree cone, depth 1..10.
void random_problem(std::mt19937_64& gen, const SE3d& T_c_w, std::array<Eigen::Vector3d, 3>& y,
                    std::array<Eigen::Vector3d, 3>& points_w) {
  std::uniform_real_distribution<double> depth(1.0, 10.0);
  std::uniform_real_distribution<double> slope(-1.2, 1.2);
  for (int i = 0; i < 3; ++i) {
    const double z = depth(gen);
    const Eigen::Vector3d p_c(slope(gen) * z, slope(gen) * z, z);
    y[i] = p_c.normalized();
    points_w[i] = T_c_w.inverse() * p_c;
  }
}

bool all_finite(const std::array<SE3d, kMaxP3pSolutions>& T, int n) {
  for (int k = 0; k < n; ++k) {
    if (!T[k].matrix().allFinite()) return false;
  }
  return true;
}

// ---- P3P -----------------------------------------------------------------------------------

TEST(P3p, NoiseFreeRandomProblemsRecoverTheTruePose) {
  std::mt19937_64 gen(42);
  constexpr int kTrials = 5000;
  constexpr double kTol = 1e-6;  // rotation (rad) and translation (relative to scene size)
  int matched = 0;
  int total_solutions = 0;
  double worst_rot = 0.0;
  double worst_trans = 0.0;
  for (int trial = 0; trial < kTrials; ++trial) {
    const SE3d T_c_w_true = random_pose(gen, 5.0);
    std::array<Eigen::Vector3d, 3> y;
    std::array<Eigen::Vector3d, 3> X;
    random_problem(gen, T_c_w_true, y, X);
    std::array<SE3d, kMaxP3pSolutions> sols;
    const int n = solve_p3p(y, X, sols);
    total_solutions += n;
    ASSERT_TRUE(all_finite(sols, n));
    double best_rot = std::numeric_limits<double>::infinity();
    double best_trans = std::numeric_limits<double>::infinity();
    for (int k = 0; k < n; ++k) {
      const double rot = rotation_angle(sols[k].linear(), T_c_w_true.linear());
      const double trans = (sols[k].translation() - T_c_w_true.translation()).norm() /
                           (1.0 + T_c_w_true.translation().norm());
      if (rot + trans < best_rot + best_trans) {
        best_rot = rot;
        best_trans = trans;
      }
      // Every solution explains the three bearings exactly.
      for (int i = 0; i < 3; ++i) {
        EXPECT_GT((sols[k] * X[i]).normalized().dot(y[i]), 1.0 - 1e-9) << "trial " << trial;
      }
    }
    if (best_rot < kTol && best_trans < kTol) ++matched;
    if (n > 0) {
      worst_rot = std::max(worst_rot, best_rot);
      worst_trans = std::max(worst_trans, best_trans);
    }
  }
  // Random triangles include a few nearly degenerate ones (world points almost collinear,
  // camera almost on the danger cylinder): allow 0.1 % of them to be less accurate.
  EXPECT_GE(matched, kTrials - kTrials / 1000);
  std::printf("P3P: %d / %d matched to 1e-6, %.2f solutions per problem\n", matched, kTrials,
              static_cast<double>(total_solutions) / kTrials);
}

TEST(P3p, TypicalProblemsAreAccurateFarFromTheOrigin) {
  // Large world coordinates (a map far from its origin) must not cost precision.
  std::mt19937_64 gen(7);
  for (int trial = 0; trial < 500; ++trial) {
    SE3d T_c_w_true = random_pose(gen, 1.0);
    T_c_w_true.translation() += Eigen::Vector3d(1000.0, -2000.0, 500.0);
    std::array<Eigen::Vector3d, 3> y;
    std::array<Eigen::Vector3d, 3> X;
    random_problem(gen, T_c_w_true, y, X);
    std::array<SE3d, kMaxP3pSolutions> sols;
    const int n = solve_p3p(y, X, sols);
    bool found = false;
    for (int k = 0; k < n; ++k) {
      const SE3d T_w_c = sols[k].inverse();
      const SE3d T_w_c_true = T_c_w_true.inverse();
      found |= rotation_angle(sols[k].linear(), T_c_w_true.linear()) < 1e-6 &&
               (T_w_c.translation() - T_w_c_true.translation()).norm() < 1e-5;
    }
    EXPECT_TRUE(found) << "trial " << trial;
  }
}

TEST(P3p, CollinearWorldPointsReturnNoSolution) {
  std::array<Eigen::Vector3d, 3> X = {Eigen::Vector3d(0, 0, 5), Eigen::Vector3d(1, 1, 6),
                                      Eigen::Vector3d(2, 2, 7)};
  std::array<Eigen::Vector3d, 3> y;
  for (int i = 0; i < 3; ++i) y[i] = X[i].normalized();
  std::array<SE3d, kMaxP3pSolutions> sols;
  EXPECT_EQ(solve_p3p(y, X, sols), 0);
  // Coincident world points.
  X[2] = X[1];
  EXPECT_EQ(solve_p3p(y, X, sols), 0);
}

TEST(P3p, NearDegenerateAndInvalidInputNeverProducesNaN) {
  std::mt19937_64 gen(3);
  std::normal_distribution<double> n01(0.0, 1.0);
  std::array<SE3d, kMaxP3pSolutions> sols;
  for (int trial = 0; trial < 2000; ++trial) {
    // Almost collinear world points (offsets from 1e-3 down to 1e-12).
    const double eps = std::pow(10.0, -3.0 - 9.0 * (trial % 10) / 9.0);
    const Eigen::Vector3d a(n01(gen), n01(gen), 5.0 + n01(gen));
    const Eigen::Vector3d d(n01(gen), n01(gen), n01(gen));
    std::array<Eigen::Vector3d, 3> X = {a, a + d, a + 2.0 * d + eps * Eigen::Vector3d::Random()};
    std::array<Eigen::Vector3d, 3> y;
    for (int i = 0; i < 3; ++i) y[i] = X[i].normalized();
    int n = solve_p3p(y, X, sols);
    EXPECT_TRUE(all_finite(sols, n)) << "near-collinear trial " << trial;
    // Inconsistent data: random bearings for random points.
    for (int i = 0; i < 3; ++i) {
      y[i] = Eigen::Vector3d(n01(gen), n01(gen), n01(gen)).normalized();
      X[i] = Eigen::Vector3d(n01(gen), n01(gen), n01(gen));
    }
    n = solve_p3p(y, X, sols);
    EXPECT_TRUE(all_finite(sols, n)) << "random trial " << trial;
    // Two identical bearings.
    y[1] = y[0];
    EXPECT_EQ(solve_p3p(y, X, sols), 0);
    // Coplanar bearings (camera centre in the plane of the three points).
    const Eigen::Vector3d c(0.0, 0.0, 0.0);
    X = {Eigen::Vector3d(1, 0, 3), Eigen::Vector3d(-1, 0, 4), Eigen::Vector3d(0.5, 0, 8)};
    for (int i = 0; i < 3; ++i) y[i] = (X[i] - c).normalized();
    n = solve_p3p(y, X, sols);
    EXPECT_TRUE(all_finite(sols, n));
  }
  // Non-finite and zero inputs.
  std::array<Eigen::Vector3d, 3> X = {Eigen::Vector3d(0, 0, 5), Eigen::Vector3d(1, 0, 5),
                                      Eigen::Vector3d(0, 1, 5)};
  std::array<Eigen::Vector3d, 3> y;
  for (int i = 0; i < 3; ++i) y[i] = X[i].normalized();
  y[2].x() = std::numeric_limits<double>::quiet_NaN();
  EXPECT_EQ(solve_p3p(y, X, sols), 0);
  y[2] = Eigen::Vector3d::Zero();
  EXPECT_EQ(solve_p3p(y, X, sols), 0);
  y[2] = X[2].normalized();
  X[0].z() = std::numeric_limits<double>::infinity();
  EXPECT_EQ(solve_p3p(y, X, sols), 0);
}

TEST(P3p, NonUnitBearingsAreNormalised) {
  std::mt19937_64 gen(11);
  const SE3d T_c_w_true = random_pose(gen, 2.0);
  std::array<Eigen::Vector3d, 3> y;
  std::array<Eigen::Vector3d, 3> X;
  random_problem(gen, T_c_w_true, y, X);
  for (int i = 0; i < 3; ++i) y[i] *= 3.0 + i;
  std::array<SE3d, kMaxP3pSolutions> sols;
  const int n = solve_p3p(y, X, sols);
  bool found = false;
  for (int k = 0; k < n; ++k) {
    found |= rotation_angle(sols[k].linear(), T_c_w_true.linear()) < 1e-6;
  }
  EXPECT_TRUE(found);
}

// ---- lie.h -----------------------------------------------------------------------------

TEST(Lie, HatVeeAndExpLogRoundTrip) {
  std::mt19937_64 gen(5);
  std::normal_distribution<double> n01(0.0, 1.0);
  for (int trial = 0; trial < 1000; ++trial) {
    // Angles from 1e-10 to ~3 rad.
    const double scale = std::pow(10.0, -10.0 + 10.5 * (trial % 100) / 99.0);
    Eigen::Vector3d w(n01(gen), n01(gen), n01(gen));
    w = w.normalized() * std::min(scale, 3.1);
    EXPECT_TRUE(vee(hat(w)).isApprox(w));
    EXPECT_NEAR((hat(w) * Eigen::Vector3d(1, 2, 3) - w.cross(Eigen::Vector3d(1, 2, 3))).norm(), 0.0,
                1e-15);
    const Eigen::Matrix3d R = so3_exp(w);
    EXPECT_NEAR((R.transpose() * R - Eigen::Matrix3d::Identity()).norm(), 0.0, 1e-14);
    EXPECT_NEAR(R.determinant(), 1.0, 1e-14);
    EXPECT_NEAR((so3_log(R) - w).norm(), 0.0, 1e-12 * std::max(1.0, w.norm()));
    // Agrees with Eigen's angle-axis.
    if (w.norm() > 0.0) {
      const Eigen::Matrix3d R2 = Eigen::AngleAxisd(w.norm(), w.normalized()).toRotationMatrix();
      EXPECT_NEAR((R - R2).norm(), 0.0, 1e-14);
    }
    Vector6d xi;
    xi << w, n01(gen), n01(gen), n01(gen);
    const SE3d T = se3_exp(xi);
    EXPECT_NEAR((se3_log(T) - xi).norm(), 0.0, 1e-10 * std::max(1.0, xi.norm()));
  }
  EXPECT_TRUE(so3_exp(Eigen::Vector3d::Zero()).isIdentity());
  EXPECT_TRUE(so3_log(Eigen::Matrix3d::Identity()).isZero());
}

TEST(Lie, LogNearPiIsAccurate) {
  for (const double delta : {0.0, 1e-12, 1e-9, 1e-7, 1e-5, 1e-3}) {
    const Eigen::Vector3d axis = Eigen::Vector3d(1.0, -2.0, 0.5).normalized();
    const Eigen::Vector3d w = (3.141592653589793 - delta) * axis;
    const Eigen::Vector3d w_back = so3_log(so3_exp(w));
    // At exactly pi, axis and -axis are the same rotation.
    const double err = std::min((w_back - w).norm(), (w_back + w).norm());
    EXPECT_LT(err, 1e-8) << "delta " << delta;
    EXPECT_NEAR((so3_exp(w_back) - so3_exp(w)).norm(), 0.0, 1e-10) << "delta " << delta;
  }
}

TEST(Lie, Se3ExpFirstOrderIsLeftPerturbation) {
  // exp(xi) * p ~ p + omega x p + v for small xi: the convention pnp.h documents.
  Vector6d xi;
  xi << 1e-7, -2e-7, 3e-7, 4e-7, 5e-7, -6e-7;
  const Eigen::Vector3d p(1.0, 2.0, 3.0);
  const Eigen::Vector3d expected = p + xi.head<3>().cross(p) + xi.tail<3>();
  EXPECT_NEAR((se3_exp(xi) * p - expected).norm(), 0.0, 1e-12);
  EXPECT_NEAR(rotation_angle(so3_exp(Eigen::Vector3d(0.1, 0, 0)), Eigen::Matrix3d::Identity()), 0.1,
              1e-15);
  EXPECT_NEAR(kRadToDeg * 0.1, 5.729577951, 1e-8);
}

// ---- random.h --------------------------------------------------------------------------

TEST(Rng, DeterministicAndInRange) {
  Rng a(123);
  Rng b(123);
  Rng c(124);
  bool differs = false;
  for (int i = 0; i < 1000; ++i) {
    const auto x = a.next();
    EXPECT_EQ(x, b.next());
    differs |= x != c.next();
  }
  EXPECT_TRUE(differs);
  a.reseed(9);
  b.reseed(9);
  EXPECT_EQ(a.next(), b.next());

  // uniform_index: in range, roughly uniform.
  constexpr std::uint32_t kBins = 7;
  constexpr int kDraws = 70000;
  std::array<int, kBins> hist{};
  Rng r(1);
  for (int i = 0; i < kDraws; ++i) {
    const std::uint32_t k = r.uniform_index(kBins);
    ASSERT_LT(k, kBins);
    ++hist[k];
  }
  for (const int h : hist) EXPECT_NEAR(h, kDraws / kBins, 5 * 100);  // ~5 sigma (sigma ~ 93)
  for (int i = 0; i < 1000; ++i) {
    const double u = r.uniform01();
    EXPECT_GE(u, 0.0);
    EXPECT_LT(u, 1.0);
  }
  EXPECT_EQ(r.uniform_index(1), 0u);
}

}  // namespace
}  // namespace mer::geometry
