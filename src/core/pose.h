#pragma once
/// @file pose.h
/// Rigid transforms. `T_a_b` maps points from frame b to frame a: p_a = T_a_b * p_b.
/// `T_w_c` is the camera-to-world pose (camera centre = T_w_c.translation()).

#include <cstdint>

#include <Eigen/Geometry>

namespace mer {

/// SE(3) as an Eigen isometry (rotation + translation, double precision).
using SE3d = Eigen::Isometry3d;

/// A timestamped pose sample, as written to TUM files (`t tx ty tz qx qy qz qw`).
struct StampedPose {
  std::int64_t t_ns = 0;          ///< capture time, ns
  SE3d T_w_c = SE3d::Identity();  ///< camera-to-world
};

/// Builds an SE3d from a unit quaternion and translation.
inline SE3d make_se3(const Eigen::Quaterniond& q, const Eigen::Vector3d& t) {
  SE3d T = SE3d::Identity();
  T.linear() = q.normalized().toRotationMatrix();
  T.translation() = t;
  return T;
}

/// Camera-to-world pose of a camera at `eye` looking at `target`, with `up` the world up
/// direction. Camera axes: x right, y down, z forward (the usual pinhole convention).
inline SE3d look_at(const Eigen::Vector3d& eye, const Eigen::Vector3d& target,
                    const Eigen::Vector3d& up) {
  const Eigen::Vector3d z = (target - eye).normalized();
  const Eigen::Vector3d x = z.cross(up).normalized();  // right = forward x up (up is -y)
  const Eigen::Vector3d y = z.cross(x);
  SE3d T = SE3d::Identity();
  T.linear().col(0) = x;
  T.linear().col(1) = y;
  T.linear().col(2) = z;
  T.translation() = eye;
  return T;
}

}  // namespace mer
