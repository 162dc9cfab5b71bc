#include "geometry/self_calibration.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <numbers>
#include <vector>

#include <Eigen/SVD>

#include "geometry/two_view.h"

namespace mer::geometry {
namespace {

/// RANSAC iterations for F (8-point samples; ~0.8^8 = 17 % clean samples at 20 % outliers,
/// so 300 iterations miss a clean one with probability ~1e-24).
constexpr int kRansacIterations = 300;
/// Keypoint noise assumed for the chi2 gates, px.
constexpr double kSigmaPx = 1.0;
/// Fewer F inliers: refuse (the 8-point F is too noisy for a focal estimate).
constexpr int kMinInliers = 50;
/// A homography with at least this fraction of F's inliers means pure rotation or a single
/// plane: every F = [e]x H fits those points, F is ill-conditioned and so is f. Indoors a
/// wall often holds 80-90 % of the points while the rest (objects, other walls) still pins F
/// down; the bootstrap spread test below rejects the pairs where it does not.
constexpr double kMaxHomographyFraction = 0.95;
/// Samples of the log-spaced scan over [f_guess / kRangeFactor, f_guess * kRangeFactor].
constexpr int kScanSamples = 64;
constexpr double kRangeFactor = 2.0;
/// Golden-section iterations (each shrinks the bracket by 0.618; 40 -> 4e-9 of the bracket).
constexpr int kGoldenIterations = 40;
/// Bootstrap resamples of the F inliers used to measure how well f is determined.
constexpr int kBootstrapSamples = 12;
/// Refuse when the bootstrap RMS spread of f exceeds this fraction of f. The goal is an
/// estimate within 2 %: 3.3 x 0.6 %. (With ~1 px noise the bootstrap underestimates the true
/// spread by up to ~1.5x, as the inlier set is fixed: still > 2 sigma.) Weak motions give
/// 1-3 %, flat costs (focal not observable) far more or a minimum on the range border.
constexpr double kMaxRelativeSigma = 0.006;

/// Mendonca-Cipolla cost (s1 - s2) / s2 of E = K^T F K.
double focal_cost(const Eigen::Matrix3d& F, double f, double cx, double cy) {
  Eigen::Matrix3d K;
  K << f, 0.0, cx, 0.0, f, cy, 0.0, 0.0, 1.0;
  const Eigen::Matrix3d E = K.transpose() * F * K;
  const Eigen::Vector3d s = Eigen::JacobiSVD<Eigen::Matrix3d>(E).singularValues();
  if (!(s(1) > 0.0)) return std::numeric_limits<double>::infinity();
  return (s(0) - s(1)) / s(1);
}

/// Minimum of the cost over [f_guess / kRangeFactor, f_guess * kRangeFactor]: log-spaced scan,
/// then golden-section search on the bracket around the best sample (in log f).
struct FocalMinimum {
  double focal = 0.0;
  double cost = 0.0;
  bool interior = false;  ///< false: minimum on the border of the range
};

FocalMinimum minimize_focal_cost(const Eigen::Matrix3d& fundamental, double cx, double cy,
                                 double f_guess) {
  // Unit norm F keeps the SVDs well scaled (the cost itself does not depend on the scale).
  const Eigen::Matrix3d F = fundamental / fundamental.norm();
  const auto cost = [&](double log_f) { return focal_cost(F, std::exp(log_f), cx, cy); };
  const double log_lo = std::log(f_guess / kRangeFactor);
  const double log_hi = std::log(f_guess * kRangeFactor);
  const double step = (log_hi - log_lo) / (kScanSamples - 1);
  int best = 0;
  double best_cost = std::numeric_limits<double>::infinity();
  for (int k = 0; k < kScanSamples; ++k) {
    const double c = cost(log_lo + step * k);
    if (c < best_cost) {
      best_cost = c;
      best = k;
    }
  }
  FocalMinimum m;
  m.focal = std::exp(log_lo + step * best);
  m.cost = best_cost;
  if (best == 0 || best == kScanSamples - 1) return m;

  constexpr double kInvPhi = std::numbers::phi - 1.0;  // 1 / golden ratio
  double a = log_lo + step * (best - 1);
  double b = log_lo + step * (best + 1);
  double x1 = b - kInvPhi * (b - a);
  double x2 = a + kInvPhi * (b - a);
  double c1 = cost(x1);
  double c2 = cost(x2);
  for (int it = 0; it < kGoldenIterations; ++it) {
    if (c1 < c2) {
      b = x2;
      x2 = x1;
      c2 = c1;
      x1 = b - kInvPhi * (b - a);
      c1 = cost(x1);
    } else {
      a = x1;
      x1 = x2;
      c1 = c2;
      x2 = a + kInvPhi * (b - a);
      c2 = cost(x2);
    }
  }
  m.focal = std::exp(0.5 * (a + b));
  m.cost = cost(0.5 * (a + b));
  m.interior = true;
  return m;
}

/// xorshift64* (Vigna 2016): bootstrap index draws.
class XorShift64Star {
 public:
  explicit XorShift64Star(std::uint64_t seed) : state_(seed != 0 ? seed : kNonZero) {}
  std::size_t below(std::size_t n) {
    constexpr int kShiftA = 12;
    constexpr int kShiftB = 25;
    constexpr int kShiftC = 27;
    constexpr std::uint64_t kMul = 0x2545F4914F6CDD1DULL;  // multiplier of xorshift64*
    state_ ^= state_ >> kShiftA;
    state_ ^= state_ << kShiftB;
    state_ ^= state_ >> kShiftC;
    return static_cast<std::size_t>((state_ * kMul) % n);  // modulo bias < n / 2^64
  }

