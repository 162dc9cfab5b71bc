#pragma once
/// @file rgbd_depth.h
/// `rgbd` depth inference: the sensor's depth at the keyframe's keypoints, in metres.

#include "depth/depth_inference.h"
#include "depth/depth_options.h"

namespace mer::depth {

/// RGB-D passthrough backend.
class RgbdDepth final : public DepthInference {
 public:
  explicit RgbdDepth(const RgbdDepthOptions& opts) : opts_(opts) {}
  std::string_view name() const override { return "rgbd"; }
  DepthScale scale() const override { return DepthScale::kMetric; }
  Status infer(const DepthRequest& req, DepthResult& out) override;

 private:
  RgbdDepthOptions opts_;
};

}  // namespace mer::depth
