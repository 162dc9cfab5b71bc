#pragma once
/// @file camera_model.h
/// Pinhole camera model on rectified (undistorted) images.

#include <Eigen/Core>

namespace mer::geometry {

/// Pinhole intrinsics, px.
struct Pinhole {
  double fx = 0.0;  ///< focal length x, px
  double fy = 0.0;  ///< focal length y, px
  double cx = 0.0;  ///< principal point x, px
  double cy = 0.0;  ///< principal point y, px

  /// Pixel of a point in camera coordinates (z must be > 0).
  Eigen::Vector2d project(const Eigen::Vector3d& p_c) const {
    return {fx * p_c.x() / p_c.z() + cx, fy * p_c.y() / p_c.z() + cy};
  }
  /// Normalized image coordinates (x/z, y/z, 1) of a pixel.
  Eigen::Vector3d unproject(const Eigen::Vector2d& uv) const {
    return {(uv.x() - cx) / fx, (uv.y() - cy) / fy, 1.0};
  }
  /// Unit bearing vector of a pixel.
  Eigen::Vector3d bearing(const Eigen::Vector2d& uv) const { return unproject(uv).normalized(); }
  /// Same intrinsics with both focal lengths replaced by `f`.
  Pinhole with_focal(double f) const { return {f, f, cx, cy}; }
};

}  // namespace mer::geometry
