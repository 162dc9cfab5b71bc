#pragma once
/// @file placeholder_tracker.h
/// The tracking stage until the localization front end lands: it does the real per-frame
/// feature work (allocation-free FAST-9 with bucketing) so the pipeline's latency and
/// allocation accounting measure something, but it does not estimate poses. When the
/// source provides ground truth, the pose is passed through from it and the run is
/// labelled `"pose_source": "ground_truth_passthrough"` in summary.json; without ground
/// truth every frame is reported as not initialized.

#include <cstdint>
#include <memory>

#include "core/options.h"
#include "features/fast_detector.h"
#include "frontend/tracking_result.h"
#include "hal/camera.h"

namespace mer::frontend {

/// Options of the tracking stage (config section `tracking`).
struct TrackingOptions {
  features::FastOptions fast;  ///< corner detection
  int keyframe_interval = 10;  ///< placeholder keyframe policy: every N-th tracked frame
  int min_features = 30;       ///< fewer features than this marks the frame lost
  int busy_work_us = 0;        ///< extra busy-wait per frame, us (load tests of the drop policy)

  template <class V>
  void visit(V& v) {
    v.section("fast", fast, "FAST-9 corner detection with grid bucketing");
    v.field("keyframe_interval", keyframe_interval, "a keyframe every N tracked frames",
            options::Range<int>{1, 100000});
    v.field("min_features", min_features, "fewer features than this marks the frame lost",
            options::Range<int>{0, 100000});
    v.field("busy_work_us", busy_work_us,
            "extra busy-wait per frame, us (simulates a heavier tracker; 0 in normal use)",
            options::Range<int>{0, 10000000});
  }
};

/// Tracking stage placeholder: `spin_once(frame) -> TrackingResult`.
class PlaceholderTracker {
 public:
  /// Allocates the detector for `width` x `height` images.
  PlaceholderTracker(const TrackingOptions& opts, int width, int height);

  /// Processes one frame. No heap allocation.
  TrackingResult spin_once(const hal::Frame& frame);

  /// "ground_truth_passthrough" or "none": where poses come from.
  const char* pose_source() const { return pose_source_; }

 private:
  TrackingOptions opts_;
  features::FastDetector detector_;
  std::uint64_t tracked_ = 0;
  const char* pose_source_ = "none";
};

}  // namespace mer::frontend
