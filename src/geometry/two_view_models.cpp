#include "geometry/two_view_models.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <numbers>

#include <Eigen/Eigenvalues>
#include <Eigen/LU>

namespace mer::geometry {
namespace two_view_detail {
namespace {

/// 95 % quantile of chi2 with 1 dof: squared point-to-epipolar-line distance / variance.
/// Score offset per image of an F inlier. A correct model's 2-dof residual (H) has an expected
/// chi2 one larger than a 1-dof residual (F: distance to a line), so with the same offset F
/// would out-score H even on a plane, where both explain every point. One less makes a correct
/// H and a correct F score the same on average, so R_H ~ 0.5 on planes (F degenerate) and
/// R_H << 0.5 when only F explains the points.
constexpr double kScoreOffsetF = kChi2TwoDof95 - 1.0;
/// Score offset per image of an H inlier.
constexpr double kScoreOffsetH = kChi2TwoDof95;
/// Most any single correspondence can add to a score (both images, zero residual).
constexpr double kMaxScorePerPoint = 2.0 * kScoreOffsetH;
/// Least-squares refits on the inlier set after RANSAC (stop early when the score drops).
constexpr int kRefitPasses = 3;
/// Homography hypotheses with |det| below this (of the Hartley-normalized H, unit Frobenius
/// norm) are singular (collinear samples) and skipped.
constexpr double kMinHomographyDet = 1e-9;
/// Mean distance of Hartley-normalized points from their centroid.
constexpr double kHartleyMeanDistance = std::numbers::sqrt2;
/// Points closer than this (px) to their centroid on average: no normalization scale.
constexpr double kMinSpreadPx = 1e-9;
/// Plane and parallax fallback: points whose H transfer misses their match by this many
/// keypoint sigmas are off the plane (those just outside H's gate are plane points with
/// larger noise and say nothing about the epipole)...
constexpr double kOffPlaneSigmas = 6.0;
/// ... and at least this many of them must agree on the epipole.
constexpr int kMinOffPlanePoints = 40;
/// Two parallax lines closer to parallel than this (|l_a x l_b| of unit-normal lines, in
/// pixels) give no epipole.
constexpr double kMinEpipoleNorm = 1e-9;

using Matrix9d = Eigen::Matrix<double, 9, 9>;
using Vector9d = Eigen::Matrix<double, 9, 1>;
using RowMatrix3d = Eigen::Matrix<double, 3, 3, Eigen::RowMajor>;

/// SplitMix64 (Steele, Lea, Flood 2014): tiny, fast, good enough to draw RANSAC samples.
class SplitMix64 {
 public:
  explicit SplitMix64(std::uint64_t seed) : state_(seed) {}
  std::uint64_t next() {
    constexpr std::uint64_t kGamma = 0x9e3779b97f4a7c15ULL;  // golden-ratio increment
    constexpr std::uint64_t kMul1 = 0xbf58476d1ce4e5b9ULL;   // mixing constants of SplitMix64
    constexpr std::uint64_t kMul2 = 0x94d049bb133111ebULL;
    constexpr int kShift1 = 30;
    constexpr int kShift2 = 27;
    constexpr int kShift3 = 31;
    std::uint64_t z = (state_ += kGamma);
    z = (z ^ (z >> kShift1)) * kMul1;
    z = (z ^ (z >> kShift2)) * kMul2;
    return z ^ (z >> kShift3);
  }
  /// Uniform in [0, n) (modulo bias < n / 2^64: negligible).
  std::size_t below(std::size_t n) { return static_cast<std::size_t>(next() % n); }

