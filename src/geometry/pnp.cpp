#include "geometry/pnp.h"

#include <algorithm>
#include <array>
#include <cmath>

#include <Eigen/Cholesky>

#include "geometry/p3p.h"

namespace mer::geometry {
namespace {

/// Pose (6) + focal (1) parameters of the refinement.
constexpr int kNumParams = 7;
using Matrix7d = Eigen::Matrix<double, kNumParams, kNumParams>;
using Vector7d = Eigen::Matrix<double, kNumParams, 1>;

// ---- Refinement (Levenberg-Marquardt) ------------------------------------------------
/// Initial LM damping, relative to the diagonal of the normal equations (starts close to
/// Gauss-Newton: RANSAC hands over poses near the optimum).
constexpr double kLmInitialLambda = 1e-4;
/// Damping factor on a rejected (x) / accepted (/) step.
constexpr double kLmLambdaUp = 10.0;
constexpr double kLmLambdaDown = 10.0;
/// Damping bounds: below kLmMinLambda it is plain Gauss-Newton; above kLmMaxLambda the
/// steps are negligible and the refinement stops.
constexpr double kLmMinLambda = 1e-9;
constexpr double kLmMaxLambda = 1e8;
/// Floor of a diagonal entry used for damping (parameters the data does not constrain).
constexpr double kLmMinDiagonal = 1e-12;
/// Converged when an accepted step lowers the cost by less than this fraction (for a
/// typical cost of ~n px^2 the remaining correction is ~1e-3 px per residual).
constexpr double kLmRelativeDecrease = 1e-6;
/// Cost charged for a point behind the camera, as a residual in px (/ sigma): large, so a
/// step is not accepted by pushing points behind the camera, and the same in every cost
/// evaluation so points that stay behind do not bias the comparison.
constexpr double kBehindCameraResidualPx = 1000.0;

// ---- RANSAC ----------------------------------------------------------------------------
/// Samples (minimal sets) drawn; P3P needs three correspondences.
constexpr int kSampleSize = 3;
/// Inlier ratios whose sample success probability w^3 is above 1 - this stop RANSAC at once.
constexpr double kCertainSample = 1e-12;
/// Local optimisation: refit rounds (mark inliers, refine, rescore) while the cost drops.
constexpr int kLoRounds = 3;
/// LM iterations per local-optimisation round (the final refinement does the rest).
constexpr int kLoIterations = 4;
/// Local optimisation stops once a round lowers the MSAC cost by less than this fraction.
constexpr double kLoMinImprovement = 1e-3;
/// Attempts to draw a sample of three distinct indices before giving up (only an issue
/// for n == 3; rejection sampling needs ~1 extra draw on average for n >= 10).
constexpr int kMaxSampleDraws = 64;

// ---- Focal estimation -------------------------------------------------------------------
/// Focal candidates are f0 * kFocalSweepRatio^k, k in [-kFocalSweepSteps, kFocalSweepSteps]:
/// a 12.5 % grid over [0.55, 1.8] x the guess. Between grid points the focal error is at
/// most ~6 %, which the widened threshold tolerates for moderately deep scenes.
constexpr double kFocalSweepRatio = 1.125;
constexpr int kFocalSweepSteps = 5;
/// The sweep scores hypotheses with the inlier threshold widened by this factor (a pose
/// computed at a focal a few percent off reprojects several px off at the image border).
constexpr double kFocalSearchThresholdScale = 4.0;
/// The sweep stops early once the best model (after joint pose + focal local
/// optimisation) explains at least this share of all correspondences at the real
/// threshold: a focal far off cannot, so the remaining candidates could only confirm it.
/// This makes the common tracking case (guess already close) cost ~1 solve().
constexpr double kFocalSweepStopInlierRatio = 0.5;
/// After the sweep, local optimisation (pose + f) is repeated with the threshold scaled by
/// these factors, from the sweep's width down to the real threshold.
constexpr std::array<double, 3> kFocalThresholdSchedule = {kFocalSearchThresholdScale, 2.0, 1.0};

/// Robust cost rho of a squared normalised residual s2 = |r|^2 / sigma^2 and its IRLS
/// weight: Huber, scaled so rho = s2 inside the kernel (px^2 units).
struct Huber {
  double width = 0.0;  ///< kernel width; <= 0 = plain least squares
  double rho(double s2) const {
    if (width <= 0.0 || s2 <= width * width) return s2;
    return 2.0 * width * std::sqrt(s2) - width * width;
  }
  double weight(double s2) const {
    if (width <= 0.0 || s2 <= width * width) return 1.0;
    return width / std::sqrt(s2);
  }
};

double inv_sigma2_of(const PnpInput& in, std::size_t i) {
  if (in.sigma.empty()) return 1.0;
  const double s = in.sigma[i];
  return 1.0 / (s * s);
}

bool selected(std::span<const std::uint8_t> mask, std::size_t i) {
  return mask.empty() || mask[i] != 0;
}

/// Robust cost of all selected correspondences; counts those in front of the camera.
double robust_cost(const PnpInput& in, std::span<const std::uint8_t> mask, const SE3d& T_c_w,
                   const Pinhole& K, const Huber& huber, int& num_used) {
  const Eigen::Matrix3d R = T_c_w.linear();
  const Eigen::Vector3d t = T_c_w.translation();
  const double behind_cost = huber.rho(kBehindCameraResidualPx * kBehindCameraResidualPx);
  double cost = 0.0;
  num_used = 0;
  for (std::size_t i = 0; i < in.X_w.size(); ++i) {
    if (!selected(mask, i)) continue;
    const Eigen::Vector3d p = R * in.X_w[i] + t;
    if (!(p.z() > 0.0)) {
      cost += behind_cost;
      continue;
    }
    const double inv_z = 1.0 / p.z();
    const double du = K.fx * p.x() * inv_z + K.cx - in.uv[i].x();
    const double dv = K.fy * p.y() * inv_z + K.cy - in.uv[i].y();
    cost += huber.rho((du * du + dv * dv) * inv_sigma2_of(in, i));
    ++num_used;
  }
  return cost;
}

/// Number of RANSAC samples needed to draw one all-inlier sample with `confidence`, given
/// `inliers` of `n`; capped at `cap`.
int required_iterations(int inliers, std::size_t n, double confidence, int cap) {
  if (inliers <= 0 || n == 0) return cap;
  const double w = static_cast<double>(inliers) / static_cast<double>(n);
  const double p_good = w * w * w;  // kSampleSize == 3
  if (p_good >= 1.0 - kCertainSample) return 0;
  const double needed = std::ceil(std::log(1.0 - confidence) / std::log1p(-p_good));
  if (!(needed < static_cast<double>(cap))) return cap;
  return static_cast<int>(needed);
}

}  // namespace

// ---- Residual and Jacobians -----------------------------------------------------------

namespace {

/// Residual of the camera-frame point p (z > 0) against uv, with the Jacobians of
/// reprojection_residual() (left perturbation, [omega; v]; focal with fx = fy = f).
inline Eigen::Vector2d residual_at(const Eigen::Vector3d& p, const Eigen::Vector2d& uv,
                                   const Pinhole& K, Eigen::Matrix<double, 2, 6>* d_r_d_xi,
                                   Eigen::Vector2d* d_r_d_f) {
  const double inv_z = 1.0 / p.z();
  const double xn = p.x() * inv_z;  // normalised image coordinates
  const double yn = p.y() * inv_z;
  const Eigen::Vector2d r(K.fx * xn + K.cx - uv.x(), K.fy * yn + K.cy - uv.y());
  if (d_r_d_xi != nullptr) {
    // d r / d p = [fx/z 0 -fx x/z^2; 0 fy/z -fy y/z^2] and d p / d xi = [-hat(p), I]:
    // columns 0..2 are (d r / d p) * -hat(p), columns 3..5 are d r / d p.
    const double fx_z = K.fx * inv_z;
    const double fy_z = K.fy * inv_z;
    auto& J = *d_r_d_xi;
    J(0, 0) = -K.fx * xn * yn;
    J(0, 1) = K.fx * (1.0 + xn * xn);
    J(0, 2) = -K.fx * yn;
    J(1, 0) = -K.fy * (1.0 + yn * yn);
    J(1, 1) = K.fy * xn * yn;
    J(1, 2) = K.fy * xn;
    J(0, 3) = fx_z;
    J(0, 4) = 0.0;
    J(0, 5) = -fx_z * xn;
    J(1, 3) = 0.0;
    J(1, 4) = fy_z;
    J(1, 5) = -fy_z * yn;
  }
  if (d_r_d_f != nullptr) *d_r_d_f = Eigen::Vector2d(xn, yn);
  return r;
}

}  // namespace

Eigen::Vector2d reprojection_residual(const SE3d& T_c_w, const Eigen::Vector3d& point_w,
                                      const Eigen::Vector2d& uv, const Pinhole& K,
                                      Eigen::Matrix<double, 2, 6>* d_r_d_xi,
                                      Eigen::Vector2d* d_r_d_f) {
  return residual_at(T_c_w.linear() * point_w + T_c_w.translation(), uv, K, d_r_d_xi, d_r_d_f);
}

// ---- Robust refinement ------------------------------------------------------------------

RefineResult refine_pose(const PnpInput& in, std::span<const std::uint8_t> mask, SE3d& T_c_w,
                         double* focal, const RefineOptions& o) {
  RefineResult res;
  const std::size_t n = in.X_w.size();
  if (in.uv.size() != n || (!mask.empty() && mask.size() < n) ||
      (!in.sigma.empty() && in.sigma.size() != n)) {
    return res;
  }
  const bool est_f = o.estimate_focal && focal != nullptr;
  const Huber huber{o.huber_px};
  Pinhole K = est_f ? in.K.with_focal(*focal) : in.K;
  double cost = robust_cost(in, mask, T_c_w, K, huber, res.num_used);
  res.initial_cost = cost;
  res.final_cost = cost;
  if (res.num_used == 0) return res;

  double lambda = kLmInitialLambda;
  bool linearize = true;
  Matrix7d H;
  Vector7d g;
  for (int it = 0; it < o.iterations; ++it) {
    res.iterations = it + 1;
    if (linearize) {
      const Eigen::Matrix3d R = T_c_w.linear();
      const Eigen::Vector3d t = T_c_w.translation();
      Eigen::Matrix<double, 6, 6> hess_xi = Eigen::Matrix<double, 6, 6>::Zero();
      Eigen::Matrix<double, 6, 1> grad_xi = Eigen::Matrix<double, 6, 1>::Zero();
      Eigen::Matrix<double, 6, 1> hess_xi_f = Eigen::Matrix<double, 6, 1>::Zero();
      double hess_ff = 0.0;
      double grad_f = 0.0;
      for (std::size_t i = 0; i < n; ++i) {
        if (!selected(mask, i)) continue;
        const Eigen::Vector3d p = R * in.X_w[i] + t;
        if (!(p.z() > 0.0)) continue;
        Eigen::Matrix<double, 2, 6> d_r_d_xi;
        Eigen::Vector2d d_r_d_f;
        const Eigen::Vector2d r =
            residual_at(p, in.uv[i], K, &d_r_d_xi, est_f ? &d_r_d_f : nullptr);
        const double inv_s2 = inv_sigma2_of(in, i);
        const double w = huber.weight(r.squaredNorm() * inv_s2) * inv_s2;
        // Fixed-size products: Eigen evaluates them coefficient-wise (no GEMM kernel).
        const Eigen::Matrix<double, 6, 2> w_jt = w * d_r_d_xi.transpose();
        hess_xi.noalias() += w_jt * d_r_d_xi;
        grad_xi.noalias() += w_jt * r;
        if (est_f) {
          hess_xi_f.noalias() += w_jt * d_r_d_f;
          hess_ff += w * d_r_d_f.squaredNorm();
          grad_f += w * d_r_d_f.dot(r);
        }
      }
      H.topLeftCorner<6, 6>() = hess_xi;
      H.block<6, 1>(0, 6) = hess_xi_f;
      H.block<1, 6>(6, 0) = hess_xi_f.transpose();
      H(6, 6) = hess_ff;
      g.head<6>() = grad_xi;
      g(6) = grad_f;
      if (!est_f) H(6, 6) = 1.0;  // focal fixed: decoupled unit row, g(6) == 0 -> no step
      linearize = false;
    }
    Matrix7d A = H;
    for (int k = 0; k < kNumParams; ++k) A(k, k) += lambda * std::max(H(k, k), kLmMinDiagonal);
    const Eigen::LDLT<Matrix7d> ldlt(A);
    if (ldlt.info() != Eigen::Success) break;
    const Vector7d delta = -ldlt.solve(g);
    if (!delta.allFinite()) break;
    const SE3d T_c_w_new = se3_exp(delta.head<6>()) * T_c_w;
    const double f_new = est_f ? *focal + delta(6) : 0.0;
    if (est_f && !(f_new > 0.0)) {
      lambda *= kLmLambdaUp;
      if (lambda > kLmMaxLambda) break;
      continue;
    }
    const Pinhole K2 = est_f ? in.K.with_focal(f_new) : in.K;
    int used_new = 0;
    const double cost_new = robust_cost(in, mask, T_c_w_new, K2, huber, used_new);
    if (cost_new < cost) {
      const double decrease = cost - cost_new;
      T_c_w = T_c_w_new;
      if (est_f) *focal = f_new;
      K = K2;
      cost = cost_new;
      res.num_used = used_new;
      lambda = std::max(lambda / kLmLambdaDown, kLmMinLambda);
      linearize = true;
      if (decrease < kLmRelativeDecrease * cost_new) break;
    } else {
      lambda *= kLmLambdaUp;
      if (lambda > kLmMaxLambda) break;
    }
  }
  res.final_cost = cost;
  return res;
}

// ---- RANSAC -----------------------------------------------------------------------------

PnpRansac::PnpRansac(const PnpOptions& opts, std::size_t max_correspondences)
    : opts_(opts),
      capacity_(max_correspondences),
      rng_(opts.seed),
      inv_sigma2_(max_correspondences, 1.0),
      mask_(max_correspondences, 0) {}

bool PnpRansac::prepare(const PnpInput& in, std::span<std::uint8_t> inlier_mask) {
  const std::size_t n = in.X_w.size();
  if (inlier_mask.size() < n) return false;
  std::fill_n(inlier_mask.begin(), n, std::uint8_t{0});
  if (in.uv.size() != n || n > capacity_) return false;
  if (!in.sigma.empty() && in.sigma.size() != n) return false;
  if (!(in.K.fx > 0.0 && in.K.fy > 0.0)) return false;
  for (std::size_t i = 0; i < n; ++i) {
    const double s = in.sigma.empty() ? 1.0 : static_cast<double>(in.sigma[i]);
    if (!(s > 0.0) || !std::isfinite(s)) return false;
    inv_sigma2_[i] = 1.0 / (s * s);
  }
  const std::size_t min_needed =
      std::max<std::size_t>(kSampleSize, static_cast<std::size_t>(std::max(opts_.min_inliers, 0)));
  if (n < min_needed) return false;
  rng_.reseed(opts_.seed);
  return true;
}

double PnpRansac::score(const PnpInput& in, const SE3d& T_c_w, const Pinhole& K, double thr2,
                        double bail_cost, int& num_inliers) const {
  // MSAC: sum of min(|r|^2 / sigma^2, thr^2); points behind the camera cost thr^2.
  const Eigen::Matrix3d R = T_c_w.linear();
  const Eigen::Vector3d t = T_c_w.translation();
  const std::size_t n = in.X_w.size();
  double cost = 0.0;
  int count = 0;
  for (std::size_t i = 0; i < n; ++i) {
    const Eigen::Vector3d p = R * in.X_w[i] + t;
    double e2 = thr2;
    if (p.z() > 0.0) {
      const double inv_z = 1.0 / p.z();
      const double du = K.fx * p.x() * inv_z + K.cx - in.uv[i].x();
      const double dv = K.fy * p.y() * inv_z + K.cy - in.uv[i].y();
      e2 = (du * du + dv * dv) * inv_sigma2_[i];
    }
    if (e2 < thr2) {
      cost += e2;
      ++count;
    } else {
      cost += thr2;
    }
    if (cost > bail_cost) break;  // cannot beat the best any more
  }
  num_inliers = count;
  return cost;
}

int PnpRansac::mark_inliers(const PnpInput& in, const SE3d& T_c_w, const Pinhole& K, double thr2,
                            std::span<std::uint8_t> mask) const {
  const Eigen::Matrix3d R = T_c_w.linear();
  const Eigen::Vector3d t = T_c_w.translation();
  int count = 0;
  for (std::size_t i = 0; i < in.X_w.size(); ++i) {
    const Eigen::Vector3d p = R * in.X_w[i] + t;
    bool inlier = false;
    if (p.z() > 0.0) {
      const double inv_z = 1.0 / p.z();
      const double du = K.fx * p.x() * inv_z + K.cx - in.uv[i].x();
      const double dv = K.fy * p.y() * inv_z + K.cy - in.uv[i].y();
      inlier = (du * du + dv * dv) * inv_sigma2_[i] < thr2;
    }
    mask[i] = inlier ? 1 : 0;
    count += inlier ? 1 : 0;
  }
  return count;
}

void PnpRansac::local_optimize(const PnpInput& in, double thr2, bool estimate_focal,
                               Hypothesis& h) {
  const std::size_t n = in.X_w.size();
  const std::span<std::uint8_t> mask(mask_.data(), n);
  const RefineOptions ro{kLoIterations, opts_.huber_px, estimate_focal};
  for (int round = 0; round < kLoRounds; ++round) {
    if (mark_inliers(in, h.T_c_w, h.K, thr2, mask) < opts_.lo_min_inliers) return;
    PnpInput sub = in;
    sub.K = h.K;
    Hypothesis cand = h;
    double f = h.K.fx;
    refine_pose(sub, mask, cand.T_c_w, &f, ro);
    if (estimate_focal) cand.K = h.K.with_focal(f);
    cand.cost = score(in, cand.T_c_w, cand.K, thr2, h.cost, cand.num_inliers);
    if (!(cand.cost < h.cost)) return;
    const bool converged = cand.cost > (1.0 - kLoMinImprovement) * h.cost;
    h = cand;
    if (converged) return;
  }
}

void PnpRansac::ransac(const PnpInput& in, const Pinhole& K, double thr2, const SE3d* prior,
                       bool estimate_focal, Hypothesis& best, int& iterations) {
  const std::size_t n = in.X_w.size();
  const auto n32 = static_cast<std::uint32_t>(n);
  auto consider = [&](const SE3d& T) {
    int inl = 0;
    const double c = score(in, T, K, thr2, best.cost, inl);
    if (!(c < best.cost)) return false;
    best.T_c_w = T;
    best.K = K;
    best.cost = c;
    best.num_inliers = inl;
    return true;
  };
  const int cap = std::max(opts_.max_iterations, 0);
  if (prior != nullptr && consider(*prior) && best.num_inliers >= opts_.lo_min_inliers) {
    local_optimize(in, thr2, estimate_focal, best);
  }
  int needed = required_iterations(best.num_inliers, n, opts_.confidence, cap);
  std::array<SE3d, kMaxP3pSolutions> sols;
  std::array<Eigen::Vector3d, 3> bearings;
  std::array<Eigen::Vector3d, 3> X;
  for (int it = 0; it < needed; ++it) {
    ++iterations;
    // Three distinct indices (rejection sampling).
    std::array<std::uint32_t, kSampleSize> idx{};
    idx[0] = rng_.uniform_index(n32);
    int draws = 0;
    do {
      idx[1] = rng_.uniform_index(n32);
    } while (idx[1] == idx[0] && ++draws < kMaxSampleDraws);
    do {
      idx[2] = rng_.uniform_index(n32);
    } while ((idx[2] == idx[0] || idx[2] == idx[1]) && ++draws < kMaxSampleDraws);
    if (draws >= kMaxSampleDraws) continue;
    for (int k = 0; k < kSampleSize; ++k) {
      bearings[k] = K.bearing(in.uv[idx[k]]);
      X[k] = in.X_w[idx[k]];
    }
    const int num_sols = solve_p3p(bearings, X, sols);
    bool improved = false;
    for (int s = 0; s < num_sols; ++s) improved |= consider(sols[s]);
    if (!improved) continue;
    if (best.num_inliers >= opts_.lo_min_inliers) {
      local_optimize(in, thr2, estimate_focal, best);
    }
    needed = required_iterations(best.num_inliers, n, opts_.confidence, cap);
  }
}

PnpResult PnpRansac::finish(const PnpInput& in, const Hypothesis& best,
                            std::span<std::uint8_t> inlier_mask, bool estimate_focal,
                            int iterations) {
  PnpResult r;
  r.iterations = iterations;
  r.T_c_w = best.T_c_w;
  r.focal = best.K.fx;
  const std::size_t n = in.X_w.size();
  const double thr2 = opts_.inlier_threshold_px * opts_.inlier_threshold_px;
  const std::span<std::uint8_t> mask = inlier_mask.first(n);
  PnpInput sub = in;
  sub.K = best.K;
  int inliers = mark_inliers(sub, r.T_c_w, sub.K, thr2, mask);
  if (opts_.refine_iterations > 0 && inliers >= kSampleSize) {
    const RefineOptions ro{opts_.refine_iterations, opts_.huber_px, estimate_focal};
    refine_pose(sub, mask, r.T_c_w, &r.focal, ro);
    if (estimate_focal) sub.K = best.K.with_focal(r.focal);
    inliers = mark_inliers(sub, r.T_c_w, sub.K, thr2, mask);
  }
  // RMS of the inliers in px.
  double sum2 = 0.0;
  for (std::size_t i = 0; i < n; ++i) {
    if (mask[i] == 0) continue;
    sum2 +=
        reprojection_residual(r.T_c_w, in.X_w[i], in.uv[i], sub.K, nullptr, nullptr).squaredNorm();
  }
  r.num_inliers = inliers;
  r.rms_px = inliers > 0 ? std::sqrt(sum2 / inliers) : 0.0;
  r.ok = inliers >= opts_.min_inliers && r.T_c_w.matrix().allFinite();
  return r;
}

PnpResult PnpRansac::solve(const PnpInput& in, std::span<std::uint8_t> inlier_mask,
                           const SE3d* prior) {
  PnpResult fail;
  fail.focal = in.K.fx;
  if (!prepare(in, inlier_mask)) return fail;
  const double thr2 = opts_.inlier_threshold_px * opts_.inlier_threshold_px;
  Hypothesis best;
  best.K = in.K;
  int iterations = 0;
  ransac(in, in.K, thr2, prior, /*estimate_focal=*/false, best, iterations);
  if (!std::isfinite(best.cost)) {
    fail.iterations = iterations;
    return fail;
  }
  return finish(in, best, inlier_mask, /*estimate_focal=*/false, iterations);
}

PnpResult PnpRansac::solve_with_focal(const PnpInput& in, std::span<std::uint8_t> inlier_mask,
                                      const SE3d* prior) {
  PnpResult fail;
  fail.focal = in.K.fx;
  if (!prepare(in, inlier_mask)) return fail;
  const double thr = opts_.inlier_threshold_px;
  const double wide2 = (thr * kFocalSearchThresholdScale) * (thr * kFocalSearchThresholdScale);
  const double f0 = in.K.fx;
  const std::size_t n = in.X_w.size();
  Hypothesis best;
  best.K = in.K.with_focal(f0);
  int iterations = 0;
  // Sweep: the guess first, then alternately above and below it.
  for (int j = 0; j <= 2 * kFocalSweepSteps; ++j) {
    const int k = (j % 2 == 1) ? (j + 1) / 2 : -(j / 2);
    const Pinhole K = in.K.with_focal(f0 * std::pow(kFocalSweepRatio, k));
    Hypothesis cand;
    cand.K = K;
    ransac(in, K, wide2, j == 0 ? prior : nullptr, /*estimate_focal=*/true, cand, iterations);
    if (!(cand.cost < best.cost)) continue;
    best = cand;
    int strict_inliers = 0;
    score(in, best.T_c_w, best.K, thr * thr, std::numeric_limits<double>::infinity(),
          strict_inliers);
    if (strict_inliers >= opts_.min_inliers &&
        strict_inliers >= kFocalSweepStopInlierRatio * static_cast<double>(n)) {
      break;
    }
  }
  if (!std::isfinite(best.cost)) {
    fail.iterations = iterations;
    return fail;
  }
  // Joint pose + focal local optimisation, threshold brought down to the real one.
  for (const double s : kFocalThresholdSchedule) {
    const double thr2 = (thr * s) * (thr * s);
    best.cost = score(in, best.T_c_w, best.K, thr2, std::numeric_limits<double>::infinity(),
                      best.num_inliers);
    local_optimize(in, thr2, /*estimate_focal=*/true, best);
  }
  return finish(in, best, inlier_mask, /*estimate_focal=*/true, iterations);
}

}  // namespace mer::geometry
