#pragma once
/// @file focal_estimator.h
/// The focal length estimated from the images (`pipeline.focal: auto`): the running median of
/// the estimates so far, two-view ones before the map is initialized (Initializer) and, with
/// `tracking.focal.refine_after_init`, one per tracked frame's PnP pose after it (Tracker),
/// until it is fixed. Without estimation it stays at the calibration's focal, fixed.
/// Adding an estimate does not allocate once reserve() has run (up to
/// `tracking.focal.max_frames` + 1024 of them).

#include <cstdint>
#include <vector>

#include "frontend/tracking_options.h"

namespace mer::frontend {

/// Focal-length estimation outcome (summary.json `focal`).
struct FocalReport {
  bool estimated = false;          ///< focal: auto
  double initial = 0.0;            ///< guess the run started from, px
  double value = 0.0;              ///< current (final) focal length, px
  bool fixed = false;              ///< stopped estimating
  std::int64_t fixed_at_seq = -1;  ///< frame it was fixed at
  int estimates = 0;               ///< estimates the running median was taken over
};

/// The running focal-length estimate of one tracker.
class FocalEstimator {
 public:
  /// Starts from `initial` (px, the calibration's focal); `estimated` is `focal: auto`
  /// (otherwise the focal is fixed at `initial`).
  FocalEstimator(const FocalOptions& opts, double initial, bool estimated);

  /// Sizes the estimate buffers (setup: allocates).
  void reserve();
  /// Whether initialization must wait for more two-view estimates
  /// (`tracking.focal.min_init_estimates`).
  bool init_waits() const {
    return report_.estimated && report_.estimates < opts_.min_init_estimates;
  }
  /// Adds a two-view estimate made before initialization: the focal becomes the median of
  /// all estimates, which is returned.
  double add_two_view(double f);
  /// Adds the PnP estimate of tracked frame `seq`, `frames_since_init` tracked frames after
  /// initialization: the focal becomes the median of all estimates, and is fixed once
  /// `stable_frames` estimates in a row are within `stable_tolerance` of it, or after
  /// `max_frames`. False (nothing changes) when `f` is not a valid focal length.
  bool add_tracked(double f, std::uint64_t seq, std::uint64_t frames_since_init);
  /// The map was initialized at frame `seq`: the focal is fixed at its median unless
  /// `tracking.focal.refine_after_init`.
  void fix_at_init(std::uint64_t seq);
  /// Whether PnP still estimates the focal jointly with the pose.
  bool refining() const { return report_.estimated && !report_.fixed; }
  /// Current focal length, px.
  double value() const { return report_.value; }
  const FocalReport& report() const { return report_; }

 private:
  double median();

  FocalOptions opts_;
  FocalReport report_;
  std::vector<double> estimates_;
  std::vector<double> scratch_;
  int stable_count_ = 0;  // consecutive tracked estimates within tolerance of the median
};

}  // namespace mer::frontend
