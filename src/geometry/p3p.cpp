#include "geometry/p3p.h"

#include <algorithm>
#include <cmath>
#include <numbers>

#include <Eigen/Geometry>
#include <Eigen/LU>

namespace mer::geometry {
namespace {

/// World triangles whose two edges from X1 make an angle with sine below this are treated
/// as collinear (the pose is not defined, the triangle alignment divides by ~0).
constexpr double kMinTriangleSine = 1e-6;
/// Bearings closer than this (1 - cos angle, ~ angle^2 / 2; 1e-12 ~ 1.4 micro-rad) are
/// treated as coincident.
constexpr double kMinBearingSeparation = 1e-12;
/// Cubic leading coefficients below this fraction of the largest coefficient are dropped
/// (the cubic degrades to a quadratic: one root went to infinity).
constexpr double kCubicLeadingEps = 1e-14;
/// Newton steps polishing each closed-form cubic root.
constexpr int kCubicNewtonSteps = 2;
/// A degenerate conic is accepted as a real line pair when the product of its two non-zero
/// eigenvalues, relative to its squared Frobenius norm, is below -this.
constexpr double kMinLinePairness = 1e-12;
/// Discriminants of the line-conic quadratic down to -this (relative) are rounded to 0
/// (a tangent intersection perturbed by rounding).
constexpr double kDiscriminantTol = 1e-10;
/// Depths (in units of the normalised triangle size) must exceed this.
constexpr double kMinDepth = 1e-9;
/// Gauss-Newton steps polishing the depths on the three distance equations.
constexpr int kDepthRefineSteps = 5;
/// Stop polishing when the squared residual (normalised units) is below this.
constexpr double kDepthRefineTol = 1e-28;
/// Jacobians of the depth equations with |det| below this are not inverted.
constexpr double kMinJacobianDet = 1e-14;

/// Real roots of c3 x^3 + c2 x^2 + c1 x + c0 (leading coefficient may be ~0); returns count.
int solve_cubic(double c3, double c2, double c1, double c0, std::array<double, 3>& roots) {
  const double scale = std::max({std::abs(c3), std::abs(c2), std::abs(c1), std::abs(c0)});
  if (scale == 0.0) return 0;
  if (std::abs(c3) <= kCubicLeadingEps * scale) {
    // Quadratic c2 x^2 + c1 x + c0.
    if (std::abs(c2) <= kCubicLeadingEps * scale) {
      if (std::abs(c1) <= kCubicLeadingEps * scale) return 0;
      roots[0] = -c0 / c1;
      return 1;
    }
    const double disc = c1 * c1 - 4.0 * c2 * c0;
    if (disc < 0.0) return 0;
    const double q = -0.5 * (c1 + std::copysign(std::sqrt(disc), c1));
    roots[0] = q / c2;
    if (q == 0.0) return 1;
    roots[1] = c0 / q;
    return 2;
  }
  const double a = c2 / c3;
  const double b = c1 / c3;
  const double c = c0 / c3;
  // Depressed cubic x^3 + p x + q with t = x - a / 3.
  const double a3 = a / 3.0;
  const double p = b - a * a3;
  const double q = 2.0 * a3 * a3 * a3 - a3 * b + c;
  const double half_q = 0.5 * q;
  const double third_p = p / 3.0;
  const double disc = half_q * half_q + third_p * third_p * third_p;
  int n = 0;
  if (disc > 0.0) {
    // One real root (Cardano, written to avoid cancellation).
    const double u = std::cbrt(-half_q - std::copysign(std::sqrt(disc), half_q));
    roots[0] = (u != 0.0 ? u - third_p / u : 0.0) - a3;
    n = 1;
  } else if (third_p < 0.0) {
    // Three real roots (trigonometric form).
    const double r = std::sqrt(-third_p);
    const double cos_arg = std::clamp(-half_q / (r * r * r), -1.0, 1.0);
    const double phi = std::acos(cos_arg) / 3.0;
    constexpr double kTwoThirdsPi = 2.0 * std::numbers::pi / 3.0;
    for (int k = 0; k < 3; ++k) roots[k] = 2.0 * r * std::cos(phi - kTwoThirdsPi * k) - a3;
    n = 3;
  } else {
    roots[0] = -a3;  // triple root
    n = 1;
  }
  for (int k = 0; k < n; ++k) {
    double& x = roots[k];
    for (int it = 0; it < kCubicNewtonSteps; ++it) {
      const double f = ((x + a) * x + b) * x + c;
      const double df = (3.0 * x + 2.0 * a) * x + b;
      if (df == 0.0) break;
      x -= f / df;
    }
  }
  return n;
}

/// Adjugate of a symmetric 3x3 matrix (symmetric too).
Eigen::Matrix3d adjugate(const Eigen::Matrix3d& A) {
  Eigen::Matrix3d C;
  C(0, 0) = A(1, 1) * A(2, 2) - A(1, 2) * A(2, 1);
  C(0, 1) = A(0, 2) * A(2, 1) - A(0, 1) * A(2, 2);
  C(0, 2) = A(0, 1) * A(1, 2) - A(0, 2) * A(1, 1);
  C(1, 1) = A(0, 0) * A(2, 2) - A(0, 2) * A(2, 0);
  C(1, 2) = A(0, 2) * A(1, 0) - A(0, 0) * A(1, 2);
  C(2, 2) = A(0, 0) * A(1, 1) - A(0, 1) * A(1, 0);
  C(1, 0) = C(0, 1);
  C(2, 0) = C(0, 2);
  C(2, 1) = C(1, 2);
  return C;
}

/// Sum of the principal 2x2 minors (= product of the two non-zero eigenvalues when singular).
double principal_minor_sum(const Eigen::Matrix3d& D) {
  return D(0, 0) * D(1, 1) - D(0, 1) * D(0, 1) + D(0, 0) * D(2, 2) - D(0, 2) * D(0, 2) +
         D(1, 1) * D(2, 2) - D(1, 2) * D(1, 2);
}

/// Unit vector spanning the (approximate) null space of a rank-2 3x3 matrix: the largest
/// cross product of two of its rows. Returns false when the matrix has rank < 2.
bool null_vector(const Eigen::Matrix3d& M, Eigen::Vector3d& v) {
  const Eigen::Vector3d c01 = M.row(0).transpose().cross(M.row(1).transpose());
  const Eigen::Vector3d c02 = M.row(0).transpose().cross(M.row(2).transpose());
  const Eigen::Vector3d c12 = M.row(1).transpose().cross(M.row(2).transpose());
  const double n01 = c01.squaredNorm();
  const double n02 = c02.squaredNorm();
  const double n12 = c12.squaredNorm();
  if (n01 >= n02 && n01 >= n12) {
    v = c01;
  } else if (n02 >= n12) {
    v = c02;
  } else {
    v = c12;
  }
  const double n = v.norm();
  if (!(n > 0.0)) return false;
  v /= n;
  return true;
}

/// Two unit vectors p, q completing the unit vector n to an orthonormal basis.
void orthonormal_complement(const Eigen::Vector3d& n, Eigen::Vector3d& p, Eigen::Vector3d& q) {
  Eigen::Index k = 0;
  n.cwiseAbs().minCoeff(&k);
  p = n.cross(Eigen::Vector3d::Unit(k)).normalized();
  q = n.cross(p);
}

/// Distance equations |li yi - lj yj|^2 = a_ij in normalised units.
struct DepthProblem {
  double a12, a13, a23;  // squared world distances
  double b12, b13, b23;  // bearing cosines

