#include "geometry/two_view.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <numbers>
#include <optional>

#include <Eigen/Eigenvalues>
#include <Eigen/LU>
#include <Eigen/SVD>

#include "core/median.h"
#include "geometry/lie.h"
#include "geometry/triangulation.h"
#include "geometry/two_view_models.h"

namespace mer::geometry {
namespace {

using two_view_detail::fit_models;
using two_view_detail::FitScratch;
using two_view_detail::kChi2TwoDof95;
using two_view_detail::kHomographySampleSize;
using two_view_detail::kResidualVarianceFactor;
using two_view_detail::kSampleSize;
using two_view_detail::ParallaxScratch;
using two_view_detail::plane_and_parallax_fundamental;
using two_view_detail::PlaneParallaxFit;
using two_view_detail::score_fundamental;

/// A rotation alone explaining this fraction of the best model's inliers means there is no
/// usable baseline (a translation large enough to initialize moves most points off the
/// rotation-only prediction by more than the 2-dof chi2 gate).
constexpr double kPureRotationInlierFraction = 0.7;
// Refits of a pure rotation on the correspondences it explains.
constexpr int kRotationRefineRounds = 3;
/// Homography singular values closer than this (relative) count as equal: the homography is a
/// rotation (no translation) or degenerate, and its decomposition is undefined.
constexpr double kMinSingularGap = 1e-6;
/// A motion candidate that is not consistent with at least this fraction of the winner's good
/// points is refuted by them and does not make the choice ambiguous.
constexpr double kMinRefutedFraction = 0.05;
/// Degrees per radian.
constexpr double kRadToDeg = 180.0 / std::numbers::pi;
/// Rays whose angle has a squared sine below this are parallel for the candidate vote
/// (~0.006 deg: far below any useful parallax).
constexpr double kMinRayAngleSin2 = 1e-8;
/// Levenberg-Marquardt settings of the motion refinement (Sampson error, 5 dof).
constexpr int kLmMaxIterations = 15;
constexpr double kLmInitialDamping = 1e-4;  // relative to diag(J^T J)
constexpr double kLmMaxDamping = 1e8;       // give up when the damping grows beyond
constexpr double kLmDampingDown = 0.1;
constexpr double kLmDampingUp = 10.0;
constexpr double kLmJacobianStep = 1e-7;          // rad / unit-vector step of the numeric Jacobian
constexpr double kLmMinRelativeDecrease = 1e-10;  // converged
/// Refine / re-gate rounds of the essential model's local optimization.
constexpr int kLocalOptimizationRounds = 4;

Eigen::Matrix3d k_matrix(const Pinhole& K) {
  Eigen::Matrix3d M;
  M << K.fx, 0.0, K.cx, 0.0, K.fy, K.cy, 0.0, 0.0, 1.0;
  return M;
}

/// Motion hypothesis: x_c1 = R x_c0 + t (t of arbitrary positive scale).
struct Motion {
  Eigen::Matrix3d R;
  Eigen::Vector3d t;
  Eigen::Vector3d n = Eigen::Vector3d::Zero();  ///< homography candidates: unit plane normal,
                                                ///< camera 0, z >= 0
};

/// Camera 1 from camera 0 with a unit translation.
SE3d unit_motion(const Motion& m) {
  SE3d T = SE3d::Identity();
  T.linear() = m.R;
  const double norm = m.t.norm();
  T.translation() = norm > 0.0 ? Eigen::Vector3d(m.t / norm) : m.t;
  return T;
}

Eigen::Vector3d facing_away(const Eigen::Vector3d& n) {
  return n.z() < 0.0 ? Eigen::Vector3d(-n) : n;
}

/// Angle between two unit normals (either sign), deg.
double normal_angle_deg(const Eigen::Vector3d& a, const Eigen::Vector3d& b) {
  return std::acos(std::min(1.0, std::abs(a.dot(b)))) * kRadToDeg;
}

/// The tied homography candidate the plane hints single out: the only one whose normal is
/// within plane_hint_agree_deg of a hint while every other is at least plane_hint_refute_deg
/// from all hints. nullopt without hints or without such a candidate.
std::optional<std::size_t> tie_broken_by_plane_hints(std::span<const Motion> candidates,
                                                     std::span<const std::size_t> tied,
                                                     std::span<const Eigen::Vector3d> hints,
                                                     const TwoViewOptions& o) {
  if (hints.empty()) return std::nullopt;
  std::optional<std::size_t> winner;
  for (const std::size_t k : tied) {
    double nearest = std::numeric_limits<double>::infinity();
    for (const Eigen::Vector3d& h : hints) {
      nearest = std::min(nearest, normal_angle_deg(candidates[k].n, h.normalized()));
    }
    if (nearest <= o.plane_hint_agree_deg) {
      if (winner) return std::nullopt;  // two candidates agree: no decision
      winner = k;
    } else if (nearest < o.plane_hint_refute_deg) {
      return std::nullopt;  // neither agrees nor is refuted
    }
  }
  return winner;
}

/// Motion candidates of one model: at most the eight of a homography.
struct MotionList {
  static constexpr std::size_t kCapacity = kMaxPlaneNormals;
  std::array<Motion, kCapacity> m;
  std::size_t size = 0;
  void push_back(const Motion& x) { m[size++] = x; }
  Motion& operator[](std::size_t k) { return m[k]; }
  const Motion& operator[](std::size_t k) const { return m[k]; }
  std::span<const Motion> span() const { return {m.data(), size}; }
};

/// The four (R, t) factorizations of an essential matrix (Hartley & Zisserman, result 9.19).
void decompose_essential(const Eigen::Matrix3d& E, MotionList& out) {
  const Eigen::JacobiSVD<Eigen::Matrix3d> svd(E, Eigen::ComputeFullU | Eigen::ComputeFullV);
  Eigen::Matrix3d U = svd.matrixU();
  Eigen::Matrix3d V = svd.matrixV();
  if (U.determinant() < 0.0) U = -U;  // E is defined up to sign: keep both factors proper
  if (V.determinant() < 0.0) V = -V;
  Eigen::Matrix3d W;
  W << 0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0;
  const Eigen::Matrix3d R1 = U * W * V.transpose();
  const Eigen::Matrix3d R2 = U * W.transpose() * V.transpose();
  const Eigen::Vector3d t = U.col(2);
  out.size = 0;
  for (const Motion& m : {Motion{R1, t}, Motion{R1, -t}, Motion{R2, t}, Motion{R2, -t}}) {
    out.push_back(m);
  }
}

/// The eight (R, t) factorizations of a calibrated homography Hn ~ R + t n^T / d
/// (Faugeras & Lustman 1988, SVD method): with Hn = U diag(d1, d2, d3) V^T and
/// s = det(U) det(V), R = s U R' V^T and t = U t', where (R', t') solve the diagonal problem
/// for d' = +d2 (rotation about y by theta) and d' = -d2 (reflection-like case), each with
/// the four sign choices (e1, e3) of the normal's components. Empty when two singular values
/// coincide (rotation-only or degenerate homography).
void decompose_homography(const Eigen::Matrix3d& Hn, MotionList& out) {
  out.size = 0;
  const Eigen::JacobiSVD<Eigen::Matrix3d> svd(Hn, Eigen::ComputeFullU | Eigen::ComputeFullV);
  const Eigen::Vector3d d = svd.singularValues();
  if (d(0) / d(1) < 1.0 + kMinSingularGap || d(1) / d(2) < 1.0 + kMinSingularGap) return;
  const Eigen::Matrix3d& U = svd.matrixU();
  const Eigen::Matrix3d& V = svd.matrixV();
  const double s = U.determinant() * V.determinant();
  const double d1 = d(0);
  const double d2 = d(1);
  const double d3 = d(2);
  const double d1s = d1 * d1;
  const double d2s = d2 * d2;
  const double d3s = d3 * d3;
  const double x1_abs = std::sqrt((d1s - d2s) / (d1s - d3s));
  const double x3_abs = std::sqrt((d2s - d3s) / (d1s - d3s));
  const double root = std::sqrt((d1s - d2s) * (d2s - d3s));
  constexpr std::array<double, 4> kE1{1.0, 1.0, -1.0, -1.0};
  constexpr std::array<double, 4> kE3{1.0, -1.0, 1.0, -1.0};
  // d' = +d2
  const double cos_theta = (d2s + d1 * d3) / ((d1 + d3) * d2);
  const double sin_theta_abs = root / ((d1 + d3) * d2);
  for (std::size_t k = 0; k < kE1.size(); ++k) {
    const double x1 = kE1[k] * x1_abs;
    const double x3 = kE3[k] * x3_abs;
    const double sin_theta = kE1[k] * kE3[k] * sin_theta_abs;
    Eigen::Matrix3d Rp;
    Rp << cos_theta, 0.0, -sin_theta, 0.0, 1.0, 0.0, sin_theta, 0.0, cos_theta;
    const Eigen::Vector3d tp = (d1 - d3) * Eigen::Vector3d(x1, 0.0, -x3);
    out.push_back(
        {s * U * Rp * V.transpose(), U * tp, facing_away(V * Eigen::Vector3d(x1, 0.0, x3))});
  }
  // d' = -d2
  const double cos_phi = (d1 * d3 - d2s) / ((d1 - d3) * d2);
  const double sin_phi_abs = root / ((d1 - d3) * d2);
  for (std::size_t k = 0; k < kE1.size(); ++k) {
    const double x1 = kE1[k] * x1_abs;
    const double x3 = kE3[k] * x3_abs;
    const double sin_phi = kE1[k] * kE3[k] * sin_phi_abs;
    Eigen::Matrix3d Rp;
    Rp << cos_phi, 0.0, sin_phi, 0.0, -1.0, 0.0, sin_phi, 0.0, -cos_phi;
    const Eigen::Vector3d tp = (d1 + d3) * Eigen::Vector3d(x1, 0.0, x3);
    out.push_back(
        {s * U * Rp * V.transpose(), U * tp, facing_away(V * Eigen::Vector3d(x1, 0.0, x3))});
  }
}

/// What triangulating a model's inliers with one motion candidate gives.
struct CandidateCheck {
  int good = 0;        ///< consistent and seen under >= min_point_parallax_deg
  int consistent = 0;  ///< in front of both cameras with reprojection chi2 below the gate
  std::vector<double> parallax_deg;  ///< of the consistent points
  std::vector<std::uint8_t> status;  ///< per correspondence: kConsistent | kGood, or kUndecided
};

constexpr std::uint8_t kConsistent = 1;  ///< CandidateCheck::status bit
constexpr std::uint8_t kGood = 2;        ///< CandidateCheck::status bit
/// CandidateCheck::status bit: the point moved too little once the candidate's rotation is
/// taken out (it lies near the epipole) to say anything about the translation. Its ray pair
/// is nearly parallel to the baseline, so noise alone puts its triangulation behind a camera
/// or far off its pixels: it neither supports nor refutes the candidate.
constexpr std::uint8_t kUndecided = 4;
/// Rotation-compensated image motion below this many keypoint sigmas: kUndecided.
constexpr double kMinDecidableDisparitySigmas = 2.0;

/// Fast triangulation for the candidate vote (camera 0 = [I | 0], camera 1 = [R | t]):
/// midpoint of the common perpendicular of the two rays, from the 2x2 normal equations of
/// min |l0 R x0 + t - l1 x1|. False for (near-)parallel rays.
bool triangulate_midpoint(const Motion& m, const Eigen::Vector3d& x0, const Eigen::Vector3d& x1,
                          Eigen::Vector3d& p_c0) {
  const Eigen::Vector3d a = m.R * x0;
  const double aa = a.squaredNorm();
  const double bb = x1.squaredNorm();
  const double ab = a.dot(x1);
  const double det = aa * bb - ab * ab;  // |a x x1|^2
  if (!(det > kMinRayAngleSin2 * aa * bb)) return false;
  const double at = a.dot(m.t);
  const double bt = x1.dot(m.t);
  const double l0 = (ab * bt - bb * at) / det;
  const double l1 = (aa * bt - ab * at) / det;
  // Midpoint in camera 1, mapped back to camera 0.
  const Eigen::Vector3d p_c1 = 0.5 * (l0 * a + m.t + l1 * x1);
  p_c0 = m.R.transpose() * (p_c1 - m.t);
  return true;
}

/// Triangulates the inliers with candidate `m` (midpoint for the vote; DLT, as in the map,
/// when `points`/`flags` are given) and applies the cheirality, reprojection and parallax
/// tests.
void check_candidate(const Motion& m, std::span<const Eigen::Vector2d> uv0,
                     std::span<const Eigen::Vector2d> uv1, std::span<const std::uint8_t> inliers,
                     const Pinhole& K, const TwoViewOptions& o,
                     std::vector<Eigen::Vector3d>* points, std::vector<std::uint8_t>* flags,
                     CandidateCheck& c) {
  c.good = 0;
  c.consistent = 0;
  c.parallax_deg.clear();
  c.status.assign(uv0.size(), 0);
  SE3d T_c1_c0 = SE3d::Identity();
  T_c1_c0.linear() = m.R;
  T_c1_c0.translation() = m.t;
  const SE3d identity = SE3d::Identity();
  const Eigen::Vector3d c1 = -(m.R.transpose() * m.t);
  const double inv_sigma2 = 1.0 / (o.sigma_px * o.sigma_px);
  const bool final_map = points != nullptr;
  for (std::size_t i = 0; i < uv0.size(); ++i) {
    if (!inliers[i]) continue;
    const Eigen::Vector3d x0 = K.unproject(uv0[i]);
    const Eigen::Vector3d x1 = K.unproject(uv1[i]);
    const Eigen::Vector3d x0_rotated = m.R * x0;
    if (x0_rotated.z() > 0.0 && (K.project(x0_rotated) - uv1[i]).squaredNorm() * inv_sigma2 <
                                    kMinDecidableDisparitySigmas * kMinDecidableDisparitySigmas) {
      c.status[i] = kUndecided;
      continue;
    }
    Eigen::Vector3d X;
    const bool ok = final_map ? triangulate_two_view(identity, T_c1_c0, x0, x1, X)
                              : triangulate_midpoint(m, x0, x1, X);
    if (!ok) continue;
    const Eigen::Vector3d X1 = T_c1_c0 * X;
    if (!(X.z() > 0.0) || !(X1.z() > 0.0)) continue;
    if ((K.project(X) - uv0[i]).squaredNorm() * inv_sigma2 > kChi2TwoDof95) continue;
    if ((K.project(X1) - uv1[i]).squaredNorm() * inv_sigma2 > kChi2TwoDof95) continue;
    ++c.consistent;
    c.status[i] = kConsistent;
    const double par = parallax_deg(X, Eigen::Vector3d::Zero(), c1);
    c.parallax_deg.push_back(par);
    if (par < o.min_point_parallax_deg) continue;
    ++c.good;
    c.status[i] |= kGood;
    if (final_map) (*points)[i] = X;
    if (flags != nullptr) (*flags)[i] = 1;
  }
}

/// Pixel fundamental matrix K^-T [t]x R K^-1 of a motion.
Eigen::Matrix3d fundamental_from_motion(const Motion& m, const Eigen::Matrix3d& K) {
  Eigen::Matrix3d t_x;
  t_x << 0.0, -m.t.z(), m.t.y(), m.t.z(), 0.0, -m.t.x(), -m.t.y(), m.t.x(), 0.0;
  const Eigen::Matrix3d Ki = K.inverse();
  return Ki.transpose() * t_x * m.R * Ki;
}

/// Orthonormal 3x2 basis of the plane orthogonal to unit vector `t`.
Eigen::Matrix<double, 3, 2> tangent_basis(const Eigen::Vector3d& t) {
  const Eigen::Vector3d helper =
      std::abs(t.x()) < std::abs(t.y()) ? Eigen::Vector3d::UnitX() : Eigen::Vector3d::UnitY();
  Eigen::Matrix<double, 3, 2> B;
  B.col(0) = t.cross(helper).normalized();
  B.col(1) = t.cross(B.col(0));
  return B;
}

using Vector5d = Eigen::Matrix<double, 5, 1>;
using Matrix5d = Eigen::Matrix<double, 5, 5>;

/// Motion moved by `d` = (rotation vector applied on the left, 2 tangent steps of unit t).
Motion perturb(const Motion& m, const Vector5d& d) {
  Motion out;
  const Eigen::Vector3d w = d.head<3>();
  const double angle = w.norm();
  out.R = angle > 0.0 ? Eigen::Matrix3d(Eigen::AngleAxisd(angle, w / angle) * m.R) : m.R;
  out.t = (m.t + tangent_basis(m.t) * d.tail<2>()).normalized();
  return out;
}

/// Sampson residuals (px) of the epipolar constraint of motion `m` on the listed
/// correspondences; returns the sum of squares.
double sampson_residuals(const Motion& m, const Eigen::Matrix3d& Ki,
                         std::span<const Eigen::Vector2d> uv0, std::span<const Eigen::Vector2d> uv1,
                         std::span<const std::size_t> idx, Eigen::Map<Eigen::VectorXd>& r) {
  const Eigen::Matrix3d F = fundamental_from_motion(m, Ki.inverse());
  for (std::size_t k = 0; k < idx.size(); ++k) {
    const Eigen::Vector3d x0 = uv0[idx[k]].homogeneous();
    const Eigen::Vector3d x1 = uv1[idx[k]].homogeneous();
    const Eigen::Vector3d l1 = F * x0;
    const Eigen::Vector3d l0 = F.transpose() * x1;
    const double den = l1.head<2>().squaredNorm() + l0.head<2>().squaredNorm();
    r(static_cast<Eigen::Index>(k)) = den > 0.0 ? x1.dot(l1) / std::sqrt(den) : 0.0;
  }
  return r.squaredNorm();
}

/// Levenberg-Marquardt on the Sampson error of the inliers over the 5-dof motion (the linear
/// 8-point F minimizes an algebraic error, biased with noise; this is close to the
/// maximum-likelihood estimate). Forward-difference Jacobian: 5 extra residual passes per
/// iteration, cheap next to RANSAC.
/// 1-sigma uncertainty of a refined motion (from the Gauss-Newton normal matrix).
struct MotionSigma {
  double rotation_deg = std::numeric_limits<double>::infinity();
  double translation_dir_deg = std::numeric_limits<double>::infinity();
};

/// Buffers of refine_motion (capacity: the correspondences).
struct RefineScratch {
  std::vector<std::size_t> idx;
  std::vector<double> r;
  std::vector<double> r_try;
  std::vector<double> J;
  void reserve(std::size_t n) {
    idx.reserve(n);
    r.reserve(n);
    r_try.reserve(n);
    J.reserve(5 * n);
  }
};

MotionSigma refine_motion(Motion& m, std::span<const Eigen::Vector2d> uv0,
                          std::span<const Eigen::Vector2d> uv1,
                          std::span<const std::uint8_t> inliers, const Pinhole& K, double sigma_px,
                          RefineScratch& s) {
  MotionSigma sigma;
  std::vector<std::size_t>& idx = s.idx;
  idx.clear();
  for (std::size_t i = 0; i < inliers.size(); ++i) {
    if (inliers[i]) idx.push_back(i);
  }
  if (idx.size() < static_cast<std::size_t>(kSampleSize)) return sigma;
  const Eigen::Matrix3d Ki = k_matrix(K).inverse();
  const auto n = static_cast<Eigen::Index>(idx.size());
  s.r.resize(idx.size());
  s.r_try.resize(idx.size());
  s.J.resize(5 * idx.size());
  // Views of the buffers (r and r_try swap buffers when a step is taken).
  double* r_buf = s.r.data();
  double* r_try_buf = s.r_try.data();
  const auto view = [n](double* p) { return Eigen::Map<Eigen::VectorXd>(p, n); };
  Eigen::Map<Eigen::MatrixXd> J(s.J.data(), n, 5);
  const auto jacobian = [&] {
    for (int k = 0; k < 5; ++k) {
      Vector5d d = Vector5d::Zero();
      d(k) = kLmJacobianStep;
      Eigen::Map<Eigen::VectorXd> r_try = view(r_try_buf);
      sampson_residuals(perturb(m, d), Ki, uv0, uv1, idx, r_try);
      J.col(k) = (r_try - view(r_buf)) / kLmJacobianStep;
    }
  };
  Eigen::Map<Eigen::VectorXd> r0 = view(r_buf);
  double cost = sampson_residuals(m, Ki, uv0, uv1, idx, r0);
  double lambda = kLmInitialDamping;
  bool converged = false;
  for (int it = 0; it < kLmMaxIterations && !converged; ++it) {
    jacobian();
    const Matrix5d jtj = J.transpose() * J;
    const Vector5d g = J.transpose() * view(r_buf);
    bool improved = false;
    while (!improved && lambda < kLmMaxDamping) {
      Matrix5d A = jtj;
      A.diagonal() *= 1.0 + lambda;
      const Vector5d d = A.ldlt().solve(-g);
      const Motion candidate = perturb(m, d);
      Eigen::Map<Eigen::VectorXd> r_try = view(r_try_buf);
      const double c = sampson_residuals(candidate, Ki, uv0, uv1, idx, r_try);
      if (c < cost) {
        improved = true;
        converged = (cost - c) / cost < kLmMinRelativeDecrease;
        m = candidate;
        cost = c;
        std::swap(r_buf, r_try_buf);
        lambda *= kLmDampingDown;
      } else {
        lambda *= kLmDampingUp;
      }
    }
    converged = converged || !improved;
  }
  // Covariance sigma^2 (J^T J)^-1 at the optimum (Sampson residuals have ~ keypoint variance).
  jacobian();
  const Matrix5d jtj = J.transpose() * J;
  const Eigen::FullPivLU<Matrix5d> lu(jtj);
  if (!lu.isInvertible()) return sigma;
  const Matrix5d cov = sigma_px * sigma_px * lu.inverse();
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> es_r(cov.topLeftCorner<3, 3>());
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix2d> es_t(cov.bottomRightCorner<2, 2>());
  sigma.rotation_deg = std::sqrt(std::max(es_r.eigenvalues().maxCoeff(), 0.0)) * kRadToDeg;
  sigma.translation_dir_deg = std::sqrt(std::max(es_t.eigenvalues().maxCoeff(), 0.0)) * kRadToDeg;
  return sigma;
}

/// Upper median of v (0 when empty), reordering a copy in `scratch`.
double median_of(std::span<const double> v, std::vector<double>& scratch) {
  scratch.assign(v.begin(), v.end());
  return upper_median(scratch);
}

/// Whether the rotation-only model x1 ~ K R K^-1 x0 maps uv0 onto uv1 within the chi2 gate
/// (`inv_var`: 1 / the variance of a two-image residual).
bool explained_by_rotation(const Eigen::Matrix3d& R, const Pinhole& K, const Eigen::Vector2d& uv0,
                           const Eigen::Vector2d& uv1, double inv_var) {
  const Eigen::Vector3d p = R * K.unproject(uv0);
  return p.z() > 0.0 && (K.project(p) - uv1).squaredNorm() * inv_var <= kChi2TwoDof95;
}

/// Inliers of the best rotation-only model x1 ~ K R K^-1 x0, fitted (orthogonal Procrustes
/// on bearing vectors) to the homography inliers; the rotation goes to `R_out`.
int rotation_only_inliers(std::span<const Eigen::Vector2d> uv0,
                          std::span<const Eigen::Vector2d> uv1,
                          std::span<const std::uint8_t> inliers_h, const Pinhole& K,
                          double sigma_px, Eigen::Matrix3d& R_out) {
  Eigen::Matrix3d M = Eigen::Matrix3d::Zero();
  for (std::size_t i = 0; i < uv0.size(); ++i) {
    if (inliers_h[i]) M += K.bearing(uv1[i]) * K.bearing(uv0[i]).transpose();
  }
  R_out = nearest_rotation(M);
  const double inv_var = 1.0 / (kResidualVarianceFactor * sigma_px * sigma_px);
  int count = 0;
  for (std::size_t i = 0; i < uv0.size(); ++i) {
    if (explained_by_rotation(R_out, K, uv0[i], uv1[i], inv_var)) ++count;
  }
  return count;
}

/// Refits a rotation-only model to every correspondence it explains (chi2 gate on the pixel
/// error), from `R`, `rounds` times (as LO-RANSAC's local optimization): the homography's
/// inliers it started from can hold a few wrong matches of a repeated texture.
void refine_rotation(std::span<const Eigen::Vector2d> uv0, std::span<const Eigen::Vector2d> uv1,
                     const Pinhole& K, double sigma_px, int rounds, Eigen::Matrix3d& R) {
  const double inv_var = 1.0 / (kResidualVarianceFactor * sigma_px * sigma_px);
  for (int round = 0; round < rounds; ++round) {
    Eigen::Matrix3d M = Eigen::Matrix3d::Zero();
    int count = 0;
    for (std::size_t i = 0; i < uv0.size(); ++i) {
      if (!explained_by_rotation(R, K, uv0[i], uv1[i], inv_var)) continue;
      M += K.bearing(uv1[i]) * K.bearing(uv0[i]).transpose();
      ++count;
    }
    if (count < kHomographySampleSize) return;
    R = nearest_rotation(M);
  }
}

/// A refused result: no map (the diagnostics filled so far are kept).
void refuse(TwoViewResult& r, TwoViewRefusal why) {
  r.ok = false;
  r.refusal = why;
  r.T_c1_c0 = SE3d::Identity();
  r.points_c0.clear();
  r.triangulated.clear();
  r.num_triangulated = 0;
}

/// r as default-constructed, its vectors emptied but keeping their capacity.
void reset_keeping_capacity(TwoViewResult& r) {
  std::vector<Eigen::Vector3d> points = std::move(r.points_c0);
  std::vector<std::uint8_t> triangulated = std::move(r.triangulated);
  std::vector<Eigen::Vector3d> normals = std::move(r.plane_normals_c0);
  std::vector<SE3d> motions = std::move(r.candidate_motions);
  r = TwoViewResult{};
  points.clear();
  triangulated.clear();
  normals.clear();
  motions.clear();
  r.points_c0 = std::move(points);
  r.triangulated = std::move(triangulated);
  r.plane_normals_c0 = std::move(normals);
  r.candidate_motions = std::move(motions);
}

}  // namespace

const char* to_string(TwoViewRefusal r) {
  switch (r) {
    case TwoViewRefusal::kNone:
      return "none";
    case TwoViewRefusal::kTooFewMatches:
      return "too_few_matches";
    case TwoViewRefusal::kStatic:
      return "static";
    case TwoViewRefusal::kPureRotation:
      return "pure_rotation";
    case TwoViewRefusal::kLowParallax:
      return "low_parallax";
    case TwoViewRefusal::kTooFewTriangulated:
      return "too_few_triangulated";
    case TwoViewRefusal::kAmbiguous:
      return "ambiguous";
    case TwoViewRefusal::kUncertainMotion:
      return "uncertain_motion";
  }
  return "unknown";
}

const char* to_string(TwoViewModel m) {
  switch (m) {
    case TwoViewModel::kNone:
      return "none";
    case TwoViewModel::kHomography:
      return "homography";
    case TwoViewModel::kEssential:
      return "essential";
  }
  return "unknown";
}

namespace {

/// Essential fallback for an ambiguous homography: at most this fraction of the F inliers
/// may lie on the homography's plane.
constexpr double kEssentialFallbackMaxPlanarFraction = 0.85;

}  // namespace

/// Every buffer of a reconstruction (TwoViewWorkspace).
struct TwoViewWorkspace::Buffers {
  FitScratch fit_scratch;
  TwoViewModelFit fit;
  ParallaxScratch parallax_scratch;
  PlaneParallaxFit pp;
  RefineScratch refine;
  MotionList candidates;
  std::array<CandidateCheck, MotionList::kCapacity> checks;
  CandidateCheck final_check;
  std::vector<double> values;  // disparities, depths
  std::vector<double> median;  // median_of's copy
  std::vector<std::uint8_t> refined_inliers;
  std::vector<std::uint8_t> mask;
  TwoViewResult retry;  // the essential model's try after an ambiguous homography

