// Robust PnP: accuracy under noise and outliers, per-observation sigma, Jacobians, focal
// estimation, allocation-free solves, determinism and failure handling.
#include "geometry/pnp.h"

#include <algorithm>
#include <cmath>
#include <random>
#include <sstream>
#include <vector>

#include <gtest/gtest.h>

#include "core/config_io.h"
#include "geometry/lie.h"
#include "platform/alloc_counter.h"

namespace mer::geometry {
namespace {

constexpr double kRadToDeg = 180.0 / 3.141592653589793;
constexpr double kWidth = 640.0;
constexpr double kHeight = 480.0;
const Pinhole kK{500.0, 500.0, 320.0, 240.0};

/// A synthetic PnP problem: points seen by a camera at T_c_w, noisy observations, a share
/// of gross outliers (uniform in the image, >= kMinOutlierErrorPx from the truth).
struct Scene {
  SE3d T_c_w;
  std::vector<Eigen::Vector3d> points_w;
  std::vector<Eigen::Vector2d> uv;
  std::vector<float> sigma;
  std::vector<std::uint8_t> is_inlier;  // ground truth
  Pinhole K;

  PnpInput input() const { return {points_w, uv, sigma, K}; }
  PnpInput input_with(const Pinhole& guess) const { return {points_w, uv, sigma, guess}; }
};

constexpr double kMinOutlierErrorPx = 15.0;
/// ORB-style pyramid: level scale 1.2^level, levels 0..3.
constexpr double kLevelScale = 1.2;
constexpr int kLevels = 4;

Scene make_scene(std::uint64_t seed, int n, double outlier_ratio, double noise_px,
                 bool use_sigma = true, const Pinhole& K = kK, double min_depth = 2.0,
                 double max_depth = 8.0) {
  std::mt19937_64 gen(seed);
  std::normal_distribution<double> n01(0.0, 1.0);
  std::uniform_real_distribution<double> u01(0.0, 1.0);
  Scene s;
  s.K = K;
  // Random camera pose: random orientation, centre within 5 m of the origin.
  const Eigen::Matrix3d R =
      Eigen::Quaterniond(n01(gen), n01(gen), n01(gen), n01(gen)).normalized().toRotationMatrix();
  const Eigen::Vector3d c(5.0 * n01(gen), 5.0 * n01(gen), 5.0 * n01(gen));
  SE3d T_w_c = SE3d::Identity();
  T_w_c.linear() = R;
  T_w_c.translation() = c;
  s.T_c_w = T_w_c.inverse();
  const int num_outliers = static_cast<int>(std::lround(outlier_ratio * n));
  for (int i = 0; i < n; ++i) {
    const Eigen::Vector2d px(u01(gen) * kWidth, u01(gen) * kHeight);
    const double z = min_depth + (max_depth - min_depth) * u01(gen);
    const Eigen::Vector3d p_c = K.unproject(px) * z;
    s.points_w.push_back(T_w_c * p_c);
    const int level = use_sigma ? static_cast<int>(u01(gen) * kLevels) : 0;
    const double sig = std::pow(kLevelScale, level);
    s.sigma.push_back(static_cast<float>(sig));
    const bool outlier = i < num_outliers;
    Eigen::Vector2d obs;
    if (outlier) {
      do {
        obs = Eigen::Vector2d(u01(gen) * kWidth, u01(gen) * kHeight);
      } while ((obs - px).norm() < kMinOutlierErrorPx);
    } else {
      obs = px + noise_px * sig * Eigen::Vector2d(n01(gen), n01(gen));
    }
    s.uv.push_back(obs);
    s.is_inlier.push_back(outlier ? 0 : 1);
  }
  if (!use_sigma) s.sigma.clear();
  // Shuffle so the outliers are not the first indices.
  std::vector<int> perm(n);
  for (int i = 0; i < n; ++i) perm[i] = i;
  std::shuffle(perm.begin(), perm.end(), gen);
  Scene t = s;
  for (int i = 0; i < n; ++i) {
    t.points_w[i] = s.points_w[perm[i]];
    t.uv[i] = s.uv[perm[i]];
    if (use_sigma) t.sigma[i] = s.sigma[perm[i]];
    t.is_inlier[i] = s.is_inlier[perm[i]];
  }
  return t;
}

double rotation_error_deg(const SE3d& a, const SE3d& b) {
  return kRadToDeg * rotation_angle(a.linear(), b.linear());
}

double position_error(const SE3d& T_c_w, const SE3d& T_c_w_true) {
  return (T_c_w.inverse().translation() - T_c_w_true.inverse().translation()).norm();
}

/// Cramer-Rao standard deviations (sqrt of the covariance trace) an efficient estimator
/// reaches on the true inliers, from the information matrix J^T W J at the true pose:
/// rotation (rad) and camera position. With the left perturbation T_c_w <- exp(xi) T_c_w
/// the camera centre moves by -R^T v and the camera rotates by omega, so the twist
/// covariance blocks are the centre / rotation covariances up to a rotation.
struct CramerRao {
  double rotation = 0.0;  ///< rad
  double position = 0.0;  ///< world units
};
CramerRao cramer_rao(const Scene& s, double noise_px) {
  Eigen::Matrix<double, 6, 6> H = Eigen::Matrix<double, 6, 6>::Zero();
  for (std::size_t i = 0; i < s.points_w.size(); ++i) {
    if (!s.is_inlier[i]) continue;
    Eigen::Matrix<double, 2, 6> J;
    reprojection_residual(s.T_c_w, s.points_w[i], s.uv[i], s.K, &J, nullptr);
    const double sig = noise_px * (s.sigma.empty() ? 1.0 : s.sigma[i]);
    H += J.transpose() * J / (sig * sig);
  }
  const Eigen::Matrix<double, 6, 6> cov = H.inverse();
  return {std::sqrt(cov.topLeftCorner<3, 3>().trace()),
          std::sqrt(cov.bottomRightCorner<3, 3>().trace())};
}

/// Fraction of entries where `mask` agrees with `reference`.
double agreement(const std::vector<std::uint8_t>& mask,
                 const std::vector<std::uint8_t>& reference) {
  int same = 0;
  for (std::size_t i = 0; i < mask.size(); ++i) same += (mask[i] != 0) == (reference[i] != 0);
  return static_cast<double>(same) / static_cast<double>(mask.size());
}

/// The mask a perfect estimator would return: the inlier test at the true pose. With
/// Gaussian noise of 1 px per axis, exp(-2.5^2 / 2) = 4.4 % of the true inliers lie beyond
/// the 2.5 px threshold, so the ground-truth labels themselves only "agree" ~95.6 %.
std::vector<std::uint8_t> oracle_mask(const Scene& s, double threshold_px) {
  std::vector<std::uint8_t> m(s.points_w.size());
  for (std::size_t i = 0; i < m.size(); ++i) {
    const double sig = s.sigma.empty() ? 1.0 : s.sigma[i];
    const Eigen::Vector2d r =
        reprojection_residual(s.T_c_w, s.points_w[i], s.uv[i], s.K, nullptr, nullptr);
    m[i] = (s.T_c_w * s.points_w[i]).z() > 0.0 && r.norm() < threshold_px * sig ? 1 : 0;
  }
  return m;
}

double mask_agreement(const std::vector<std::uint8_t>& mask, const Scene& s) {
  return agreement(mask, s.is_inlier);
}

/// Share of the gross outliers (ground truth) that the mask rejects.
double outlier_rejection(const std::vector<std::uint8_t>& mask, const Scene& s) {
  int outliers = 0;
  int rejected = 0;
  for (std::size_t i = 0; i < mask.size(); ++i) {
    if (s.is_inlier[i]) continue;
    ++outliers;
    rejected += mask[i] == 0 ? 1 : 0;
  }
  return outliers == 0 ? 1.0 : static_cast<double>(rejected) / outliers;
}

// ---- Accuracy under noise and outliers ---------------------------------------------------

/// Position bound: kPositionSigmas x the Cramer-Rao standard deviation of the centre (a
/// 3-dof Gaussian exceeds 5 sigma of its trace-norm with probability < 1e-4). For these
/// scenes (f = 500 px, 300 points at 2..8 m, 1 px noise) that is ~1-2 cm. The rotation
/// bound is the task's 0.2 deg (~10-20 CR sigmas here); the CR ratio is printed as well.
constexpr double kPositionSigmas = 5.0;
constexpr double kRotationLimitDeg = 0.2;
constexpr double kMinMaskAgreement = 0.95;

void check_accuracy(double outlier_ratio, bool use_sigma) {
  constexpr int kN = 300;
  constexpr double kNoisePx = 1.0;
  constexpr int kScenes = 20;
  const PnpOptions opts;
  PnpRansac pnp(opts, kN);
  std::vector<std::uint8_t> mask(kN);
  double worst_rot = 0.0;
  double worst_rot_cr = 0.0;
  double worst_pos = 0.0;
  double worst_pos_cr = 0.0;
  double worst_oracle = 1.0;
  double worst_labels = 1.0;
  int total_iters = 0;
  for (int k = 0; k < kScenes; ++k) {
    const Scene s = make_scene(1000 + k, kN, outlier_ratio, kNoisePx, use_sigma);
    const PnpResult r = pnp.solve(s.input(), mask);
    ASSERT_TRUE(r.ok) << "scene " << k;
    const CramerRao cr = cramer_rao(s, kNoisePx);
    const double rot = rotation_error_deg(r.T_c_w, s.T_c_w);
    const double pos = position_error(r.T_c_w, s.T_c_w);
    const double oracle = agreement(mask, oracle_mask(s, opts.inlier_threshold_px));
    const double labels = mask_agreement(mask, s);
    EXPECT_LT(rot, kRotationLimitDeg) << "scene " << k;
    EXPECT_LT(pos, kPositionSigmas * cr.position) << "scene " << k;
    EXPECT_GE(oracle, kMinMaskAgreement) << "scene " << k;
    EXPECT_EQ(outlier_rejection(mask, s), 1.0) << "scene " << k;
    // Labels: 4.4 % of the true inliers are beyond the threshold (see oracle_mask).
    EXPECT_GE(labels, kMinMaskAgreement - 0.03) << "scene " << k;
    EXPECT_LT(r.rms_px, 2.0 * kNoisePx);
    worst_rot = std::max(worst_rot, rot);
    worst_rot_cr = std::max(worst_rot_cr, rot / (kRadToDeg * cr.rotation));
    worst_pos = std::max(worst_pos, pos);
    worst_pos_cr = std::max(worst_pos_cr, pos / cr.position);
    worst_oracle = std::min(worst_oracle, oracle);
    worst_labels = std::min(worst_labels, labels);
    total_iters += r.iterations;
  }
  std::printf(
      "outliers %.0f%% sigma %d: worst rot %.4f deg (%.2f CR sigma), worst pos %.4f m "
      "(%.2f CR sigma), worst mask agreement: oracle %.3f labels %.3f, mean iterations %.1f\n",
      100.0 * outlier_ratio, use_sigma ? 1 : 0, worst_rot, worst_rot_cr, worst_pos, worst_pos_cr,
      worst_oracle, worst_labels, static_cast<double>(total_iters) / kScenes);
}

TEST(PnpRansac, NoOutliers) {
  check_accuracy(0.0, true);
}
TEST(PnpRansac, ThirtyPercentOutliers) {
  check_accuracy(0.3, true);
}
TEST(PnpRansac, FiftyPercentOutliers) {
  check_accuracy(0.5, true);
}
TEST(PnpRansac, ThirtyPercentOutliersUnitSigma) {
  check_accuracy(0.3, false);
}

TEST(PnpRansac, NoiseFreeIsExact) {
  const Scene s = make_scene(77, 100, 0.3, 0.0);
  PnpRansac pnp(PnpOptions{}, 100);
  std::vector<std::uint8_t> mask(100);
  const PnpResult r = pnp.solve(s.input(), mask);
  ASSERT_TRUE(r.ok);
  EXPECT_LT(rotation_error_deg(r.T_c_w, s.T_c_w), 1e-7);
  EXPECT_LT(position_error(r.T_c_w, s.T_c_w), 1e-8);
  EXPECT_EQ(mask_agreement(mask, s), 1.0);
  EXPECT_EQ(r.num_inliers, 70);
}

TEST(PnpRansac, SigmaScalesTheInlierThreshold) {
  // Exact observations plus 40 perturbed by 3.5 px: with sigma 2 they are within
  // 2.5 px * sigma (inliers); with sigma 1 they are not.
  Scene s = make_scene(5, 200, 0.0, 0.0, /*use_sigma=*/false);
  s.sigma.assign(200, 1.0F);
  for (int i = 0; i < 40; ++i) s.uv[i] += Eigen::Vector2d(3.5, 0.0);
  PnpRansac pnp(PnpOptions{}, 200);
  std::vector<std::uint8_t> mask(200);
  PnpResult r = pnp.solve(s.input(), mask);
  ASSERT_TRUE(r.ok);
  EXPECT_EQ(r.num_inliers, 160);
  for (int i = 0; i < 40; ++i) EXPECT_EQ(mask[i], 0) << i;
  for (int i = 0; i < 40; ++i) s.sigma[i] = 2.0F;
  r = pnp.solve(s.input(), mask);
  ASSERT_TRUE(r.ok);
  EXPECT_EQ(r.num_inliers, 200);
}

TEST(PnpRansac, PointsBehindTheCameraAreOutliers) {
  // Mirroring a point through the camera centre keeps its pixel: without the depth test
  // these would be perfect inliers.
  Scene s = make_scene(9, 200, 0.0, 0.5);
  const SE3d T_w_c = s.T_c_w.inverse();
  for (int i = 0; i < 60; ++i) {
    const Eigen::Vector3d p_c = s.T_c_w * s.points_w[i];
    s.points_w[i] = T_w_c * (-p_c);
    s.is_inlier[i] = 0;
  }
  PnpRansac pnp(PnpOptions{}, 200);
  std::vector<std::uint8_t> mask(200);
  const PnpResult r = pnp.solve(s.input(), mask);
  ASSERT_TRUE(r.ok);
  for (int i = 0; i < 60; ++i) EXPECT_EQ(mask[i], 0) << i;
  EXPECT_LT(rotation_error_deg(r.T_c_w, s.T_c_w), 0.2);
}

TEST(PnpRansac, PriorIsUsedAsFirstHypothesis) {
  const Scene s = make_scene(21, 300, 0.3, 1.0);
  PnpRansac pnp(PnpOptions{}, 300);
  std::vector<std::uint8_t> mask(300);
  const PnpResult blind = pnp.solve(s.input(), mask);
  // A prior a little off (as from a motion model) still explains the inliers well enough.
  Vector6d xi;
  xi << 0.002, -0.001, 0.001, 0.01, -0.005, 0.005;
  const SE3d prior = se3_exp(xi) * s.T_c_w;
  const PnpResult with_prior = pnp.solve(s.input(), mask, &prior);
  ASSERT_TRUE(blind.ok);
  ASSERT_TRUE(with_prior.ok);
  EXPECT_LT(rotation_error_deg(with_prior.T_c_w, s.T_c_w), 0.2);
  EXPECT_LE(with_prior.iterations, blind.iterations);
  EXPECT_GE(agreement(mask, oracle_mask(s, PnpOptions{}.inlier_threshold_px)), 0.95);
  // A wrong prior does not hurt.
  SE3d bad = SE3d::Identity();
  const PnpResult with_bad = pnp.solve(s.input(), mask, &bad);
  ASSERT_TRUE(with_bad.ok);
  EXPECT_LT(rotation_error_deg(with_bad.T_c_w, s.T_c_w), 0.2);
}

TEST(PnpRansac, SameSeedSameResult) {
  const Scene s = make_scene(33, 300, 0.4, 1.0);
  PnpOptions o;
  o.seed = 12345;
  PnpRansac a(o, 300);
  PnpRansac b(o, 300);
  std::vector<std::uint8_t> mask_a(300);
  std::vector<std::uint8_t> mask_b(300);
  const PnpResult ra = a.solve(s.input(), mask_a);
  const PnpResult rb = b.solve(s.input(), mask_b);
  const PnpResult ra2 = a.solve(s.input(), mask_a);  // same instance again
  EXPECT_TRUE(ra.T_c_w.matrix() == rb.T_c_w.matrix());
  EXPECT_TRUE(ra.T_c_w.matrix() == ra2.T_c_w.matrix());
  EXPECT_EQ(ra.iterations, rb.iterations);
  EXPECT_EQ(ra.num_inliers, rb.num_inliers);
  EXPECT_EQ(mask_a, mask_b);
  const PnpResult fa = a.solve_with_focal(s.input_with(kK.with_focal(400.0)), mask_a);
  const PnpResult fb = b.solve_with_focal(s.input_with(kK.with_focal(400.0)), mask_b);
  EXPECT_EQ(fa.focal, fb.focal);
  EXPECT_TRUE(fa.T_c_w.matrix() == fb.T_c_w.matrix());
}

TEST(PnpRansac, FailsCleanly) {
  PnpRansac pnp(PnpOptions{}, 100);
  std::vector<std::uint8_t> mask(200, 7);
  // Too few correspondences.
  const Scene few = make_scene(1, 10, 0.0, 0.0);
  EXPECT_FALSE(pnp.solve(few.input(), mask).ok);
  // More than the capacity.
  const Scene many = make_scene(1, 150, 0.0, 0.0);
  EXPECT_FALSE(pnp.solve(many.input(), mask).ok);
  // Mask too small.
  const Scene s = make_scene(2, 50, 0.0, 0.0);
  std::vector<std::uint8_t> small(10);
  EXPECT_FALSE(pnp.solve(s.input(), small).ok);
  // Pure garbage: observations unrelated to the points.
  Scene garbage = make_scene(3, 100, 1.0, 0.0);
  const PnpResult r = pnp.solve(garbage.input(), mask);
  EXPECT_FALSE(r.ok);
  EXPECT_TRUE(r.T_c_w.matrix().allFinite());
  // Invalid sigma.
  Scene bad_sigma = make_scene(4, 50, 0.0, 0.0);
  bad_sigma.sigma[3] = 0.0F;
  EXPECT_FALSE(pnp.solve(bad_sigma.input(), mask).ok);
  for (int i = 0; i < 50; ++i) EXPECT_EQ(mask[i], 0);
  // Degenerate: all world points identical.
  Scene same = make_scene(5, 50, 0.0, 0.0);
  std::fill(same.points_w.begin(), same.points_w.end(), Eigen::Vector3d(1, 2, 3));
  const PnpResult rs = pnp.solve(same.input(), mask);
  EXPECT_FALSE(rs.ok);
  EXPECT_TRUE(rs.T_c_w.matrix().allFinite());
}

// ---- Jacobians ---------------------------------------------------------------------------

TEST(ReprojectionResidual, AnalyticJacobiansMatchCentralDifferences) {
  std::mt19937_64 gen(17);
  std::normal_distribution<double> n01(0.0, 1.0);
  constexpr double kStepXi = 1e-6;
  constexpr double kStepF = 1e-3;  // px
  constexpr double kRelTol = 1e-5;
  for (int trial = 0; trial < 200; ++trial) {
    const Scene s = make_scene(100 + trial, 1, 0.0, 2.0);
    const Pinhole K{400.0 + 200.0 * std::abs(n01(gen)), 400.0 + 200.0 * std::abs(n01(gen)), 320.0,
                    240.0};
    const SE3d& T = s.T_c_w;
    const Eigen::Vector3d& X = s.points_w[0];
    const Eigen::Vector2d& uv = s.uv[0];
    Eigen::Matrix<double, 2, 6> J;
    Eigen::Vector2d d_r_d_f;
    const Eigen::Vector2d r = reprojection_residual(T, X, uv, K, &J, &d_r_d_f);
    EXPECT_TRUE(r.isApprox(K.project(T * X) - uv));
    Eigen::Matrix<double, 2, 6> d_r_d_xi_num;
    for (int k = 0; k < 6; ++k) {
      Vector6d d = Vector6d::Zero();
      d(k) = kStepXi;
      const Eigen::Vector2d rp = reprojection_residual(se3_exp(d) * T, X, uv, K, nullptr, nullptr);
      const Eigen::Vector2d rm = reprojection_residual(se3_exp(-d) * T, X, uv, K, nullptr, nullptr);
      d_r_d_xi_num.col(k) = (rp - rm) / (2.0 * kStepXi);
    }
    EXPECT_LT((d_r_d_xi_num - J).norm() / J.norm(), kRelTol) << "trial " << trial << "\n"
                                                             << J << "\n"
                                                             << d_r_d_xi_num;
    // Focal: fx = fy = f.
    const Pinhole Kf = K.with_focal(K.fx);
    reprojection_residual(T, X, uv, Kf, nullptr, &d_r_d_f);
    const Eigen::Vector2d rp =
        reprojection_residual(T, X, uv, Kf.with_focal(Kf.fx + kStepF), nullptr, nullptr);
    const Eigen::Vector2d rm =
        reprojection_residual(T, X, uv, Kf.with_focal(Kf.fx - kStepF), nullptr, nullptr);
    const Eigen::Vector2d d_r_d_f_num = (rp - rm) / (2.0 * kStepF);
    EXPECT_LT((d_r_d_f_num - d_r_d_f).norm() / std::max(d_r_d_f.norm(), 1e-3), kRelTol)
        << "trial " << trial;
  }
}

// ---- refine_pose ------------------------------------------------------------------------

TEST(RefinePose, ConvergesFromAPerturbedPose) {
  const Scene s = make_scene(44, 200, 0.0, 0.0);
  Vector6d xi;
  xi << 0.02, -0.03, 0.01, 0.1, 0.05, -0.08;
  SE3d T = se3_exp(xi) * s.T_c_w;
  const RefineResult rr = refine_pose(s.input(), {}, T, nullptr, RefineOptions{20, 2.0, false});
  EXPECT_EQ(rr.num_used, 200);
  EXPECT_LT(rr.final_cost, 1e-12);
  EXPECT_GT(rr.initial_cost, rr.final_cost);
  EXPECT_LT(rotation_error_deg(T, s.T_c_w), 1e-6);
  EXPECT_LT(position_error(T, s.T_c_w), 1e-7);
}

TEST(RefinePose, EstimatesFocalAndHonoursTheMask) {
  Scene s = make_scene(45, 200, 0.25, 0.0);  // outliers masked out below
  SE3d T = s.T_c_w;
  T.translation() += Eigen::Vector3d(0.05, -0.02, 0.1);
  double f = 460.0;
  const PnpInput in = s.input_with(kK.with_focal(f));
  const RefineResult rr = refine_pose(in, s.is_inlier, T, &f, RefineOptions{30, 2.0, true});
  EXPECT_EQ(rr.num_used, 150);
  EXPECT_NEAR(f, 500.0, 1e-4);
  EXPECT_LT(rotation_error_deg(T, s.T_c_w), 1e-6);
  // Without the focal flag f stays put.
  double f2 = 460.0;
  SE3d T2 = s.T_c_w;
  refine_pose(in, s.is_inlier, T2, &f2, RefineOptions{5, 2.0, false});
  EXPECT_EQ(f2, 460.0);
}

// ---- Focal estimation ----------------------------------------------------------------------

TEST(PnpRansac, SolveWithFocalFromThirtyPercentOff) {
  constexpr int kN = 300;
  PnpRansac pnp(PnpOptions{}, kN);
  std::vector<std::uint8_t> mask(kN);
  double worst = 0.0;
  for (const double guess : {350.0, 650.0}) {
    for (int k = 0; k < 10; ++k) {
      const Scene s = make_scene(500 + k, kN, 0.2, 1.0);
      const PnpResult r = pnp.solve_with_focal(s.input_with(kK.with_focal(guess)), mask);
      ASSERT_TRUE(r.ok) << "guess " << guess << " scene " << k;
      const double rel = std::abs(r.focal - 500.0) / 500.0;
      EXPECT_LT(rel, 0.01) << "guess " << guess << " scene " << k << " f " << r.focal;
      EXPECT_LT(rotation_error_deg(r.T_c_w, s.T_c_w), 0.5);
      EXPECT_GE(agreement(mask, oracle_mask(s, PnpOptions{}.inlier_threshold_px)), 0.95);
      EXPECT_EQ(outlier_rejection(mask, s), 1.0);
      worst = std::max(worst, rel);
    }
  }
  std::printf("focal: worst relative error %.4f %%\n", 100.0 * worst);
}

TEST(PnpRansac, SolveWithFocalFullSweepUnderHeavyOutliers) {
  // 60 % outliers: no model explains half the data, so every focal candidate is tried.
  constexpr int kN = 300;
  PnpRansac pnp(PnpOptions{}, kN);
  std::vector<std::uint8_t> mask(kN);
  for (const double guess : {350.0, 650.0}) {
    const Scene s = make_scene(600, kN, 0.6, 1.0);
    const PnpResult r = pnp.solve_with_focal(s.input_with(kK.with_focal(guess)), mask);
    ASSERT_TRUE(r.ok) << "guess " << guess;
    EXPECT_NEAR(r.focal, 500.0, 5.0) << "guess " << guess;
    EXPECT_EQ(outlier_rejection(mask, s), 1.0);
    EXPECT_GT(r.iterations, 2 * PnpOptions{}.max_iterations);  // several candidates ran
  }
}

// ---- Real-time contract -----------------------------------------------------------------

TEST(PnpRansac, NoAllocationPerSolve) {
  ASSERT_TRUE(platform::alloc::counter_linked());
  constexpr int kN = 400;
  const Scene s = make_scene(8, kN, 0.3, 1.0);
  const PnpInput in = s.input();
  PnpRansac pnp(PnpOptions{}, kN);
  std::vector<std::uint8_t> mask(kN);
  const SE3d prior = s.T_c_w;
  SE3d T = s.T_c_w;
  double f = 480.0;
  const std::uint64_t before = platform::alloc::thread_allocations();
  const PnpResult r1 = pnp.solve(in, mask);
  const PnpResult r2 = pnp.solve(in, mask, &prior);
  const PnpResult r3 = pnp.solve_with_focal(s.input_with(kK.with_focal(f)), mask);
  refine_pose(in, mask, T, &f, RefineOptions{10, 2.0, true});
  const std::uint64_t after = platform::alloc::thread_allocations();
  EXPECT_EQ(after - before, 0u);
  EXPECT_TRUE(r1.ok && r2.ok && r3.ok);
}

// ---- Options ---------------------------------------------------------------------------------

TEST(PnpOptions, DefaultsValidateAndLoadFromYaml) {
  PnpOptions o;
  EXPECT_TRUE(options::validate(o).is_ok());
  ASSERT_TRUE(options::load_yaml_string("pnp.yaml",
                                        "max_iterations: 50\nconfidence: 0.99\nseed: 77\n"
                                        "inlier_threshold_px: 3.0\nlo_min_inliers: 20\n",
                                        o)
                  .is_ok());
  EXPECT_EQ(o.max_iterations, 50);
  EXPECT_EQ(o.seed, 77u);
  EXPECT_EQ(o.lo_min_inliers, 20);
  EXPECT_DOUBLE_EQ(o.inlier_threshold_px, 3.0);
  EXPECT_FALSE(options::load_yaml_string("pnp.yaml", "confidence: 1.5\n", o).is_ok());
  std::ostringstream os;
  options::print(o, os);
  EXPECT_NE(os.str().find("huber_px"), std::string::npos);
}

}  // namespace
}  // namespace mer::geometry