 private:
  static constexpr std::uint64_t kNonZero = 0x9E3779B97F4A7C15ULL;  // any non-zero state
  std::uint64_t state_;
};

}  // namespace

FocalEstimate estimate_focal_two_view(std::span<const Eigen::Vector2d> uv0,
                                      std::span<const Eigen::Vector2d> uv1, double cx, double cy,
                                      double f_guess, std::uint64_t seed) {
  FocalEstimate est;
  if (uv0.size() != uv1.size() || uv0.size() < static_cast<std::size_t>(kMinInliers) ||
      !(f_guess > 0.0)) {
    return est;
  }
  const TwoViewModelFit fit = fit_two_view_models(uv0, uv1, kRansacIterations, kSigmaPx, seed);
  est.num_inliers = fit.num_inliers_f;
  if (fit.num_inliers_f < kMinInliers) return est;
  // Pure rotation or a dominant plane: every F = [e]x H fits the homography's points, so F
  // (and any f derived from it) is arbitrary.
  if (fit.num_inliers_h >= kMaxHomographyFraction * fit.num_inliers_f) return est;

  const FocalMinimum m = minimize_focal_cost(fit.F, cx, cy, f_guess);
  est.focal = m.focal;
  est.cost = m.cost;
  if (!m.interior) return est;  // true f outside the range, or no minimum at all

  // How well is f determined? Refit F on bootstrap resamples of the inliers and look at the
  // spread of the minimizers. (The curvature of the cost alone does not say: its scale depends
  // on the motion, and near-degenerate motions have a sharp-looking but noise-driven minimum.)
  std::vector<std::size_t> inliers;
  for (std::size_t i = 0; i < fit.inliers_f.size(); ++i) {
    if (fit.inliers_f[i]) inliers.push_back(i);
  }
  XorShift64Star rng(seed);
  std::vector<double> counts(uv0.size());
  double sum_sq = 0.0;
  for (int b = 0; b < kBootstrapSamples; ++b) {
    std::fill(counts.begin(), counts.end(), 0.0);
    for (std::size_t k = 0; k < inliers.size(); ++k)
      counts[inliers[rng.below(inliers.size())]] += 1.0;
    Eigen::Matrix3d F;
    if (!fit_fundamental_8point(uv0, uv1, counts, F)) return est;
    const FocalMinimum mb = minimize_focal_cost(F, cx, cy, f_guess);
    if (!mb.interior) return est;
    const double rel = (mb.focal - m.focal) / m.focal;
    sum_sq += rel * rel;
  }
  est.relative_sigma = std::sqrt(sum_sq / kBootstrapSamples);
  est.ok = est.relative_sigma <= kMaxRelativeSigma;
  return est;
}

double median_focal(std::span<const double> estimates) {
  std::vector<double> v;
  v.reserve(estimates.size());
  for (const double e : estimates) {
    if (std::isfinite(e) && e > 0.0) v.push_back(e);
  }
  if (v.empty()) return 0.0;
  std::sort(v.begin(), v.end());
  const std::size_t m = v.size() / 2;
  return v.size() % 2 == 1 ? v[m] : 0.5 * (v[m - 1] + v[m]);
}

}  // namespace mer::geometry
