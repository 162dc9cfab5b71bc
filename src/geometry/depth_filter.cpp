#include "geometry/depth_filter.h"

#include <algorithm>
#include <cmath>
#include <numbers>

namespace mer::geometry {
namespace {

constexpr double kSigmasInRange = 6.0;  // a new seed's +-3 sigma spans [0, rho_max]
constexpr double kMinVariance = 1e-300;

double gaussian_pdf(double x, double mu, double sigma) {
  const double d = (x - mu) / sigma;
  return std::exp(-0.5 * d * d) / (sigma * std::sqrt(2.0 * std::numbers::pi));
}

// Inverse of the distance along the reference ray at which it meets the ray from the second
// camera that makes the angle `beta` with the baseline back to the reference centre (law of
// sines in the triangle reference centre, second centre, point; `alpha` is the angle at the
// reference centre). 0 at infinity, negative beyond it.
double inverse_range(double alpha, double beta, double baseline) {
  return std::sin(alpha + beta) / (baseline * std::sin(beta));
}

}  // namespace

DepthSeed make_depth_seed(double depth, double min_depth, double prior_evidence) {
  DepthSeed s;
  s.rho_max = 1.0 / min_depth;
  s.mu = 1.0 / depth;
  const double sigma = s.rho_max / kSigmasInRange;
  s.sigma2 = sigma * sigma;
  s.a = prior_evidence;
  s.b = prior_evidence;
  return s;
}

void update_depth_seed(DepthSeed& seed, double rho, double tau) {
  const double tau2 = tau * tau;
  const double norm_sigma = std::sqrt(seed.sigma2 + tau2);
  // The Gaussian part's posterior: the product of the prior and the measurement.
  const double s2 = 1.0 / (1.0 / seed.sigma2 + 1.0 / tau2);
  const double m = s2 * (seed.mu / seed.sigma2 + rho / tau2);
  // Responsibilities of "good measurement" and "wrong match, uniform over the range".
  double c1 = seed.a / (seed.a + seed.b) * gaussian_pdf(rho, seed.mu, norm_sigma);
  double c2 = seed.b / (seed.a + seed.b) / seed.rho_max;
  const double norm = c1 + c2;
  if (!(norm > 0.0)) return;  // both underflowed: the measurement is uninformative
  c1 /= norm;
  c2 /= norm;
  const double a = seed.a;
  const double b = seed.b;
  // First two moments of the inlier ratio under the mixed posterior.
  const double f = c1 * (a + 1.0) / (a + b + 1.0) + c2 * a / (a + b + 1.0);
  const double e = c1 * (a + 1.0) * (a + 2.0) / ((a + b + 1.0) * (a + b + 2.0)) +
                   c2 * a * (a + 1.0) / ((a + b + 1.0) * (a + b + 2.0));
  const double mu_new = c1 * m + c2 * seed.mu;
  seed.sigma2 = std::max(
      kMinVariance, c1 * (s2 + m * m) + c2 * (seed.sigma2 + seed.mu * seed.mu) - mu_new * mu_new);
  seed.mu = mu_new;
  // Beta parameters with those moments.
  seed.a = (e - f) / (f - e / f);
  seed.b = seed.a * (1.0 - f) / f;
}

double inverse_depth_sigma(const Eigen::Vector3d& f_ref, double depth,
                           const Eigen::Vector3d& t_ref_cur, double pixel_angle) {
  const double baseline = t_ref_cur.norm();
  const Eigen::Vector3d f = f_ref.normalized();
  if (baseline <= 0.0 || f.z() <= 0.0 || depth <= 0.0) return 0.0;
  const Eigen::Vector3d t = t_ref_cur / baseline;
  const double alpha = std::acos(std::clamp(f.dot(t), -1.0, 1.0));
  // The angle at the second centre between the ray to the point and the baseline back.
  const Eigen::Vector3d to_point = f * (depth / f.z()) - t_ref_cur;
  const double n = to_point.norm();
  if (n <= 0.0) return 0.0;
  const double beta = std::acos(std::clamp(to_point.dot(-t) / n, -1.0, 1.0));
  const double lo = beta - pixel_angle;
  const double hi = beta + pixel_angle;
  if (lo <= 0.0 || hi >= std::numbers::pi) return 0.0;  // the ray runs along the baseline
  // Inverse depth (z) at the two rays one pixel either side, half their difference.
  const double rho_lo = inverse_range(alpha, lo, baseline) / f.z();
  const double rho_hi = inverse_range(alpha, hi, baseline) / f.z();
  return 0.5 * std::abs(rho_lo - rho_hi);
}

bool depth_seed_converged(const DepthSeed& seed, double ratio) {
  return std::sqrt(seed.sigma2) < seed.rho_max / ratio;
}

}  // namespace mer::geometry
