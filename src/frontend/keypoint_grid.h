#pragma once
/// @file keypoint_grid.h
/// A frame's keypoints bucketed into square cells, for descriptor searches within a radius:
/// the tracker's projection-guided matching of map-points and the initializer's search of its
/// reference keypoints. Sized once by reserve(); build() and search() do not allocate.

#include <cstdint>
#include <limits>
#include <span>
#include <vector>

#include <Eigen/Core>

#include "features/keypoint.h"

namespace mer::frontend {

/// The keypoints of one frame in a grid of `cell_px` cells.
class KeypointGrid {
 public:
  /// Best and second-best descriptor distance among the keypoints searched; index -1 when
  /// none was in range.
  struct Match {
    int best = std::numeric_limits<int>::max();
    int second = std::numeric_limits<int>::max();
    int index = -1;
  };

  /// Sizes the grid for `width` x `height` images in cells of `cell_px` px and at most
  /// `max_keypoints` keypoints (setup: allocates).
  void reserve(int width, int height, int cell_px, int max_keypoints);
  /// Buckets a frame's keypoints: the first capacity() of them (with their descriptors).
  /// The grid keeps views of the two: they must stay valid until the next build().
  void build(std::span<const features::Keypoint> keypoints,
             std::span<const features::Descriptor> descriptors);
  /// Best and second-best distance to `desc` among the keypoints within `r` px of `uv` on
  /// pyramid levels [min_level, max_level].
  Match search(const Eigen::Vector2d& uv, double r, int min_level, int max_level,
               const features::Descriptor& desc) const;

  /// Keypoints the grid was built from (level-0 px; at most capacity()).
  std::span<const features::Keypoint> keypoints() const { return keypoints_; }
  /// Their descriptors.
  std::span<const features::Descriptor> descriptors() const { return descriptors_; }
  /// Keypoints a build can hold (reserve's max_keypoints).
  std::size_t capacity() const { return items_.size(); }

 private:
  int cell_px_ = 16;
  int cols_ = 0;
  int rows_ = 0;
  std::vector<std::int32_t> start_;  // cols*rows + 1
  std::vector<std::int32_t> items_;  // keypoint indices sorted by cell
  std::vector<std::int32_t> fill_;
  std::span<const features::Keypoint> keypoints_;
  std::span<const features::Descriptor> descriptors_;
};

}  // namespace mer::frontend
