#pragma once
/// @file external_depth.h
/// `external` depth inference: per-frame depth maps produced elsewhere (typically a learned
/// monocular model run offline over the sequence), read from a DepthMapSource and sampled at
/// the keyframe's keypoints.
///
/// - Association: the map whose timestamp is nearest the keyframe's capture time, if within
///   `max_time_diff_s`. None: the keyframe gets no depth and DepthResult::input_missing is
///   set (the keyframe builder warns and counts it); not an error of the run.
/// - Resolution: a map of another size than the keyframe image is taken as a plain resize of
///   the full image (no crop or padding): keypoint (x, y) reads the map at
///     x_m = (x + 1/2) W_m / W - 1/2,   y_m = (y + 1/2) H_m / H - 1/2
///   (pixel centres at integer coordinates in both images).
/// - Sampling: bilinear over the 2x2 map pixels around (x_m, y_m), refused across a depth
///   edge (geometry::sample_depth with `max_depth_step`) and outside [min_depth, max_depth].
/// - Unit: `scale: unknown` (DepthScale::kUnknown) is aligned to the map by the keyframe
///   builder (robust median of map depth / map-file depth over the 3D-2D matches);
///   `metric` (DepthScale::kMetric) is metres.
/// Confidence is the constant `confidence` for every sampled depth.

#include <cstdint>
#include <optional>

#include "depth/depth_inference.h"
#include "depth/depth_map_source.h"
#include "depth/depth_options.h"

namespace mer::depth {

/// Depth maps from a DepthMapSource, sampled at the keypoints.
class ExternalDepth final : public DepthInference {
 public:
  /// `source` must outlive the backend.
  ExternalDepth(const ExternalDepthOptions& opts, DepthMapSource& source);
  std::string_view name() const override { return "external"; }
  DepthScale scale() const override;
  Status infer(const DepthRequest& req, DepthResult& out) override;

  /// Index into the source's timestamps of the map nearest `t_ns` within max_time_diff_s,
  /// or nullopt. O(log n).
  std::optional<std::size_t> nearest(std::int64_t t_ns) const;

 private:
  ExternalDepthOptions opts_;
  DepthMapSource& source_;
  std::int64_t max_dt_ns_;
  cv::Mat map_;  // the last map read (reused buffer)
};

}  // namespace mer::depth
