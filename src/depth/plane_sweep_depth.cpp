#include "depth/plane_sweep_depth.h"

#include <algorithm>

namespace mer::depth {

PlaneSweepDepth::PlaneSweepDepth(const PlaneSweepDepthOptions& opts)
    : opts_(opts), stereo_(opts.stereo) {
  sources_.reserve(static_cast<std::size_t>(opts.stereo.max_sources));
}

Status PlaneSweepDepth::infer(const DepthRequest& req, DepthResult& out) {
  const std::size_t n = req.keypoints.size();
  if (out.depth.size() < n || out.confidence.size() < n || out.support_view.size() < n ||
      out.support_keypoint.size() < n) {
    return invalid_argument("plane_sweep depth: output buffers smaller than the keypoints");
  }
  std::fill_n(out.depth.begin(), n, 0.0F);
  std::fill_n(out.confidence.begin(), n, 0.0F);
  std::fill_n(out.support_view.begin(), n, kNoSupport);
  std::fill_n(out.support_keypoint.begin(), n, kNoSupport);
  out.num_valid = 0;
  if (req.gray == nullptr || req.recent.empty() || !(req.depth_hint_min > 0.0) ||
      !(req.depth_hint_max > req.depth_hint_min)) {
    return Status::ok();  // nothing to sweep against yet: no depth for this keyframe
  }
  sources_.clear();
  const auto ns = std::min<std::size_t>(static_cast<std::size_t>(opts_.sources),
                                        static_cast<std::size_t>(opts_.stereo.max_sources));
  const double min_baseline =
      opts_.min_baseline_ratio * 0.5 * (req.depth_hint_min + req.depth_hint_max);
  for (const RecentView& r : req.recent) {
    if (sources_.size() >= ns) break;
    if ((r.T_w_c.translation() - req.T_w_c.translation()).norm() < min_baseline) continue;
    sources_.push_back({r.gray, r.T_w_c});
  }
  if (sources_.empty()) return Status::ok();  // every recent frame too close to the keyframe
  PlaneSweepInput in;
  in.gray = req.gray;
  in.T_w_c = req.T_w_c;
  in.K = req.K;
  in.sources = sources_;
  in.min_depth = req.depth_hint_min / opts_.range_margin;
  in.max_depth = req.depth_hint_max * opts_.range_margin;
  if (Status s = stereo_.compute(in); !s.is_ok()) return s;
  for (std::size_t i = 0; i < n; ++i) {
    const features::Keypoint& kp = req.keypoints[i];
    const float d = stereo_.depth_at(kp.x, kp.y);
    if (!(d > 0.0F)) continue;
    out.depth[i] = d;
    out.confidence[i] = stereo_.confidence_at(kp.x, kp.y);
    ++out.num_valid;
  }
  return Status::ok();
}

}  // namespace mer::depth
