#include "depth/rgbd_depth.h"

namespace mer::depth {

Status RgbdDepth::infer(const DepthRequest& req, DepthResult& out) {
  if (req.sensor_depth.size() < req.keypoints.size()) {
    return invalid_argument("rgbd depth: the keyframe carries no sensor depth");
  }
  out.num_valid = 0;
  for (std::size_t i = 0; i < req.keypoints.size(); ++i) {
    const double d = req.sensor_depth[i];
    const bool ok = d >= opts_.min_depth_m && d <= opts_.max_depth_m;
    out.depth[i] = ok ? static_cast<float>(d) : 0.0F;
    out.confidence[i] = ok ? 1.0F : 0.0F;
    out.support_view[i] = kNoSupport;
    out.support_keypoint[i] = kNoSupport;
    out.num_valid += ok ? 1 : 0;
  }
  return Status::ok();
}

}  // namespace mer::depth
