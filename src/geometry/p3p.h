#pragma once
/// @file p3p.h
/// Minimal absolute pose from three point-bearing pairs (P3P), Lambda Twist style
/// (Persson & Nordberg, "Lambda Twist: An Accurate Fast Robust Perspective Three Point
/// (P3P) Solver", ECCV 2018):
///
///  1. The unknown depths L = (l1, l2, l3) satisfy three quadrics
///     |li yi - lj yj|^2 = |Xi - Xj|^2. Eliminating the constants gives two homogeneous
///     conics L^T D1 L = 0, L^T D2 L = 0 in the projective plane of L.
///  2. A real root g of the cubic det(D1 + g D2) = 0 gives a degenerate member D0 of the
///     pencil: a pair of real lines through the (up to four) intersection points.
///  3. D0 is split into its two lines with the eigen-decomposition of the rank-2 matrix
///     (eigenvalues of opposite sign); each line is intersected with one of the conics
///     (a quadratic), the scale comes from the distance equations.
///  4. Each positive-depth solution is polished with a few Gauss-Newton steps on the
///     original three equations, and the pose is the rigid transform between the
///     triangles (Xi) and (li yi).
///
/// No allocation; about a microsecond per call.

#include <array>

#include <Eigen/Core>

#include "core/pose.h"

namespace mer::geometry {

/// Maximum number of P3P solutions.
inline constexpr int kMaxP3pSolutions = 4;

/// Solves P3P. `bearings` are unit vectors in the camera frame (towards points_w[i]);
/// `points_w` the matching world points. Writes the world-to-camera poses of all solutions with
/// positive depths into T_c_w[0 .. n) and returns n (0..4). Degenerate input (collinear or
/// coincident world points, coincident bearings, non-finite values) returns 0; no output is ever
/// NaN.
int solve_p3p(const std::array<Eigen::Vector3d, 3>& bearings,
              const std::array<Eigen::Vector3d, 3>& points_w,
              std::array<SE3d, kMaxP3pSolutions>& T_c_w);

}  // namespace mer::geometry
