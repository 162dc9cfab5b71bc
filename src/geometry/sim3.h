#pragma once
/// @file sim3.h
/// Similarity transforms Sim(3): p_a = s * R * p_b + t. `S_a_b` maps points from frame b to
/// frame a, like SE3d. Monocular maps are known up to scale, so a loop found after the scale
/// drifted is a similarity between the two ends of the loop, not a rigid motion.

#include <cmath>
#include <span>

#include <Eigen/Core>
#include <Eigen/Geometry>

#include "core/pose.h"

namespace mer::geometry {

/// A similarity transform (rotation, translation, positive scale).
struct Sim3d {
  Eigen::Matrix3d R = Eigen::Matrix3d::Identity();  ///< rotation
  Eigen::Vector3d t = Eigen::Vector3d::Zero();      ///< translation
  double s = 1.0;                                   ///< scale (> 0)

  /// The rigid transform T as a similarity of scale 1.
  static Sim3d from_se3(const SE3d& T) { return Sim3d{T.linear(), T.translation(), 1.0}; }
  /// The rigid part (rotation, translation): the camera pose a corrected keyframe keeps.
  SE3d rigid() const {
    SE3d T = SE3d::Identity();
    T.linear() = R;
    T.translation() = t;
    return T;
  }
  /// Maps a point: s * R * p + t.
  Eigen::Vector3d operator*(const Eigen::Vector3d& p) const { return s * (R * p) + t; }
  /// Composition: (this * o)(p) = this(o(p)).
  Sim3d operator*(const Sim3d& o) const { return Sim3d{R * o.R, s * (R * o.t) + t, s * o.s}; }
  /// Inverse: p_b = (R^T (p_a - t)) / s.
  Sim3d inverse() const {
    const Eigen::Matrix3d Rt = R.transpose();
    return Sim3d{Rt, -(Rt * t) / s, 1.0 / s};
  }
};

/// A camera-to-world pose moved by a world-frame similarity: the camera keeps its rigid
/// pose in the corrected world (its local geometry is scaled by S.s).
inline SE3d apply_to_pose(const Sim3d& S_w2_w1, const SE3d& T_w1_c) {
  return (S_w2_w1 * Sim3d::from_se3(T_w1_c)).rigid();
}

/// Least-squares similarity (Umeyama) mapping the columns of `src` onto `dst` (3 x n, n >= 3);
/// with `with_scale` false the scale stays 1 (a rigid fit).
inline Sim3d umeyama_sim3(const Eigen::Matrix3Xd& src, const Eigen::Matrix3Xd& dst,
                          bool with_scale) {
  const Eigen::Matrix4d M = Eigen::umeyama(src, dst, with_scale);
  Sim3d S;
  const Eigen::Matrix3d s_r = M.topLeftCorner<3, 3>();
  S.s = with_scale ? std::cbrt(s_r.determinant()) : 1.0;
  S.R = s_r / S.s;
  S.t = M.topRightCorner<3, 1>();
  return S;
}

/// The similarity S_b_a taking camera poses `from` (camera -> world a) onto `to` (camera ->
/// world b), same order, at least one pair: apply_to_pose(S, from[i]) ~ to[i]. Its rotation is
/// the chordal mean of the pairs' rotations from one world to the other (the orientations fix
/// it even when the cameras lie on a line), then scale and translation by least squares on
/// the camera centres (scale 1 when they coincide, or when `with_scale` is false).
Sim3d fit_similarity_to_poses(std::span<const SE3d> from, std::span<const SE3d> to,
                              bool with_scale = true);

}  // namespace mer::geometry
