#include "geometry/triangulation.h"

#include <array>
#include <cmath>
#include <numbers>
#include <random>
#include <vector>

#include <Eigen/Geometry>
#include <gtest/gtest.h>

#include "platform/alloc_counter.h"

namespace mer::geometry {
namespace {

constexpr double kF = 500.0;  // focal length used to express normalized noise in px

/// Camera-from-world pose of a camera at `centre` looking at `target`.
SE3d camera_at(const Eigen::Vector3d& centre, const Eigen::Vector3d& target) {
  return look_at(centre, target, Eigen::Vector3d(0, -1, 0)).inverse();
}

Eigen::Vector3d normalized_projection(const SE3d& T_c_w, const Eigen::Vector3d& p_w) {
  const Eigen::Vector3d p = T_c_w * p_w;
  return p / p.z();
}

/// `n` cameras on an arc of radius 4 m around `target` (spread `spread_m` along the arc),
/// all looking at `target`.
std::vector<SE3d> arc_cameras(int n, const Eigen::Vector3d& target, double spread_m) {
  std::vector<SE3d> T;
  for (int i = 0; i < n; ++i) {
    const double a = n == 1 ? 0.0 : spread_m / 4.0 * (i / (n - 1.0) - 0.5);
    const Eigen::Vector3d c = target + 4.0 * Eigen::Vector3d(std::sin(a), 0.1 * i, -std::cos(a));
    T.push_back(camera_at(c, target));
  }
  return T;
}

TEST(Triangulation, NoiseFreeIsExact) {
  std::mt19937_64 rng(1);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  // World far from the origin: the solver works relative to the first camera centre.
  const std::array<Eigen::Vector3d, 2> offsets{Eigen::Vector3d(0, 0, 0),
                                               Eigen::Vector3d(1e3, -2e3, 5e2)};
  for (const Eigen::Vector3d& offset : offsets) {
    const std::vector<SE3d> T = arc_cameras(6, offset, 1.5);
    for (int k = 0; k < 100; ++k) {
      const Eigen::Vector3d X = offset + Eigen::Vector3d(u(rng), u(rng), u(rng));
      std::vector<Eigen::Vector3d> x;
      for (const SE3d& T_c_w : T) x.push_back(normalized_projection(T_c_w, X));
      Eigen::Vector3d X2, Xn;
      ASSERT_TRUE(triangulate_two_view(T[0], T[1], x[0], x[1], X2));
      EXPECT_LT((X2 - X).norm(), 1e-8);
      ASSERT_TRUE(triangulate_multi_view(T, x, Xn));
      EXPECT_LT((Xn - X).norm(), 1e-8);
    }
  }
}

TEST(Triangulation, MultiViewBeatsTwoViewOnNoisyData) {
  std::mt19937_64 rng(2);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  std::normal_distribution<double> noise(0.0, 1.0 / kF);  // 1 px at f = 500
  const Eigen::Vector3d target(0, 0, 0);
  const std::vector<SE3d> T = arc_cameras(6, target, 1.0);
  double se_first = 0.0, se_wide = 0.0, se_multi = 0.0;
  constexpr int kPoints = 500;
  for (int k = 0; k < kPoints; ++k) {
    const Eigen::Vector3d X = target + Eigen::Vector3d(u(rng), u(rng), u(rng));
    std::vector<Eigen::Vector3d> x;
    for (const SE3d& T_c_w : T) {
      x.push_back(normalized_projection(T_c_w, X) + Eigen::Vector3d(noise(rng), noise(rng), 0.0));
    }
    Eigen::Vector3d p_first, p_wide, Xn;
    // The first pair (initialization keyframes, baseline 1/5 of the arc) and the widest pair.
    ASSERT_TRUE(triangulate_two_view(T[0], T[1], x[0], x[1], p_first));
    ASSERT_TRUE(triangulate_two_view(T.front(), T.back(), x.front(), x.back(), p_wide));
    ASSERT_TRUE(triangulate_multi_view(T, x, Xn));
    se_first += (p_first - X).squaredNorm();
    se_wide += (p_wide - X).squaredNorm();
    se_multi += (Xn - X).squaredNorm();
  }
  const double rms_first = std::sqrt(se_first / kPoints);
  const double rms_wide = std::sqrt(se_wide / kPoints);
  const double rms_multi = std::sqrt(se_multi / kPoints);
  std::printf(
      "[ triangulation ] RMS error, 1 px noise, 4 m range, 1 m arc: first pair %.1f mm, "
      "widest pair %.1f mm, all six views %.1f mm\n",
      1e3 * rms_first, 1e3 * rms_wide, 1e3 * rms_multi);
  // Depth precision grows with sum (b_i - mean b)^2 over the views: first pair (b/5 apart)
  // 0.02 b^2, widest pair 0.5 b^2, six evenly spaced views 0.7 b^2. Expected RMS ratios:
  // multi / first ~ 0.17 and multi / widest ~ 0.85 (lateral error also shrinks).
  EXPECT_LT(rms_multi, 0.3 * rms_first);
  EXPECT_LT(rms_multi, 0.95 * rms_wide);
  // Absolute level: depth error ~ sqrt(2) sigma Z^2 / (f b) = 1.4 * 16 / 500 m = 45 mm for the
  // widest pair (b = 1 m); RMS over all axes must stay below that.
  EXPECT_LT(rms_wide, 0.045);
}

TEST(Triangulation, PointBehindACameraIsRejected) {
  const SE3d T0 = camera_at({-0.5, 0, 0}, {-0.5, 0, 5});
  const SE3d T1 = camera_at({0.5, 0, 0}, {0.5, 0, 5});
  // In front of both: accepted.
  Eigen::Vector3d X;
  const Eigen::Vector3d front(0.1, 0.2, 3.0);
  EXPECT_TRUE(triangulate_two_view(T0, T1, normalized_projection(T0, front),
                                   normalized_projection(T1, front), X));
  // Behind both (normalized coordinates of a point at z < 0 are those of its mirror image, but
  // the DLT solution is the point behind): rejected.
  Eigen::Vector3d untouched(7, 7, 7);
  X = untouched;
  const Eigen::Vector3d behind(0.1, 0.2, -3.0);
  EXPECT_FALSE(triangulate_two_view(T0, T1, normalized_projection(T0, behind),
                                    normalized_projection(T1, behind), X));
  EXPECT_EQ(X, untouched);  // not written on failure
  // Behind the second camera only: camera 1 turned around.
  const SE3d T_back_w = camera_at({0.5, 0, 0}, {0.5, 0, -5});
  const Eigen::Vector3d x1_back = normalized_projection(T_back_w, front);  // z < 0 in camera 1
  EXPECT_LT((T_back_w * front).z(), 0.0);
  EXPECT_FALSE(triangulate_two_view(T0, T_back_w, normalized_projection(T0, front), x1_back, X));
  // Multi-view: one view of three behind -> rejected.
  const std::array<SE3d, 3> T{T0, T1, T_back_w};
  const std::array<Eigen::Vector3d, 3> x{normalized_projection(T0, front),
                                         normalized_projection(T1, front), x1_back};
  EXPECT_FALSE(triangulate_multi_view(T, x, X));
  EXPECT_TRUE(triangulate_multi_view(std::span(T).first(2), std::span(x).first(2), X));
  EXPECT_LT((X - front).norm(), 1e-9);
}

TEST(Triangulation, PointAtInfinityAndBadInputAreRejected) {
  // Same ray direction from two centres: parallel rays, the point is at infinity.
  const SE3d T0 = camera_at({0, 0, 0}, {0, 0, 5});
  const SE3d T1 = camera_at({1, 0, 0}, {1, 0, 5});
  const Eigen::Vector3d x(0.1, -0.05, 1.0);
  Eigen::Vector3d X;
  EXPECT_FALSE(triangulate_two_view(T0, T1, x, x, X));
  // Zero baseline: no depth.
  EXPECT_FALSE(triangulate_two_view(T0, T0, x, x, X));
  // Fewer than two views, mismatched spans.
  const std::array<SE3d, 2> T{T0, T1};
  const std::array<Eigen::Vector3d, 2> xs{x, x};
  EXPECT_FALSE(triangulate_multi_view(std::span(T).first(1), std::span(xs).first(1), X));
  EXPECT_FALSE(triangulate_multi_view(T, std::span(xs).first(1), X));
}

TEST(Triangulation, ManyViewsAndNoAllocation) {
  // Eigen's own heap path calls malloc, which the counter does not see; the implementation
  // uses fixed-size matrices only, so this guards the rest (no std::vector and the like).
  const Eigen::Vector3d target(0.3, -0.2, 0.1);
  const Eigen::Vector3d X = target + Eigen::Vector3d(0.2, 0.1, -0.3);
  for (const int n : {2, 8, 40}) {
    const std::vector<SE3d> T = arc_cameras(n, target, 2.0);
    std::vector<Eigen::Vector3d> x;
    for (const SE3d& T_c_w : T) x.push_back(normalized_projection(T_c_w, X));
    Eigen::Vector3d Xn;
    const std::uint64_t before = platform::alloc::thread_allocations();
    const bool ok = triangulate_multi_view(T, x, Xn);
    const std::uint64_t after = platform::alloc::thread_allocations();
    ASSERT_TRUE(ok) << n;
    EXPECT_LT((Xn - X).norm(), 1e-9) << n;
    EXPECT_EQ(after - before, 0u) << n;
  }
}

TEST(Triangulation, ParallaxAngle) {
  const double expected = 2.0 * std::atan(0.5) * 180.0 / std::numbers::pi;  // 53.13 deg
  EXPECT_NEAR(parallax_deg({0, 0, 1}, {-0.5, 0, 0}, {0.5, 0, 0}), expected, 1e-12);
  EXPECT_NEAR(parallax_deg({0, 0, 1e6}, {-0.5, 0, 0}, {0.5, 0, 0}), 5.7295779e-5, 1e-10);
  EXPECT_EQ(parallax_deg({1, 2, 3}, {0, 0, 0}, {0, 0, 0}), 0.0);
  EXPECT_NEAR(parallax_deg({0, 0, 0}, {0, 0, -1}, {0, 0, 1}), 180.0, 1e-12);
}

}  // namespace
}  // namespace mer::geometry