  void reserve(std::size_t n) {
    fit_scratch.reserve(n, fit);
    parallax_scratch.reserve(n, pp);
    refine.reserve(n);
    for (CandidateCheck& c : checks) reserve_check(c, n);
    reserve_check(final_check, n);
    values.reserve(n);
    median.reserve(n);
    refined_inliers.reserve(n);
    mask.reserve(n);
    reserve_result(retry, n);
  }
  static void reserve_check(CandidateCheck& c, std::size_t n) {
    c.parallax_deg.reserve(n);
    c.status.reserve(n);
  }
  static void reserve_result(TwoViewResult& r, std::size_t n) {
    r.points_c0.reserve(n);
    r.triangulated.reserve(n);
    r.plane_normals_c0.reserve(MotionList::kCapacity);
    // Both models' candidates (an ambiguous homography, then the essential model's).
    r.candidate_motions.reserve(2 * MotionList::kCapacity);
  }
};

TwoViewWorkspace::TwoViewWorkspace() : b_(std::make_unique<Buffers>()) {}
TwoViewWorkspace::~TwoViewWorkspace() = default;
TwoViewWorkspace::TwoViewWorkspace(TwoViewWorkspace&&) noexcept = default;
TwoViewWorkspace& TwoViewWorkspace::operator=(TwoViewWorkspace&&) noexcept = default;

void TwoViewWorkspace::reserve(std::size_t max_correspondences, TwoViewResult& out) {
  b_->reserve(max_correspondences);
  Buffers::reserve_result(out, max_correspondences);
}

namespace {

void reconstruct_impl(std::span<const Eigen::Vector2d> uv0, std::span<const Eigen::Vector2d> uv1,
                      const Pinhole& K, const TwoViewOptions& o, bool force_essential,
                      std::span<const Eigen::Vector3d> plane_hints, TwoViewWorkspace::Buffers& ws,
                      TwoViewResult& r) {
  reset_keeping_capacity(r);
  const std::size_t n = uv0.size();
  if (uv1.size() != n || n < static_cast<std::size_t>(std::max(o.min_matches, kSampleSize))) {
    return refuse(r, TwoViewRefusal::kTooFewMatches);
  }

  // 1. Static scene: the camera did not move (or barely).
  ws.values.resize(n);
  for (std::size_t i = 0; i < n; ++i) ws.values[i] = (uv1[i] - uv0[i]).norm();
  r.median_disparity_px = median_of(ws.values, ws.median);
  if (r.median_disparity_px < o.min_median_disparity_px) {
    return refuse(r, TwoViewRefusal::kStatic);
  }

  // 2. Both models, same samples.
  TwoViewModelFit& fit = ws.fit;
  fit_models(uv0, uv1, o.ransac_iterations, o.sigma_px, o.seed, ws.fit_scratch, fit);
  r.score_h = fit.score_h;
  r.score_f = fit.score_f;
  const int best_inliers = std::max(fit.num_inliers_h, fit.num_inliers_f);
  if (best_inliers < o.min_triangulated) {
    return refuse(r, TwoViewRefusal::kTooFewTriangulated);
  }

  // 3. Pure rotation: the image moved, but a rotation alone explains it. Then F is not
  //    unique (any F = [e]x H fits) and any "translation" is noise.
  if (fit.num_inliers_h >= kHomographySampleSize) {
    Eigen::Matrix3d R = Eigen::Matrix3d::Identity();
    const int n_rot = rotation_only_inliers(uv0, uv1, fit.inliers_h, K, o.sigma_px, R);
    if (n_rot >= kPureRotationInlierFraction * best_inliers) {
      refine_rotation(uv0, uv1, K, o.sigma_px, kRotationRefineRounds, R);
      r.rotation_c1_c0 = R;
      r.rotation_inliers = n_rot;
      return refuse(r, TwoViewRefusal::kPureRotation);
    }
  }

  // 4. Model selection and motion candidates.
  const double r_h =
      fit.score_h / std::max(fit.score_h + fit.score_f, std::numeric_limits<double>::min());
  const Eigen::Matrix3d Km = k_matrix(K);
  MotionList& candidates = ws.candidates;
  candidates.size = 0;
  std::span<const std::uint8_t> inliers;
  // The essential fallback needs points off the plane: when the homography explains nearly
  // all of F's inliers, E is as undetermined as the plane's twin solution.
  // Then F = [e1]x H from the points off the plane (plane and parallax) replaces the 8-point
  // F; without enough of them agreeing on the epipole the pair stays ambiguous.
  Eigen::Matrix3d F = fit.F;
  std::span<const std::uint8_t> inliers_f = fit.inliers_f;
  int num_inliers_f = fit.num_inliers_f;
  PlaneParallaxFit& pp = ws.pp;
  pp.F = Eigen::Matrix3d::Zero();
  pp.inliers.clear();
  pp.num_inliers = 0;
  pp.num_off_plane_inliers = 0;
  if (force_essential &&
      fit.num_inliers_h > kEssentialFallbackMaxPlanarFraction * fit.num_inliers_f) {
    if (!plane_and_parallax_fundamental(fit.H, uv0, uv1, o.sigma_px, o.ransac_iterations, o.seed,
                                        ws.parallax_scratch, pp)) {
      return refuse(r, TwoViewRefusal::kAmbiguous);
    }
    F = pp.F;
    inliers_f = pp.inliers;
    num_inliers_f = pp.num_inliers;
  }
  if (!force_essential && r_h > o.homography_ratio) {
    r.model = TwoViewModel::kHomography;
    r.num_inliers = fit.num_inliers_h;
    inliers = fit.inliers_h;
    decompose_homography(Km.inverse() * fit.H * Km, candidates);
    if (candidates.size == 0) return refuse(r, TwoViewRefusal::kPureRotation);
  } else {
    r.model = TwoViewModel::kEssential;
    r.num_inliers = num_inliers_f;
    inliers = inliers_f;
    decompose_essential(Km.transpose() * F * Km, candidates);
  }

  // 5. Cheirality / reprojection / parallax vote.
  std::size_t best = 0;
  std::array<CandidateCheck, MotionList::kCapacity>& checks = ws.checks;
  for (std::size_t k = 0; k < candidates.size; ++k) {
    check_candidate(candidates[k], uv0, uv1, inliers, K, o, nullptr, nullptr, checks[k]);
    const auto key = [](const CandidateCheck& c) { return std::pair(c.good, c.consistent); };
    if (key(checks[k]) > key(checks[best])) best = k;
  }
  r.median_parallax_deg = median_of(checks[best].parallax_deg, ws.median);
  if (r.median_parallax_deg < o.min_parallax_deg) {
    return refuse(r, TwoViewRefusal::kLowParallax);
  }
  if (checks[best].good < o.min_triangulated) {
    return refuse(r, TwoViewRefusal::kTooFewTriangulated);
  }
  // Ambiguity: another candidate consistent with nearly as many points that also agrees with
  // (almost) all of the winner's good points. A candidate that puts a fraction of the
  // winner's well-triangulated points behind a camera or off their pixels is refuted by them
  // (they are model inliers; chance outliers among them are rare), e.g. the twin solution of
  // a homography whose virtual plane crosses the field of view. The pre-filter counts
  // consistent points, not good ones: under forward motion the true decomposition sees less
  // parallax than its twin (which moves sideways), so fewer of its points pass the parallax
  // bar, though it explains them all.
  std::array<std::size_t, MotionList::kCapacity> tied_buf{best};
  std::size_t num_tied = 1;
  for (std::size_t k = 0; k < candidates.size; ++k) {
    if (k == best || checks[k].consistent <= o.ambiguity_ratio * checks[best].consistent) {
      continue;
    }
    int refuted = 0;
    for (std::size_t i = 0; i < n; ++i) {
      if ((checks[best].status[i] & kGood) && !(checks[k].status[i] & (kConsistent | kUndecided))) {
        ++refuted;
      }
    }
    if (refuted < kMinRefutedFraction * checks[best].good) tied_buf[num_tied++] = k;
  }
  const std::span<const std::size_t> tied(tied_buf.data(), num_tied);
  if (tied.size() > 1) {
    const bool planar = r.model == TwoViewModel::kHomography;
    const std::optional<std::size_t> winner =
        planar ? tie_broken_by_plane_hints(candidates.span(), tied, plane_hints, o) : std::nullopt;
    if (!winner) {
      if (planar && r.median_parallax_deg >= o.plane_hint_min_parallax_deg) {
        for (const std::size_t k : tied) r.plane_normals_c0.push_back(candidates[k].n);
      }
      for (const std::size_t k : tied) r.candidate_motions.push_back(unit_motion(candidates[k]));
      return refuse(r, TwoViewRefusal::kAmbiguous);
    }
    if (*winner != best) {
      best = *winner;
      r.median_parallax_deg = median_of(checks[best].parallax_deg, ws.median);
      if (r.median_parallax_deg < o.min_parallax_deg) {
        return refuse(r, TwoViewRefusal::kLowParallax);
      }
      if (checks[best].good < o.min_triangulated) {
        return refuse(r, TwoViewRefusal::kTooFewTriangulated);
      }
    }
  }

  // 6. Essential model: refine the winning motion on the Sampson error (the 8-point F is an
  //    algebraic fit, and its inlier set was gated with that biased F), re-gate all
  //    correspondences with the refined motion and repeat until the inlier set settles
  //    (local optimization, as in LO-RANSAC). The homography is kept as decomposed: its DLT
  //    fit on a plane is already constrained by every inlier in both images.
  std::vector<std::uint8_t>& refined_inliers = ws.refined_inliers;
  if (r.model == TwoViewModel::kEssential) {
    const double inv_var = 1.0 / (kResidualVarianceFactor * o.sigma_px * o.sigma_px);
    refined_inliers.assign(inliers.begin(), inliers.end());
    std::vector<std::uint8_t>& mask = ws.mask;
    mask.assign(n, 0);
    for (int round = 0; round < kLocalOptimizationRounds; ++round) {
      const MotionSigma sig =
          refine_motion(candidates[best], uv0, uv1, refined_inliers, K, o.sigma_px, ws.refine);
      r.rotation_sigma_deg = sig.rotation_deg;
      r.translation_dir_sigma_deg = sig.translation_dir_deg;
      int count = 0;
      score_fundamental(fundamental_from_motion(candidates[best], Km), uv0, uv1, inv_var,
                        -std::numeric_limits<double>::infinity(), mask, count);
      if (mask == refined_inliers) break;
      refined_inliers.swap(mask);
      r.num_inliers = count;
    }
    inliers = refined_inliers;
  }

  // 7. Map of the winner, scaled to median depth 1 in camera 0.
  r.points_c0.assign(n, Eigen::Vector3d::Zero());
  r.triangulated.assign(n, 0);
  CandidateCheck& final_check = ws.final_check;
  check_candidate(candidates[best], uv0, uv1, inliers, K, o, &r.points_c0, &r.triangulated,
                  final_check);
  r.num_triangulated = final_check.good;
  // The refined motion and the DLT points must pass the same tests as the vote.
  r.median_parallax_deg = median_of(final_check.parallax_deg, ws.median);
  if (r.median_parallax_deg < o.min_parallax_deg) {
    return refuse(r, TwoViewRefusal::kLowParallax);
  }
  // The plane-and-parallax F rests on the few points off the plane: it must show a sharp
  // translation direction whatever the parallax.
  const bool from_plane_parallax = pp.num_inliers > 0;
  if ((r.median_parallax_deg < o.confident_parallax_deg || from_plane_parallax) &&
      (r.model != TwoViewModel::kEssential ||
       r.translation_dir_sigma_deg > o.max_translation_dir_sigma_deg)) {
    r.candidate_motions.push_back(unit_motion(candidates[best]));
    return refuse(r, TwoViewRefusal::kUncertainMotion);
  }
  if (final_check.good < o.min_triangulated) {
    return refuse(r, TwoViewRefusal::kTooFewTriangulated);
  }
  std::vector<double>& depths = ws.values;
  depths.clear();
  for (std::size_t i = 0; i < n; ++i) {
    if (r.triangulated[i]) depths.push_back(r.points_c0[i].z());
  }
  const double scale = 1.0 / median_of(depths, ws.median);
  for (std::size_t i = 0; i < n; ++i) {
    if (r.triangulated[i]) r.points_c0[i] *= scale;
  }
  r.T_c1_c0 = SE3d::Identity();
  r.T_c1_c0.linear() = candidates[best].R;
  r.T_c1_c0.translation() = candidates[best].t * scale;
  r.ok = true;
}

}  // namespace

TwoViewResult reconstruct_two_view(std::span<const Eigen::Vector2d> uv0,
                                   std::span<const Eigen::Vector2d> uv1, const Pinhole& K,
                                   const TwoViewOptions& o,
                                   std::span<const Eigen::Vector3d> plane_hints) {
  TwoViewWorkspace ws;
  TwoViewResult r;
  reconstruct_two_view(uv0, uv1, K, o, plane_hints, ws, r);
  return r;
}

void reconstruct_two_view(std::span<const Eigen::Vector2d> uv0,
                          std::span<const Eigen::Vector2d> uv1, const Pinhole& K,
                          const TwoViewOptions& o, std::span<const Eigen::Vector3d> plane_hints,
                          TwoViewWorkspace& ws, TwoViewResult& r) {
  TwoViewWorkspace::Buffers& b = *ws.b_;
  reconstruct_impl(uv0, uv1, K, o, false, plane_hints, b, r);
  // A homography preferred by the scores can still be ambiguous (a dominant plane seen
  // under forward-ish motion has two physically valid decompositions) while the points off
  // the plane (boxes in front of a wall, another wall) pin down the essential matrix: try
  // the essential model before refusing. Its own checks (parallax, cheirality, ambiguity)
  // still apply, so a truly degenerate pair is refused either way.
  if (!r.ok && r.model == TwoViewModel::kHomography &&
      (r.refusal == TwoViewRefusal::kAmbiguous ||
       r.refusal == TwoViewRefusal::kTooFewTriangulated)) {
    TwoViewResult& e = b.retry;
    reconstruct_impl(uv0, uv1, K, o, true, plane_hints, b, e);
    if (e.ok) {
      std::swap(r, e);  // (both keep their buffers)
      return;
    }
    r.candidate_motions.insert(r.candidate_motions.end(), e.candidate_motions.begin(),
                               e.candidate_motions.end());
  }
}

}  // namespace mer::geometry
