#pragma once
/// @file triangulation.h
/// Linear (DLT) triangulation of points from calibrated views.
///
/// Each view contributes the two rows x * P3 - P1 and y * P3 - P2 of the DLT system
/// A X = 0 (Hartley & Zisserman, "Multiple View Geometry", sec. 12.2), with P = [R | t] of
/// T_c_w and (x, y) the normalized image coordinates. The rows are folded into a 4x4
/// triangular factor with Givens rotations as they arrive (numerically the same as an SVD of
/// the stacked 2n x 4 matrix, without squaring its condition number), and the point is the
/// right singular vector of the smallest singular value. Coordinates are expressed relative
/// to the first camera centre so that world points far from the origin stay well scaled.
/// Nothing allocates, for any number of views.

#include <span>

#include <Eigen/Core>

#include "core/pose.h"

namespace mer::geometry {

/// Linear (DLT, SVD) triangulation from two views; x0/x1 normalized image coords
/// (x/z, y/z, 1). Returns false if the point is at infinity or behind either camera
/// (X_w is written only on success).
bool triangulate_two_view(const SE3d& T_c0_w, const SE3d& T_c1_w, const Eigen::Vector3d& x0,
                          const Eigen::Vector3d& x1, Eigen::Vector3d& X_w);

/// Multi-view linear triangulation (n >= 2 views, T_c_w.size() == x_norm.size()) for keyframe
/// depth. Returns false for fewer than two views, mismatched spans, a point at infinity or a
/// point behind any of the cameras. No allocation (for any n).
bool triangulate_multi_view(std::span<const SE3d> T_c_w, std::span<const Eigen::Vector3d> x_norm,
                            Eigen::Vector3d& X_w);

/// Parallax angle (deg) at X_w between the two camera centres (0 when X_w coincides with a
/// centre).
double parallax_deg(const Eigen::Vector3d& X_w, const Eigen::Vector3d& c0_w,
                    const Eigen::Vector3d& c1_w);

}  // namespace mer::geometry
