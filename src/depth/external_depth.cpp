#include "depth/external_depth.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <string>

#include "geometry/depth_sampling.h"

namespace mer::depth {
namespace {

constexpr double kNsPerS = 1e9;

std::string seconds(std::int64_t t_ns) {
  char buf[32];
  std::snprintf(buf, sizeof(buf), "%.6f", static_cast<double>(t_ns) / kNsPerS);
  return buf;
}

}  // namespace

ExternalDepth::ExternalDepth(const ExternalDepthOptions& opts, DepthMapSource& source)
    : opts_(opts),
      source_(source),
      max_dt_ns_(static_cast<std::int64_t>(std::llround(opts.max_time_diff_s * kNsPerS))) {}

DepthScale ExternalDepth::scale() const {
  return opts_.scale == ExternalDepthScale::kMetric ? DepthScale::kMetric : DepthScale::kUnknown;
}

std::optional<std::size_t> ExternalDepth::nearest(std::int64_t t_ns) const {
  const std::span<const std::int64_t> ts = source_.timestamps();
  if (ts.empty()) return std::nullopt;
  const auto it = std::lower_bound(ts.begin(), ts.end(), t_ns);
  std::size_t best = 0;
  if (it == ts.end()) {
    best = ts.size() - 1;
  } else if (it == ts.begin()) {
    best = 0;
  } else {
    const auto hi = static_cast<std::size_t>(it - ts.begin());
    // Ties go to the earlier map.
    best = (*it - t_ns) < (t_ns - ts[hi - 1]) ? hi : hi - 1;
  }
  const std::int64_t dt = ts[best] > t_ns ? ts[best] - t_ns : t_ns - ts[best];
  if (dt > max_dt_ns_) return std::nullopt;
  return best;
}

Status ExternalDepth::infer(const DepthRequest& req, DepthResult& out) {
  const std::size_t n = req.keypoints.size();
  if (out.depth.size() < n || out.confidence.size() < n || out.support_view.size() < n ||
      out.support_keypoint.size() < n) {
    return invalid_argument("external depth: output buffers smaller than the keypoints");
  }
  std::fill_n(out.depth.begin(), n, 0.0F);
  std::fill_n(out.confidence.begin(), n, 0.0F);
  std::fill_n(out.support_view.begin(), n, kNoSupport);
  std::fill_n(out.support_keypoint.begin(), n, kNoSupport);
  out.num_valid = 0;
  out.input_missing = false;
  if (req.gray == nullptr || req.gray->empty()) {
    return invalid_argument("external depth: the request carries no keyframe image (size)");
  }
  const std::optional<std::size_t> idx = nearest(req.t_ns);
  if (!idx) {
    out.input_missing = true;
    // Short: the log ring keeps the first 200 characters (the folder comes last).
    char dt[32];
    std::snprintf(dt, sizeof(dt), "%g", opts_.max_time_diff_s);
    return input_error("no depth map within " + std::string(dt) + " s of t=" + seconds(req.t_ns) +
                       " s in '" + source_.describe() + "'");
  }
  if (Status s = source_.load(*idx, map_); !s.is_ok()) return s;
  if (map_.empty() || map_.type() != CV_32FC1) {
    return runtime_error("external depth: map " + std::to_string(*idx) + " of '" +
                         source_.describe() + "' is not a single-channel float image");
  }
  const geometry::DepthImageView view{map_.ptr<float>(), map_.cols, map_.rows, map_.step1()};
  const float sx = static_cast<float>(map_.cols) / static_cast<float>(req.gray->cols);
  const float sy = static_cast<float>(map_.rows) / static_cast<float>(req.gray->rows);
  const auto conf = static_cast<float>(opts_.confidence);
  for (std::size_t i = 0; i < n; ++i) {
    const features::Keypoint& kp = req.keypoints[i];
    const float x = (kp.x + 0.5F) * sx - 0.5F;
    const float y = (kp.y + 0.5F) * sy - 0.5F;
    const float d = geometry::sample_depth(view, x, y, opts_.max_depth_step);
    if (!(d > 0.0F) || d < opts_.min_depth || d > opts_.max_depth) continue;
    out.depth[i] = d;
    out.confidence[i] = conf;
    ++out.num_valid;
  }
  return Status::ok();
}

}  // namespace mer::depth