 private:
  std::uint64_t state_;
};

/// Hartley normalization: translate the centroid to 0, scale the mean distance to sqrt(2).
Eigen::Matrix3d hartley_normalization(std::span<const Eigen::Vector2d> pts) {
  Eigen::Vector2d mean = Eigen::Vector2d::Zero();
  for (const auto& p : pts) mean += p;
  mean /= static_cast<double>(pts.size());
  double mean_dist = 0.0;
  for (const auto& p : pts) mean_dist += (p - mean).norm();
  mean_dist /= static_cast<double>(pts.size());
  const double s = mean_dist > kMinSpreadPx ? kHartleyMeanDistance / mean_dist : 1.0;
  Eigen::Matrix3d T;
  T << s, 0.0, -s * mean.x(), 0.0, s, -s * mean.y(), 0.0, 0.0, 1.0;
  return T;
}

Eigen::Vector2d apply(const Eigen::Matrix3d& T, const Eigen::Vector2d& p) {
  return {T(0, 0) * p.x() + T(0, 2), T(1, 1) * p.y() + T(1, 2)};
}

/// Unit vector minimizing |A a| given A^T A (eigenvector of the smallest eigenvalue).
Vector9d smallest_eigenvector(const Matrix9d& ata) {
  const Eigen::SelfAdjointEigenSolver<Matrix9d> es(ata);
  return es.eigenvectors().col(0);
}

void add_rows_fundamental(Matrix9d& ata, const Eigen::Vector2d& p0, const Eigen::Vector2d& p1,
                          double weight = 1.0) {
  Vector9d a;
  a << p1.x() * p0.x(), p1.x() * p0.y(), p1.x(), p1.y() * p0.x(), p1.y() * p0.y(), p1.y(), p0.x(),
      p0.y(), 1.0;
  ata.selfadjointView<Eigen::Lower>().rankUpdate(a, weight);
}

void add_rows_homography(Matrix9d& ata, const Eigen::Vector2d& p0, const Eigen::Vector2d& p1) {
  Vector9d a;
  a << 0.0, 0.0, 0.0, -p0.x(), -p0.y(), -1.0, p1.y() * p0.x(), p1.y() * p0.y(), p1.y();
  ata.selfadjointView<Eigen::Lower>().rankUpdate(a);
  a << p0.x(), p0.y(), 1.0, 0.0, 0.0, 0.0, -p1.x() * p0.x(), -p1.x() * p0.y(), -p1.x();
  ata.selfadjointView<Eigen::Lower>().rankUpdate(a);
}

Eigen::Matrix3d to_matrix(const Vector9d& v) {
  return RowMatrix3d(v.data());
}

/// F from the normal matrix of the normalized 8-point system, rank 2 enforced, then
/// denormalized to pixels (x1^T F x0 = 0).
Eigen::Matrix3d solve_fundamental(const Matrix9d& ata, const Eigen::Matrix3d& T0,
                                  const Eigen::Matrix3d& T1) {
  Matrix9d full = ata.selfadjointView<Eigen::Lower>();
  const Eigen::Matrix3d Fn = to_matrix(smallest_eigenvector(full));
  const Eigen::JacobiSVD<Eigen::Matrix3d> svd(Fn, Eigen::ComputeFullU | Eigen::ComputeFullV);
  Eigen::Vector3d sv = svd.singularValues();
  sv(2) = 0.0;
  const Eigen::Matrix3d F2 = svd.matrixU() * sv.asDiagonal() * svd.matrixV().transpose();
  return T1.transpose() * F2 * T0;
}

/// H from the normal matrix of the normalized DLT system, denormalized to pixels. Returns
/// false for a singular hypothesis.
bool solve_homography(const Matrix9d& ata, const Eigen::Matrix3d& T0, const Eigen::Matrix3d& T1,
                      Eigen::Matrix3d& H) {
  Matrix9d full = ata.selfadjointView<Eigen::Lower>();
  const Eigen::Matrix3d Hn = to_matrix(smallest_eigenvector(full));
  if (!(std::abs(Hn.determinant()) > kMinHomographyDet)) return false;
  H = T1.inverse() * Hn * T0;
  return true;
}

}  // namespace

double score_fundamental(const Eigen::Matrix3d& F, std::span<const Eigen::Vector2d> uv0,
                         std::span<const Eigen::Vector2d> uv1, double inv_var, double to_beat,
                         std::vector<std::uint8_t>& inliers, int& count) {
  // Scalar code: this loop and the one of score_homography dominate the run time.
  const double f00 = F(0, 0), f01 = F(0, 1), f02 = F(0, 2);
  const double f10 = F(1, 0), f11 = F(1, 1), f12 = F(1, 2);
  const double f20 = F(2, 0), f21 = F(2, 1), f22 = F(2, 2);
  double score = 0.0;
  count = 0;
  const std::size_t n = uv0.size();
  for (std::size_t i = 0; i < n; ++i) {
    const double u0 = uv0[i].x(), v0 = uv0[i].y(), u1 = uv1[i].x(), v1 = uv1[i].y();
    const double a1 = f00 * u0 + f01 * v0 + f02;  // epipolar line of x0 in image 1
    const double b1 = f10 * u0 + f11 * v0 + f12;
    const double c1 = f20 * u0 + f21 * v0 + f22;
    const double a0 = f00 * u1 + f10 * v1 + f20;  // epipolar line of x1 in image 0
    const double b0 = f01 * u1 + f11 * v1 + f21;
    const double num = u1 * a1 + v1 * b1 + c1;
    const double num2 = num * num * inv_var;
    const double chi1 = num2 / (a1 * a1 + b1 * b1);
    const double chi0 = num2 / (a0 * a0 + b0 * b0);
    const bool in = chi1 <= kChi2OneDof95 && chi0 <= kChi2OneDof95;  // false for NaN
    inliers[i] = in ? 1 : 0;
    if (in) {
      score += (kScoreOffsetF - chi1) + (kScoreOffsetF - chi0);
      ++count;
    } else if (score + static_cast<double>(n - i - 1) * kMaxScorePerPoint < to_beat) {
      return -1.0;
    }
  }
  return score;
}

namespace {

/// Truncated symmetric transfer score of H (2-dof chi2 in both images); early exit as above.
double score_homography(const Eigen::Matrix3d& H, std::span<const Eigen::Vector2d> uv0,
                        std::span<const Eigen::Vector2d> uv1, double inv_var, double to_beat,
                        std::vector<std::uint8_t>& inliers, int& count) {
  const Eigen::Matrix3d G = H.inverse();
  const double h00 = H(0, 0), h01 = H(0, 1), h02 = H(0, 2);
  const double h10 = H(1, 0), h11 = H(1, 1), h12 = H(1, 2);
  const double h20 = H(2, 0), h21 = H(2, 1), h22 = H(2, 2);
  const double g00 = G(0, 0), g01 = G(0, 1), g02 = G(0, 2);
  const double g10 = G(1, 0), g11 = G(1, 1), g12 = G(1, 2);
  const double g20 = G(2, 0), g21 = G(2, 1), g22 = G(2, 2);
  double score = 0.0;
  count = 0;
  const std::size_t n = uv0.size();
  for (std::size_t i = 0; i < n; ++i) {
    const double u0 = uv0[i].x(), v0 = uv0[i].y(), u1 = uv1[i].x(), v1 = uv1[i].y();
    const double w1 = 1.0 / (h20 * u0 + h21 * v0 + h22);  // x0 transferred to image 1
    const double du1 = (h00 * u0 + h01 * v0 + h02) * w1 - u1;
    const double dv1 = (h10 * u0 + h11 * v0 + h12) * w1 - v1;
    const double chi1 = (du1 * du1 + dv1 * dv1) * inv_var;
    bool in = chi1 <= kChi2TwoDof95;  // false for NaN
    double chi0 = 0.0;
    if (in) {
      const double w0 = 1.0 / (g20 * u1 + g21 * v1 + g22);  // x1 transferred to image 0
      const double du0 = (g00 * u1 + g01 * v1 + g02) * w0 - u0;
      const double dv0 = (g10 * u1 + g11 * v1 + g12) * w0 - v0;
      chi0 = (du0 * du0 + dv0 * dv0) * inv_var;
      in = chi0 <= kChi2TwoDof95;
    }
    inliers[i] = in ? 1 : 0;
    if (in) {
      score += (kScoreOffsetH - chi1) + (kScoreOffsetH - chi0);
      ++count;
    } else if (score + static_cast<double>(n - i - 1) * kMaxScorePerPoint < to_beat) {
      return -1.0;
    }
  }
  return score;
}

/// Draws kSampleSize distinct indices in [0, n).
void draw_sample(SplitMix64& rng, std::size_t n, std::array<std::size_t, kSampleSize>& idx) {
  for (int k = 0; k < kSampleSize; ++k) {
    bool fresh = false;
    while (!fresh) {
      idx[k] = rng.below(n);
      fresh = std::find(idx.begin(), idx.begin() + k, idx[k]) == idx.begin() + k;
    }
  }
}

}  // namespace

/// fit_two_view_models into `fit` (every field overwritten) with the buffers of `s`.
void fit_models(std::span<const Eigen::Vector2d> uv0, std::span<const Eigen::Vector2d> uv1,
                int iterations, double sigma_px, std::uint64_t seed, FitScratch& s,
                TwoViewModelFit& fit) {
  fit.H = Eigen::Matrix3d::Identity();
  fit.F = Eigen::Matrix3d::Zero();
  fit.num_inliers_h = 0;
  fit.num_inliers_f = 0;
  fit.score_h = 0;
  fit.score_f = 0;
  const std::size_t n = std::min(uv0.size(), uv1.size());
  fit.inliers_h.assign(n, 0);
  fit.inliers_f.assign(n, 0);
  if (uv0.size() != uv1.size() || n < static_cast<std::size_t>(kSampleSize)) return;
  const double inv_var = 1.0 / (kResidualVarianceFactor * sigma_px * sigma_px);

  const Eigen::Matrix3d T0 = hartley_normalization(uv0);
  const Eigen::Matrix3d T1 = hartley_normalization(uv1);
  std::vector<Eigen::Vector2d>& p0 = s.p0;
  std::vector<Eigen::Vector2d>& p1 = s.p1;
  p0.resize(n);
  p1.resize(n);
  for (std::size_t i = 0; i < n; ++i) {
    p0[i] = apply(T0, uv0[i]);
    p1[i] = apply(T1, uv1[i]);
  }

  std::vector<std::uint8_t>& mask = s.mask;
  mask.assign(n, 0);
  SplitMix64 rng(seed);
  std::array<std::size_t, kSampleSize> idx{};
  fit.score_h = -1.0;
  fit.score_f = -1.0;
  for (int it = 0; it < iterations; ++it) {
    draw_sample(rng, n, idx);
    Matrix9d ata_f = Matrix9d::Zero();
    Matrix9d ata_h = Matrix9d::Zero();
    for (int k = 0; k < kSampleSize; ++k) {
      add_rows_fundamental(ata_f, p0[idx[k]], p1[idx[k]]);
      if (k < kHomographySampleSize) add_rows_homography(ata_h, p0[idx[k]], p1[idx[k]]);
    }
    const Eigen::Matrix3d F = solve_fundamental(ata_f, T0, T1);
    int count = 0;
    double score = score_fundamental(F, uv0, uv1, inv_var, fit.score_f, mask, count);
    if (score > fit.score_f) {
      fit.score_f = score;
      fit.F = F;
      fit.num_inliers_f = count;
      fit.inliers_f.swap(mask);
    }
    Eigen::Matrix3d H;
    if (!solve_homography(ata_h, T0, T1, H)) continue;
    score = score_homography(H, uv0, uv1, inv_var, fit.score_h, mask, count);
    if (score > fit.score_h) {
      fit.score_h = score;
      fit.H = H;
      fit.num_inliers_h = count;
      fit.inliers_h.swap(mask);
    }
  }

  // Least-squares refits on the inlier sets (kept only while the score improves).
  for (int pass = 0; pass < kRefitPasses && fit.num_inliers_f >= kSampleSize; ++pass) {
    Matrix9d ata = Matrix9d::Zero();
    for (std::size_t i = 0; i < n; ++i) {
      if (fit.inliers_f[i]) add_rows_fundamental(ata, p0[i], p1[i]);
    }
    const Eigen::Matrix3d F = solve_fundamental(ata, T0, T1);
    int count = 0;
    const double score = score_fundamental(F, uv0, uv1, inv_var, fit.score_f, mask, count);
    if (!(score > fit.score_f)) break;
    fit.score_f = score;
    fit.F = F;
    fit.num_inliers_f = count;
    fit.inliers_f.swap(mask);
  }
  for (int pass = 0; pass < kRefitPasses && fit.num_inliers_h >= kHomographySampleSize; ++pass) {
    Matrix9d ata = Matrix9d::Zero();
    for (std::size_t i = 0; i < n; ++i) {
      if (fit.inliers_h[i]) add_rows_homography(ata, p0[i], p1[i]);
    }
    Eigen::Matrix3d H;
    if (!solve_homography(ata, T0, T1, H)) break;
    int count = 0;
    const double score = score_homography(H, uv0, uv1, inv_var, fit.score_h, mask, count);
    if (!(score > fit.score_h)) break;
    fit.score_h = score;
    fit.H = H;
    fit.num_inliers_h = count;
    fit.inliers_h.swap(mask);
  }
  fit.score_h = std::max(fit.score_h, 0.0);
  fit.score_f = std::max(fit.score_f, 0.0);
}

bool plane_and_parallax_fundamental(const Eigen::Matrix3d& H, std::span<const Eigen::Vector2d> uv0,
                                    std::span<const Eigen::Vector2d> uv1, double sigma_px,
                                    int iterations, std::uint64_t seed, ParallaxScratch& s,
                                    PlaneParallaxFit& out) {
  const std::size_t n = uv0.size();
  const double inv_var = 1.0 / (kResidualVarianceFactor * sigma_px * sigma_px);
  const double min_off2 = kOffPlaneSigmas * kOffPlaneSigmas * sigma_px * sigma_px;
  std::vector<std::size_t>& off = s.off;
  std::vector<Eigen::Vector3d>& lines = s.lines;
  off.clear();
  lines.clear();
  for (std::size_t i = 0; i < n; ++i) {
    const Eigen::Vector3d q = H * uv0[i].homogeneous();
    if (!(std::abs(q.z()) > std::numeric_limits<double>::min())) continue;
    if ((q.hnormalized() - uv1[i]).squaredNorm() < min_off2) continue;
    const Eigen::Vector3d l = uv1[i].homogeneous().cross(q);
    const double norm = l.head<2>().norm();
    if (!(norm > 0.0)) continue;
    off.push_back(i);
    lines.push_back(l / norm);
  }
  if (static_cast<int>(off.size()) < kMinOffPlanePoints) return false;
  auto f_of = [&H](const Eigen::Vector3d& e) {
    Eigen::Matrix3d e_x;
    e_x << 0.0, -e.z(), e.y(), e.z(), 0.0, -e.x(), -e.y(), e.x(), 0.0;
    return Eigen::Matrix3d(e_x * H);
  };
  SplitMix64 rng(seed);
  std::vector<std::uint8_t>& mask = s.mask;
  mask.assign(n, 0);
  double best_score = -1.0;
  Eigen::Vector3d best_e = Eigen::Vector3d::Zero();
  for (int it = 0; it < iterations; ++it) {
    const std::size_t a = rng.below(off.size());
    const std::size_t b = rng.below(off.size());
    if (a == b) continue;
    const Eigen::Vector3d e = lines[a].cross(lines[b]);
    if (!(e.norm() > kMinEpipoleNorm)) continue;
    int count = 0;
    const double score =
        score_fundamental(f_of(e.normalized()), uv0, uv1, inv_var, best_score, mask, count);
    if (score > best_score) {
      best_score = score;
      best_e = e.normalized();
    }
  }
  if (!(best_score > 0.0)) return false;
  // Least squares over the inlier lines: the unit e minimizing sum (l . e)^2.
  Eigen::Vector3d e = best_e;
  for (int pass = 0; pass < kRefitPasses; ++pass) {
    int count = 0;
    (void)score_fundamental(f_of(e), uv0, uv1, inv_var, -std::numeric_limits<double>::infinity(),
                            mask, count);
    Eigen::Matrix3d ata = Eigen::Matrix3d::Zero();
    for (std::size_t k = 0; k < off.size(); ++k) {
      if (mask[off[k]]) ata += lines[k] * lines[k].transpose();
    }
    const Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> es(ata);
    const Eigen::Vector3d refit = es.eigenvectors().col(0);
    const double score = score_fundamental(f_of(refit), uv0, uv1, inv_var,
                                           -std::numeric_limits<double>::infinity(), mask, count);
    if (!(score > best_score)) break;
    best_score = score;
    e = refit;
  }
  out.F = f_of(e);
  out.inliers.assign(n, 0);
  (void)score_fundamental(out.F, uv0, uv1, inv_var, -std::numeric_limits<double>::infinity(),
                          out.inliers, out.num_inliers);
  out.num_off_plane_inliers = 0;
  for (const std::size_t i : off) out.num_off_plane_inliers += out.inliers[i];
  return out.num_off_plane_inliers >= kMinOffPlanePoints;
}

}  // namespace two_view_detail

using two_view_detail::add_rows_fundamental;
using two_view_detail::apply;
using two_view_detail::FitScratch;
using two_view_detail::hartley_normalization;
using two_view_detail::kSampleSize;
using two_view_detail::Matrix9d;
using two_view_detail::solve_fundamental;

TwoViewModelFit fit_two_view_models(std::span<const Eigen::Vector2d> uv0,
                                    std::span<const Eigen::Vector2d> uv1, int iterations,
                                    double sigma_px, std::uint64_t seed) {
  FitScratch s;
  TwoViewModelFit fit;
  fit_models(uv0, uv1, iterations, sigma_px, seed, s, fit);
  return fit;
}

bool fit_fundamental_8point(std::span<const Eigen::Vector2d> uv0,
                            std::span<const Eigen::Vector2d> uv1, std::span<const double> weights,
                            Eigen::Matrix3d& F) {
  if (uv0.size() != uv1.size() || weights.size() != uv0.size()) return false;
  const std::size_t used = static_cast<std::size_t>(
      std::count_if(weights.begin(), weights.end(), [](double w) { return w > 0.0; }));
  if (used < static_cast<std::size_t>(kSampleSize)) return false;
  const Eigen::Matrix3d T0 = hartley_normalization(uv0);
  const Eigen::Matrix3d T1 = hartley_normalization(uv1);
  Matrix9d ata = Matrix9d::Zero();
  for (std::size_t i = 0; i < uv0.size(); ++i) {
    if (weights[i] > 0.0)
      add_rows_fundamental(ata, apply(T0, uv0[i]), apply(T1, uv1[i]), weights[i]);
  }
  F = solve_fundamental(ata, T0, T1);
  return true;
}

}  // namespace mer::geometry
