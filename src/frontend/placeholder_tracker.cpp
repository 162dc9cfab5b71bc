#include "frontend/placeholder_tracker.h"

#include "platform/clock.h"

namespace mer::frontend {
namespace {
constexpr std::uint64_t kFnvOffset = 1469598103934665603ULL;
constexpr std::uint64_t kFnvPrime = 1099511628211ULL;
}  // namespace

PlaceholderTracker::PlaceholderTracker(const TrackingOptions& opts, int width, int height)
    : opts_(opts), detector_(opts.fast, width, height) {}

TrackingResult PlaceholderTracker::spin_once(const hal::Frame& frame) {
  TrackingResult r;
  r.seq = frame.seq;
  r.t_ns = frame.t_ns;
  const auto corners = detector_.detect(frame.gray);
  r.num_features = static_cast<std::int32_t>(corners.size());
  std::uint64_t h = kFnvOffset;
  for (const auto& c : corners) {
    h = (h ^ static_cast<std::uint64_t>(static_cast<std::uint16_t>(c.x))) * kFnvPrime;
    h = (h ^ static_cast<std::uint64_t>(static_cast<std::uint16_t>(c.y))) * kFnvPrime;
  }
  r.feature_hash = h;
  if (opts_.busy_work_us > 0) {
    const std::int64_t until =
        platform::monotonic_now_ns() + std::int64_t{opts_.busy_work_us} * 1000;
    while (platform::monotonic_now_ns() < until) {
    }
  }
  if (!frame.has_ground_truth) {
    r.state = TrackState::kNotInitialized;
    return r;
  }
  pose_source_ = "ground_truth_passthrough";
  if (r.num_features < opts_.min_features) {
    r.state = TrackState::kLost;
    return r;
  }
  r.state = TrackState::kTracked;
  r.T_w_c = frame.T_w_c_gt;
  r.is_keyframe = (tracked_ % static_cast<std::uint64_t>(opts_.keyframe_interval)) == 0;
  ++tracked_;
  return r;
}

}  // namespace mer::frontend
