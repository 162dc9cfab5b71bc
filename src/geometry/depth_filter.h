#pragma once
/// @file depth_filter.h
/// A keypoint's depth before it is known: a recursive estimate of its inverse depth from
/// measurements made as the camera moves, robust to wrong matches.
///
/// The model is the parametric one of Vogiatzis & Hernandez ("Video-based, real-time
/// multi-view stereo", IVC 2011), used by SVO's depth filter: a measurement of the inverse
/// depth is, with probability pi, Gaussian around the true value (its sigma from the
/// geometry, `inverse_depth_sigma`) and otherwise uniform over [0, rho_max] (a wrong match
/// anywhere along the epipolar segment). The posterior over (inverse depth, pi) is
/// approximated by a Gaussian times a Beta distribution whose first two moments match the
/// true posterior after each measurement. A seed starts wide (inverse depth from the scene's
/// median depth, sigma covering [0, rho_max]) and is converged once its sigma is a small
/// fraction of rho_max; its inlier ratio says whether the measurements agreed. Inverse depth
/// makes points far away (rho near 0) and rotation-only motion, where a measurement says
/// little, part of the same model (Civera et al., "Inverse depth parametrization for
/// monocular SLAM", T-RO 2008). Nothing allocates. Not yet used by the pipeline: fed only by
/// keyframes it did not converge (docs/decisions/depth-seeds-at-keyframes.md); it is meant
/// for seeds updated on every tracked frame.

#include <Eigen/Core>

#include "core/pose.h"

namespace mer::geometry {

/// Inverse-depth estimate of one keypoint with the inlier evidence of its measurements.
struct DepthSeed {
  double mu = 0.0;       ///< inverse depth mean, 1 / map units
  double sigma2 = 0.0;   ///< inverse depth variance
  double a = 10.0;       ///< Beta parameter: evidence for good measurements
  double b = 10.0;       ///< Beta parameter: evidence for wrong ones
  double rho_max = 0.0;  ///< largest inverse depth (the nearest point): the outlier range

  /// Expected fraction of good measurements, a / (a + b).
  double inlier_ratio() const { return a / (a + b); }
  /// Depth at the mean inverse depth (0 when the mean is not positive).
  double depth() const { return mu > 0.0 ? 1.0 / mu : 0.0; }
};

/// A new seed: inverse depth 1 / `depth`, sigma rho_max / 6 so that +-3 sigma spans the
/// range [0, 1 / `min_depth`], equal Beta evidence `prior_evidence` for good and wrong
/// measurements. `depth` and `min_depth` must be positive.
DepthSeed make_depth_seed(double depth, double min_depth, double prior_evidence = 10.0);

/// Fuses one measurement: inverse depth `rho` with standard deviation `tau` (> 0). The
/// mean moves toward `rho` by the probability that it is a good measurement; one far out
/// mostly lowers the inlier ratio.
void update_depth_seed(DepthSeed& seed, double rho, double tau);

/// Standard deviation of an inverse-depth measurement made by triangulating the ray `f_ref`
/// (unit bearing in the reference camera) at depth `depth` (along the optical axis,
/// z of the point) against a second camera whose centre is `t_ref_cur` in the reference
/// frame, when the second camera's ray is off by `pixel_angle` (radians: keypoint sigma /
/// focal length). 0 when the geometry gives no measurement (no baseline, or the rays are
/// parallel).
double inverse_depth_sigma(const Eigen::Vector3d& f_ref, double depth,
                           const Eigen::Vector3d& t_ref_cur, double pixel_angle);

/// True when the seed's sigma is below rho_max / `ratio` (a converged estimate).
bool depth_seed_converged(const DepthSeed& seed, double ratio);

}  // namespace mer::geometry
