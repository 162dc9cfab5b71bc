#include "geometry/window_ba.h"

#include <algorithm>
#include <cmath>

#include <Eigen/Eigenvalues>

#include "geometry/lie.h"

namespace mer::geometry {
namespace {

constexpr int kPoseDof = 6;
// A view whose reference-ray point has camera depth below this (q_z, in units of the ray's
// z = 1) is behind it.
constexpr double kMinDepthFactor = 1e-6;
// Information added to each inverse depth so that a point no view constrains (every view
// without translation) keeps its value instead of making the system singular.
constexpr double kInvDepthPriorInformation = 1e-9;
// Added to the reduced system's diagonal: a view no point constrains stays where it is.
constexpr double kMinDiagonal = 1e-12;
// Weight that holds the scale view's translation on the unit sphere (radial direction).
constexpr double kRadialLock = 1e12;
// Levenberg-Marquardt damping: initial value, factor, bounds.
constexpr double kLambdaInit = 1e-4;
constexpr double kLambdaFactor = 10.0;
constexpr double kLambdaMax = 1e8;
constexpr double kLambdaMin = 1e-12;
// A solve stops when an accepted step lowers the cost by less than this fraction.
constexpr double kRelativeDecrease = 1e-6;
constexpr double kRadToDeg = 57.29577951308232;

}  // namespace

bool window_ba_residual(const Pinhole& K, const Eigen::Matrix3d& R, const Eigen::Vector3d& t,
                        const Eigen::Vector3d& f, double rho, const Eigen::Vector2d& uv,
                        double inv_sigma, Eigen::Vector2d& r,
                        Eigen::Matrix<double, 2, 6>* d_r_d_pose, Eigen::Vector2d* d_r_d_rho) {
  const Eigen::Vector3d Rf = R * f;
  const Eigen::Vector3d q = Rf + rho * t;
  if (q.z() <= kMinDepthFactor) return false;
  const double iz = 1.0 / q.z();
  r.x() = (K.fx * q.x() * iz + K.cx - uv.x()) * inv_sigma;
  r.y() = (K.fy * q.y() * iz + K.cy - uv.y()) * inv_sigma;
  if (d_r_d_pose == nullptr && d_r_d_rho == nullptr) return true;
  Eigen::Matrix<double, 2, 3> d_r_d_q;
  d_r_d_q << K.fx * iz, 0.0, -K.fx * q.x() * iz * iz,  //
      0.0, K.fy * iz, -K.fy * q.y() * iz * iz;
  d_r_d_q *= inv_sigma;
  if (d_r_d_pose != nullptr) {
    // q = Exp(w) R f + rho (t + dt): dq/dw = -hat(R f), dq/dt = rho I.
    d_r_d_pose->leftCols<3>() = -d_r_d_q * hat(Rf);
    d_r_d_pose->rightCols<3>() = d_r_d_q * rho;
  }
  if (d_r_d_rho != nullptr) *d_r_d_rho = d_r_d_q * t;
  return true;
}

void WindowBundleAdjuster::reserve(int max_views, int max_points) {
  max_views_ = std::max(max_views, 1);
  max_points_ = std::max(max_points, 1);
  const auto nv = static_cast<std::size_t>(max_views_);
  const auto np = static_cast<std::size_t>(max_points_);
  T_.assign(nv, SE3d::Identity());
  saved_T_.assign(nv, SE3d::Identity());
  rho_.assign(np, 0.0);
  rho_saved_.assign(np, 0.0);
  f_.assign(np, Eigen::Vector3d::Zero());
  inv_sigma_.assign(np, 1.0);
  obs_uv_.assign(nv * np, Eigen::Vector2d::Zero());
  obs_valid_.assign(nv * np, 0);
  h_cp_.assign(nv * np, Eigen::Matrix<double, 6, 1>::Zero());
  h_pp_.assign(np, 0.0);
  b_p_.assign(np, 0.0);
  const int n = kPoseDof * max_views_;
  h_cc_.setZero(n, n);
  b_c_.setZero(n);
  b_s_.setZero(n);
  dc_.setZero(n);
  // Sizes the factorization's storage (solves then reuse it).
  S_.setIdentity(n, n);
  ldlt_.compute(S_);
  cov_rhs_.setZero(n, kPoseDof);
}

void WindowBundleAdjuster::reset(const Pinhole& K, double huber_chi2) {
  K_ = K;
  huber_k_ = std::sqrt(huber_chi2);
  std::fill(obs_valid_.begin(), obs_valid_.end(), kNone);
  num_views_ = 0;
  num_points_ = 0;
  scale_view_ = -1;
  fixed_view_ = -1;
}

int WindowBundleAdjuster::add_point(const Eigen::Vector2d& uv_ref, double inv_depth,
                                    double sigma_px) {
  if (num_points_ >= max_points_) return -1;
  const auto i = static_cast<std::size_t>(num_points_);
  f_[i] = K_.unproject(uv_ref);
  inv_sigma_[i] = 1.0 / sigma_px;
  rho_[i] = inv_depth;
  return num_points_++;
}

int WindowBundleAdjuster::add_view(const SE3d& T_c_ref) {
  if (num_views_ >= max_views_) return -1;
  T_[static_cast<std::size_t>(num_views_)] = T_c_ref;
  return num_views_++;
}

void WindowBundleAdjuster::set_scale_view(int v) {
  scale_view_ = v;
  SE3d& T = T_[static_cast<std::size_t>(v)];
  const double norm = T.translation().norm();
  if (norm > 0.0) T.translation() /= norm;
}

void WindowBundleAdjuster::observe(int v, int i, const Eigen::Vector2d& uv) {
  obs_uv_[index(v, i)] = uv;
  obs_valid_[index(v, i)] = kActive;
}

int WindowBundleAdjuster::drop_outliers(double chi2_gate) {
  int dropped = 0;
  for (int v = 0; v < num_views_; ++v) {
    for (int i = 0; i < num_points_; ++i) {
      if (obs_valid_[index(v, i)] == kActive && chi2(v, i) > chi2_gate) {
        obs_valid_[index(v, i)] = kDropped;
        ++dropped;
      }
    }
  }
  return dropped;
}

double WindowBundleAdjuster::truncated_cost(double chi2_gate) const {
  double c = 0.0;
  for (int v = 0; v < num_views_; ++v) {
    for (int i = 0; i < num_points_; ++i) {
      if (obs_valid_[index(v, i)] != kNone) c += std::min(chi2(v, i), chi2_gate);
    }
  }
  return c;
}

double WindowBundleAdjuster::point_truncated_cost(int i, double chi2_gate) const {
  double c = 0.0;
  for (int v = 0; v < num_views_; ++v) {
    if (obs_valid_[index(v, i)] != kNone) c += std::min(chi2(v, i), chi2_gate);
  }
  return c;
}

int WindowBundleAdjuster::num_observations() const {
  int n = 0;
  for (int v = 0; v < num_views_; ++v) {
    for (int i = 0; i < num_points_; ++i) n += obs_valid_[index(v, i)] != kNone ? 1 : 0;
  }
  return n;
}

double WindowBundleAdjuster::huber(double s) const {
  const double k2 = huber_k_ * huber_k_;
  return s <= k2 ? s : 2.0 * huber_k_ * std::sqrt(s) - k2;
}

double WindowBundleAdjuster::chi2(int v, int i) const {
  const std::size_t o = index(v, i);
  if (obs_valid_[o] == kNone) return 0.0;
  const auto ui = static_cast<std::size_t>(i);
  const SE3d& T = T_[static_cast<std::size_t>(v)];
  Eigen::Vector2d r;
  if (!window_ba_residual(K_, T.linear(), T.translation(), f_[ui], rho_[ui], obs_uv_[o],
                          inv_sigma_[ui], r, nullptr, nullptr)) {
    return kWindowBaBehindChi2;
  }
  return r.squaredNorm();
}

double WindowBundleAdjuster::cost() const {
  double c = 0.0;
  for (int v = 0; v < num_views_; ++v) {
    for (int i = 0; i < num_points_; ++i) {
      if (obs_valid_[index(v, i)] == kActive) c += huber(chi2(v, i));
    }
  }
  return c;
}

double WindowBundleAdjuster::linearize() {
  h_cc_.setZero();
  b_c_.setZero();
  double c = 0.0;
  Eigen::Vector2d r;
  Eigen::Matrix<double, 2, 6> Jc;
  Eigen::Vector2d Jp;
  for (int i = 0; i < num_points_; ++i) {
    const auto ui = static_cast<std::size_t>(i);
    double hpp = kInvDepthPriorInformation;
    double bp = 0.0;
    for (int v = 0; v < num_views_; ++v) {
      const std::size_t o = index(v, i);
      h_cp_[o].setZero();
      if (obs_valid_[o] != kActive) continue;
      const SE3d& T = T_[static_cast<std::size_t>(v)];
      if (!window_ba_residual(K_, T.linear(), T.translation(), f_[ui], rho_[ui], obs_uv_[o],
                              inv_sigma_[ui], r, &Jc, &Jp)) {
        c += huber(kWindowBaBehindChi2);
        continue;
      }
      const double s = r.squaredNorm();
      c += huber(s);
      const double w = s <= huber_k_ * huber_k_ ? 1.0 : huber_k_ / std::sqrt(s);
      const int b = kPoseDof * v;
      h_cc_.block<6, 6>(b, b).noalias() += w * Jc.transpose() * Jc;
      b_c_.segment<6>(b).noalias() += w * Jc.transpose() * r;
      h_cp_[o].noalias() = w * Jc.transpose() * Jp;
      hpp += w * Jp.squaredNorm();
      bp += w * Jp.dot(r);
    }
    h_pp_[ui] = hpp;
    b_p_[ui] = bp;
  }
  return c;
}

void WindowBundleAdjuster::reduce(double lambda, bool points_fixed) {
  S_ = h_cc_;
  b_s_ = b_c_;
  for (int k = 0; k < kPoseDof * num_views_; ++k) S_(k, k) += lambda * S_(k, k) + kMinDiagonal;
  for (int k = kPoseDof * num_views_; k < S_.rows(); ++k) S_(k, k) = 1.0;
  if (!points_fixed) {
    for (int i = 0; i < num_points_; ++i) {
      const auto ui = static_cast<std::size_t>(i);
      const double h = h_pp_[ui] * (1.0 + lambda);
      for (int v1 = 0; v1 < num_views_; ++v1) {
        const std::size_t o1 = index(v1, i);
        if (obs_valid_[o1] != kActive) continue;
        b_s_.segment<6>(kPoseDof * v1) -= h_cp_[o1] * (b_p_[ui] / h);
        for (int v2 = v1; v2 < num_views_; ++v2) {
          const std::size_t o2 = index(v2, i);
          if (obs_valid_[o2] != kActive) continue;
          const Eigen::Matrix<double, 6, 6> blk = h_cp_[o1] * h_cp_[o2].transpose() / h;
          S_.block<6, 6>(kPoseDof * v1, kPoseDof * v2) -= blk;
          if (v2 != v1) S_.block<6, 6>(kPoseDof * v2, kPoseDof * v1) -= blk.transpose();
        }
      }
    }
  }
  if (fixed_view_ >= 0) {
    S_.block<6, 6>(kPoseDof * fixed_view_, kPoseDof * fixed_view_).diagonal().array() +=
        kRadialLock;
  }
  if (scale_view_ >= 0) {
    const Eigen::Vector3d u = T_[static_cast<std::size_t>(scale_view_)].translation().normalized();
    S_.block<3, 3>(kPoseDof * scale_view_ + 3, kPoseDof * scale_view_ + 3) +=
        kRadialLock * u * u.transpose();
  }
}

WindowBaSummary WindowBundleAdjuster::solve(int iterations, bool points_fixed) {
  WindowBaSummary out;
  double c = linearize();
  out.initial_cost = c;
  double lambda = kLambdaInit;
  for (int it = 0; it < iterations; ++it) {
    ++out.iterations;
    reduce(lambda, points_fixed);
    ldlt_.compute(S_);
    if (ldlt_.info() != Eigen::Success) break;
    dc_ = -b_s_;
    ldlt_.solveInPlace(dc_);
    std::copy_n(T_.begin(), num_views_, saved_T_.begin());
    std::copy_n(rho_.begin(), num_points_, rho_saved_.begin());
    for (int v = 0; v < num_views_; ++v) {
      SE3d& T = T_[static_cast<std::size_t>(v)];
      const Eigen::Matrix<double, 6, 1> d = dc_.segment<6>(kPoseDof * v);
      T.linear() = so3_exp(d.head<3>()) * T.linear();
      T.translation() += d.tail<3>();
      if (v == scale_view_) T.translation().normalize();
    }
    if (!points_fixed) {
      for (int i = 0; i < num_points_; ++i) {
        const auto ui = static_cast<std::size_t>(i);
        double g = b_p_[ui];
        for (int v = 0; v < num_views_; ++v) {
          const std::size_t o = index(v, i);
          if (obs_valid_[o] == kActive) g += h_cp_[o].dot(dc_.segment<6>(kPoseDof * v));
        }
        rho_[ui] -= g / (h_pp_[ui] * (1.0 + lambda));
      }
    }
    const double c_new = cost();
    if (c_new < c) {
      const bool converged = c - c_new < kRelativeDecrease * c;
      c = linearize();
      lambda = std::max(lambda / kLambdaFactor, kLambdaMin);
      if (converged) break;
    } else {
      std::copy_n(saved_T_.begin(), num_views_, T_.begin());
      std::copy_n(rho_saved_.begin(), num_points_, rho_.begin());
      lambda *= kLambdaFactor;
      if (lambda > kLambdaMax) break;
    }
  }
  out.final_cost = c;
  for (int v = 0; v < num_views_; ++v) {
    for (int i = 0; i < num_points_; ++i) {
      if (obs_valid_[index(v, i)] != kActive) continue;
      if (chi2(v, i) >= kWindowBaBehindChi2) {
        ++out.behind;
      } else {
        ++out.observations;
      }
    }
  }
  return out;
}

WindowBaSigma WindowBundleAdjuster::sigma(int v) {
  WindowBaSigma out;
  if (v < 0 || v >= num_views_) return out;
  linearize();
  reduce(0.0, false);
  ldlt_.compute(S_);
  if (ldlt_.info() != Eigen::Success || !ldlt_.isPositive()) return out;
  cov_rhs_.setZero();
  cov_rhs_.block<6, 6>(kPoseDof * v, 0).setIdentity();
  ldlt_.solveInPlace(cov_rhs_);
  const Eigen::Matrix<double, 6, 6> C = cov_rhs_.block<6, 6>(kPoseDof * v, 0);
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> rot(C.topLeftCorner<3, 3>(),
                                                           Eigen::EigenvaluesOnly);
  const Eigen::Vector3d t = T_[static_cast<std::size_t>(v)].translation();
  const double tn = t.norm();
  if (tn <= 0.0) return out;
  // Direction of t: its tangent part, over its length.
  const Eigen::Matrix3d P = Eigen::Matrix3d::Identity() - t * t.transpose() / (tn * tn);
  const Eigen::Matrix3d Ct = P * C.bottomRightCorner<3, 3>() * P / (tn * tn);
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> dir(Ct, Eigen::EigenvaluesOnly);
  out.rotation_deg = std::sqrt(std::max(rot.eigenvalues().maxCoeff(), 0.0)) * kRadToDeg;
  out.translation_dir_deg = std::sqrt(std::max(dir.eigenvalues().maxCoeff(), 0.0)) * kRadToDeg;
  out.ok = true;
  return out;
}

}  // namespace mer::geometry
