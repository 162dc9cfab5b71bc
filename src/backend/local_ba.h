#pragma once
/// @file local_ba.h
/// Local bundle adjustment of the covisibility window around a new keyframe, on Ceres:
/// the newest keyframe and its most covisible neighbours (`window_keyframes`) and every
/// map-point they observe are optimized; other keyframes observing those points
/// (`max_fixed_keyframes`, most shared points first) are held fixed and anchor the gauge.
/// Residuals are 3D-2D reprojection errors weighted by the keypoint's pyramid sigma, with a
/// Huber kernel. A first solve with all observations is followed by a second one without
/// the observations it found to be outliers; points with too few consistent observations
/// are culled. Bounded by iterations and wall time. The optimized poses and positions are
/// written back to the map (which the tracker reads at its next frame).
///
/// Runs on the keyframe-creation thread, after the keyframe is inserted; it is the map's
/// writer while it runs.

#include <cstdint>
#include <vector>

#include "core/options.h"
#include "geometry/camera_model.h"
#include "map/map.h"

namespace mer::backend {

/// Options of the local optimization (config section `backend`).
struct LocalBaOptions {
  bool enabled = true;              ///< run local bundle adjustment after each keyframe
  int window_keyframes = 8;         ///< keyframes optimized (the new one + most covisible)
  int max_fixed_keyframes = 16;     ///< keyframes held fixed (most shared points first)
  int max_iterations = 10;          ///< Levenberg-Marquardt iterations per solve
  double max_time_ms = 60.0;        ///< wall-time cap of one solve, ms
  double huber_sigmas = 2.45;       ///< Huber kernel width, keypoint sigmas (sqrt of chi2 95 %)
  double outlier_chi2 = 5.991;      ///< squared error / sigma^2 above this is an outlier
  int min_inlier_observations = 2;  ///< points with fewer consistent observations are culled

  template <class V>
  void visit(V& v) {
    v.field("enabled", enabled, "run local bundle adjustment after each keyframe");
    v.field("window_keyframes", window_keyframes,
            "keyframes optimized: the new one and its most covisible neighbours",
            options::Range<int>{1, 100});
    v.field("max_fixed_keyframes", max_fixed_keyframes,
            "keyframes held fixed (those sharing the most points)", options::Range<int>{0, 1000});
    v.field("max_iterations", max_iterations, "Levenberg-Marquardt iterations per solve",
            options::Range<int>{1, 1000});
    v.field("max_time_ms", max_time_ms,
            "wall-time cap of one solve, ms (not applied in lockstep: results stay deterministic)",
            options::Range<double>{1.0, 100000.0});
    v.field("huber_sigmas", huber_sigmas, "Huber kernel width, keypoint sigmas",
            options::Range<double>{0.1, 100.0});
    v.field("outlier_chi2", outlier_chi2, "squared error / sigma^2 above this is an outlier",
            options::Range<double>{0.1, 1000.0});
    v.field("min_inlier_observations", min_inlier_observations,
            "points with fewer consistent observations are culled", options::Range<int>{1, 100});
  }
};

/// What one run did.
struct LocalBaReport {
  bool ran = false;
  int keyframes = 0;  ///< optimized
  int fixed_keyframes = 0;
  int points = 0;
  int observations = 0;
  int outliers = 0;
  int culled_points = 0;
  double initial_cost = 0.0;
  double final_cost = 0.0;
  double ms = 0.0;
};

/// Totals over a run (summary.json `backend`).
struct LocalBaTotals {
  std::uint64_t runs = 0;
  std::uint64_t culled_points = 0;
  std::uint64_t outliers = 0;
  double total_ms = 0.0;
  double max_ms = 0.0;
};

/// Local bundle adjustment stage: `spin_once(new keyframe) -> LocalBaReport`.
class LocalBundleAdjuster {
 public:
  /// `deterministic` (lockstep replay) drops the wall-time cap: a solve cut by the clock
  /// would make the result depend on the machine's load.
  LocalBundleAdjuster(const LocalBaOptions& opts, map::Map& map, std::vector<float> level_sigma2,
                      bool deterministic = false);

  /// Optimizes the window around `kf` with intrinsics `K`.
  LocalBaReport spin_once(map::KeyframeId kf, const geometry::Pinhole& K);

  const LocalBaTotals& totals() const { return totals_; }

 private:
  LocalBaOptions opts_;
  map::Map& map_;
  std::vector<float> level_sigma2_;
  bool deterministic_;
  LocalBaTotals totals_;
};

}  // namespace mer::backend
