#pragma once
/// @file chi2.h
/// The one set of chi-square gates of the project: the 95 % quantiles a squared error over
/// its variance is tested against (reprojection errors: 2 dof; distances to an epipolar line
/// or depth errors: 1 dof).

namespace mer {

/// 95 % quantile of chi2 with 1 degree of freedom.
inline constexpr double kChi2OneDof95 = 3.841;
/// 95 % quantile of chi2 with 2 degrees of freedom.
inline constexpr double kChi2TwoDof95 = 5.991;

}  // namespace mer
