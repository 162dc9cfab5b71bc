#pragma once
/// @file depth_sampling.h
/// Reading a per-pixel depth map at a sub-pixel position, shared by the front end (sensor
/// depth in RGB-D mode) and the depth-inference backends (depth maps from files).

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <initializer_list>

namespace mer::geometry {

/// A row-major single-channel float image (a depth map), viewed without owning it.
struct DepthImageView {
  const float* data = nullptr;  ///< first pixel (null: no depth map)
  int width = 0;                ///< pixels per row
  int height = 0;               ///< rows
  std::size_t stride = 0;       ///< floats from one row start to the next
};

/// Depth at sub-pixel (x, y), pixel centres at integer coordinates: bilinear over the 2x2
/// pixels around it,
///   d = (1-b) ((1-a) d00 + a d01) + b ((1-a) d10 + a d11),  a = x - floor(x), b = y - floor(y).
/// 0 (no reading) outside the image, where one of the four pixels has no depth (0, negative
/// or not finite), or across a depth edge: max - min of the four > `max_step` * min. At an
/// occlusion boundary, where corners are found, an interpolated or nearest depth belongs to
/// neither surface.
inline float sample_depth(const DepthImageView& depth, float x, float y, double max_step) {
  if (depth.data == nullptr) return 0.0F;
  if (!std::isfinite(x) || !std::isfinite(y)) return 0.0F;
  const float fx = std::floor(x);
  const float fy = std::floor(y);
  if (fx < 0.0F || fy < 0.0F || fx + 1.0F >= static_cast<float>(depth.width) ||
      fy + 1.0F >= static_cast<float>(depth.height)) {
    return 0.0F;
  }
  const auto u0 = static_cast<std::size_t>(fx);
  const auto v0 = static_cast<std::size_t>(fy);
  const float* row0 = depth.data + v0 * depth.stride;
  const float* row1 = row0 + depth.stride;
  const float d00 = row0[u0];
  const float d01 = row0[u0 + 1];
  const float d10 = row1[u0];
  const float d11 = row1[u0 + 1];
  for (const float d : {d00, d01, d10, d11}) {
    if (!(d > 0.0F) || !std::isfinite(d)) return 0.0F;
  }
  const float lo = std::min({d00, d01, d10, d11});
  const float hi = std::max({d00, d01, d10, d11});
  if (hi - lo > static_cast<float>(max_step) * lo) return 0.0F;
  const float a = x - fx;
  const float b = y - fy;
  return (1.0F - b) * ((1.0F - a) * d00 + a * d01) + b * ((1.0F - a) * d10 + a * d11);
}

}  // namespace mer::geometry
