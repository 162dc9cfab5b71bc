#pragma once
/// @file depth_map_source.h
/// Where the `external` depth backend gets its depth maps from: an indexed set of per-frame
/// depth maps (e.g. a learned model's output recorded offline), one per capture time. The
/// core only sees this interface; reading files (PNG, PFM) lives outside src/ and is
/// injected by the application.

#include <cstddef>
#include <cstdint>
#include <span>
#include <string>

#include <opencv2/core/mat.hpp>

#include "core/status.h"

namespace mer::depth {

/// An indexed collection of depth maps.
class DepthMapSource {
 public:
  virtual ~DepthMapSource() = default;
  /// Where the maps come from (a folder), for messages.
  virtual std::string describe() const = 0;
  /// Capture times of the available maps, ns, strictly increasing. Fixed for the source's
  /// lifetime (indexed once, when it is created).
  virtual std::span<const std::int64_t> timestamps() const = 0;
  /// Reads map `index` (< timestamps().size()) into `depth` as CV_32FC1: depth along the
  /// optical axis in the source's unit; 0 or a non-finite value means no depth at a pixel.
  /// An error names the file and what is wrong with it. Called on the keyframe thread.
  virtual Status load(std::size_t index, cv::Mat& depth) = 0;
};

}  // namespace mer::depth