  Eigen::Vector3d residual(const Eigen::Vector3d& l) const {
    return {l(0) * l(0) + l(1) * l(1) - 2.0 * b12 * l(0) * l(1) - a12,
            l(0) * l(0) + l(2) * l(2) - 2.0 * b13 * l(0) * l(2) - a13,
            l(1) * l(1) + l(2) * l(2) - 2.0 * b23 * l(1) * l(2) - a23};
  }
  Eigen::Matrix3d jacobian(const Eigen::Vector3d& l) const {
    Eigen::Matrix3d J;
    J << 2.0 * (l(0) - b12 * l(1)), 2.0 * (l(1) - b12 * l(0)), 0.0,  //
        2.0 * (l(0) - b13 * l(2)), 0.0, 2.0 * (l(2) - b13 * l(0)),   //
        0.0, 2.0 * (l(1) - b23 * l(2)), 2.0 * (l(2) - b23 * l(1));
    return J;
  }
  /// Gauss-Newton polish; keeps only improving steps.
  void refine(Eigen::Vector3d& l) const {
    Eigen::Vector3d r = residual(l);
    double cost = r.squaredNorm();
    for (int it = 0; it < kDepthRefineSteps && cost > kDepthRefineTol; ++it) {
      const Eigen::Matrix3d J = jacobian(l);
      const double det = J.determinant();
      if (!(std::abs(det) > kMinJacobianDet)) break;
      const Eigen::Vector3d l_new = l - J.inverse() * r;
      const Eigen::Vector3d r_new = residual(l_new);
      const double cost_new = r_new.squaredNorm();
      if (!(cost_new < cost)) break;
      l = l_new;
      r = r_new;
      cost = cost_new;
    }
  }
};

/// The conic pencil of the depth problem and its degenerate member. L^T M_ij L = a_ij with
/// M12 = [1 -b12 0; -b12 1 0; 0 0 0] etc.; D1 = a23 M12 - a12 M23 and D2 = a23 M13 - a13 M23
/// are homogeneous: L^T D1 L = L^T D2 L = 0. D0 is the pencil's best-conditioned line pair
/// (a real root of det(u D1 + v D2) = 0), D3 the member least like D0. False: no line pair.
bool degenerate_member(const DepthProblem& dp, Eigen::Matrix3d& D0, Eigen::Matrix3d& D3) {
  Eigen::Matrix3d D1;
  D1 << dp.a23, -dp.a23 * dp.b12, 0.0,                     //
      -dp.a23 * dp.b12, dp.a23 - dp.a12, dp.a12 * dp.b23,  //
      0.0, dp.a12 * dp.b23, -dp.a12;
  Eigen::Matrix3d D2;
  D2 << dp.a23, 0.0, -dp.a23 * dp.b13,  //
      0.0, -dp.a13, dp.a13 * dp.b23,    //
      -dp.a23 * dp.b13, dp.a13 * dp.b23, dp.a23 - dp.a13;
  // det(u D1 + v D2) = u^3 det D1 + u^2 v tr(adj(D1) D2) + u v^2 tr(adj(D2) D1) + v^3 det D2.
  const double k0 = D1.determinant();
  const double k1 = (adjugate(D1).cwiseProduct(D2)).sum();
  const double k2 = (adjugate(D2).cwiseProduct(D1)).sum();
  const double k3 = D2.determinant();
  // Solve in the orientation with the larger leading coefficient (roots stay bounded).
  const bool in_gamma = std::abs(k3) >= std::abs(k0);  // D0 = D1 + g D2, else D0 = g D1 + D2
  std::array<double, 3> roots{};
  const int num_roots =
      in_gamma ? solve_cubic(k3, k2, k1, k0, roots) : solve_cubic(k0, k1, k2, k3, roots);
  // Of the real roots, take the one whose line pair is best conditioned.
  double best_pairness = -kMinLinePairness;
  double best_root = 0.0;
  bool found = false;
  for (int k = 0; k < num_roots; ++k) {
    const Eigen::Matrix3d D =
        in_gamma ? Eigen::Matrix3d(D1 + roots[k] * D2) : Eigen::Matrix3d(roots[k] * D1 + D2);
    const double norm2 = D.squaredNorm();
    if (!(norm2 > 0.0)) continue;
    const double pairness = principal_minor_sum(D) / norm2;
    if (pairness < best_pairness) {
      best_pairness = pairness;
      best_root = roots[k];
      D0 = D;
      found = true;
    }
  }
  if (!found) return false;
  const bool d0_mostly_d1 = in_gamma ? std::abs(best_root) <= 1.0 : std::abs(best_root) >= 1.0;
  D3 = d0_mostly_d1 ? D2 : D1;
  return true;
}

/// Splits the line pair D0 = s+ e+ e+^T + s- e- e-^T (normalized in place): its lines are
/// n . L = 0 with n = e+ -+ slope e-. False: degenerate.
bool split_line_pair(Eigen::Matrix3d& D0, Eigen::Vector3d& e_pos, Eigen::Vector3d& e_neg,
                     double& slope) {
  D0 /= std::sqrt(D0.squaredNorm());
  const double tr = D0.trace();
  const double m = principal_minor_sum(D0);  // s+ * s- < 0
  const double root_disc = std::sqrt(tr * tr - 4.0 * m);
  // Larger-magnitude eigenvalue computed directly, the other from the product (stable).
  const double s_big = 0.5 * (tr + std::copysign(root_disc, tr == 0.0 ? 1.0 : tr));
  const double s_small = m / s_big;
  const double s_pos = std::max(s_big, s_small);
  const double s_neg = std::min(s_big, s_small);
  Eigen::Vector3d e0;  // null vector of D0
  if (!null_vector(D0, e0)) return false;
  if (!null_vector(D0 - s_pos * Eigen::Matrix3d::Identity(), e_pos)) return false;
  e_pos -= e_pos.dot(e0) * e0;  // enforce orthogonality against rounding
  e_pos.normalize();
  e_neg = e0.cross(e_pos);
  // s+ u+^2 + s- u-^2 = 0  =>  u+ = +-sqrt(-s- / s+) u-
  slope = std::sqrt(-s_neg / s_pos);
  return true;
}

/// The world triangle as the camera sees it: its frame X (two sides and the normal),
/// inverted for the alignment R = Y X^-1, and its centroid.
struct WorldTriangle {
  Eigen::Matrix3d frame_inv;  // X^-1
  Eigen::Vector3d centroid_w;
};

/// The camera pose from the three depths `L` along the unit bearings `y`: the rigid alignment
/// of the camera-frame triangle onto the world one. False when not finite.
bool align_triangles(const Eigen::Vector3d& L, const std::array<Eigen::Vector3d, 3>& y,
                     const WorldTriangle& w, SE3d& T) {
  const Eigen::Vector3d P1 = L(0) * y[0];
  const Eigen::Vector3d P2 = L(1) * y[1];
  const Eigen::Vector3d P3 = L(2) * y[2];
  Eigen::Matrix3d Y;
  Y.col(0) = P1 - P2;
  Y.col(1) = P1 - P3;
  Y.col(2) = Y.col(0).cross(Y.col(1));
  const Eigen::Matrix3d R0 = Y * w.frame_inv;
  if (!R0.allFinite()) return false;
  // Project onto SO(3) (R0 is a rotation up to rounding).
  const Eigen::Quaterniond quat = Eigen::Quaterniond(R0).normalized();
  T = SE3d::Identity();
  T.linear() = quat.toRotationMatrix();
  T.translation() = (P1 + P2 + P3) / 3.0 - T.linear() * w.centroid_w;
  return T.matrix().allFinite();
}

}  // namespace

int solve_p3p(const std::array<Eigen::Vector3d, 3>& bearings,
              const std::array<Eigen::Vector3d, 3>& points_w,
              std::array<SE3d, kMaxP3pSolutions>& T_c_w) {
  // ---- Input checks and normalisation ------------------------------------------------
  std::array<Eigen::Vector3d, 3> y;
  for (int i = 0; i < 3; ++i) {
    if (!bearings[i].allFinite() || !points_w[i].allFinite()) return 0;
    const double n = bearings[i].norm();
    if (!(n > 0.0)) return 0;
    y[i] = bearings[i] / n;
  }
  const Eigen::Vector3d d12 = points_w[0] - points_w[1];
  const Eigen::Vector3d d13 = points_w[0] - points_w[2];
  const Eigen::Vector3d d23 = points_w[1] - points_w[2];
  const Eigen::Vector3d normal = d12.cross(d13);
  const double a12_raw = d12.squaredNorm();
  const double a13_raw = d13.squaredNorm();
  const double a23_raw = d23.squaredNorm();
  // |d12 x d13| = |d12| |d13| sin(angle)
  if (!(normal.squaredNorm() > kMinTriangleSine * kMinTriangleSine * a12_raw * a13_raw)) return 0;
  const double b12 = y[0].dot(y[1]);
  const double b13 = y[0].dot(y[2]);
  const double b23 = y[1].dot(y[2]);
  if (b12 > 1.0 - kMinBearingSeparation || b13 > 1.0 - kMinBearingSeparation ||
      b23 > 1.0 - kMinBearingSeparation) {
    return 0;
  }
  // Work with the triangle scaled to a12 + a13 + a23 = 1 (depths scale by sqrt(scale)).
  const double scale = a12_raw + a13_raw + a23_raw;
  const DepthProblem dp{a12_raw / scale, a13_raw / scale, a23_raw / scale, b12, b13, b23};

  // ---- The conic pencil's line pair D0, and D3 to intersect its lines with -----------
  Eigen::Matrix3d D0;
  Eigen::Matrix3d D3;
  if (!degenerate_member(dp, D0, D3)) return 0;
  Eigen::Vector3d e_pos;
  Eigen::Vector3d e_neg;
  double slope = 0.0;
  if (!split_line_pair(D0, e_pos, e_neg, slope)) return 0;

  // S = M12 + M13 + M23, the sum of the three distance forms: positive definite for
  // distinct bearings, it fixes the scale of a direction L (L^T S L = a12 + a13 + a23).
  Eigen::Matrix3d S;
  S << 2.0, -b12, -b13,  //
      -b12, 2.0, -b23,   //
      -b13, -b23, 2.0;
  const double a_sum = dp.a12 + dp.a13 + dp.a23;  // == 1

  Eigen::Matrix3d X;
  X.col(0) = d12;
  X.col(1) = d13;
  X.col(2) = normal;
  const WorldTriangle world{X.inverse(), (points_w[0] + points_w[1] + points_w[2]) / 3.0};
  const double depth_scale = std::sqrt(scale);

  int num = 0;
  for (const double sign : {1.0, -1.0}) {
    const Eigen::Vector3d n = e_pos - sign * slope * e_neg;  // n . L = 0
    Eigen::Vector3d p;
    Eigen::Vector3d q;
    orthonormal_complement(n.normalized(), p, q);
    // L = alpha p + beta q on the line; (alpha, beta)^T [A B; B C] (alpha, beta) = 0.
    const double A = p.dot(D3 * p);
    const double B = p.dot(D3 * q);
    const double C = q.dot(D3 * q);
    double disc = B * B - A * C;
    if (disc < -kDiscriminantTol * (B * B + std::abs(A * C))) continue;
    disc = std::max(disc, 0.0);
    const double h = -(B + std::copysign(std::sqrt(disc), B));  // stable quadratic roots
    std::array<Eigen::Vector3d, 2> dirs;
    int num_dirs = 0;
    if (std::abs(A) >= std::abs(C)) {
      if (A == 0.0) continue;
      dirs[num_dirs++] = (h / A) * p + q;  // beta = 1
      if (h != 0.0) dirs[num_dirs++] = (C / h) * p + q;
    } else {
      dirs[num_dirs++] = p + (h / C) * q;  // alpha = 1
      if (h != 0.0) dirs[num_dirs++] = p + (A / h) * q;
    }
    for (int k = 0; k < num_dirs; ++k) {
      Eigen::Vector3d L = dirs[k];
      const double form = L.dot(S * L);
      if (!(form > 0.0)) continue;
      L *= std::sqrt(a_sum / form);
      if (L.sum() < 0.0) L = -L;
      if (!(L.minCoeff() > kMinDepth)) continue;
      dp.refine(L);
      if (!(L.minCoeff() > kMinDepth)) continue;
      SE3d T;
      if (!align_triangles(L * depth_scale, y, world, T)) continue;
      T_c_w[num++] = T;
      if (num == kMaxP3pSolutions) return num;
    }
  }
  return num;
}

}  // namespace mer::geometry
