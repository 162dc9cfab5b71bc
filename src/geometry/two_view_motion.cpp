// The motion candidates of a two-view reconstruction, their vote and the essential model's
// refinement (two_view_motion.h).
#include "geometry/two_view_motion.h"

#include <algorithm>
#include <cmath>
#include <numbers>

#include <Eigen/Eigenvalues>
#include <Eigen/LU>
#include <Eigen/SVD>

#include "geometry/triangulation.h"
#include "geometry/two_view_models.h"

namespace mer::geometry::two_view_detail {
namespace {

/// Homography singular values closer than this (relative) count as equal: the homography is a
/// rotation (no translation) or degenerate, and its decomposition is undefined.
constexpr double kMinSingularGap = 1e-6;
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

/// Rotation-compensated image motion below this many keypoint sigmas: kUndecided.
constexpr double kMinDecidableDisparitySigmas = 2.0;

Eigen::Vector3d facing_away(const Eigen::Vector3d& n) {
  return n.z() < 0.0 ? Eigen::Vector3d(-n) : n;
}

/// Angle between two unit normals (either sign), deg.
double normal_angle_deg(const Eigen::Vector3d& a, const Eigen::Vector3d& b) {
  return std::acos(std::min(1.0, std::abs(a.dot(b)))) * kRadToDeg;
}

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

}  // namespace

/// Camera 1 from camera 0 with a unit translation.
SE3d unit_motion(const Motion& m) {
  SE3d T = SE3d::Identity();
  T.linear() = m.R;
  const double norm = m.t.norm();
  T.translation() = norm > 0.0 ? Eigen::Vector3d(m.t / norm) : m.t;
  return T;
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

}  // namespace mer::geometry::two_view_detail
