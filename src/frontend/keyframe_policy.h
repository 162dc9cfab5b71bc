#pragma once
/// @file keyframe_policy.h
/// When a tracked frame becomes a keyframe. Any one criterion fires:
/// - `too_few_inliers`: fewer tracked inliers than `min_inliers`, or fewer than
///   `min_inlier_ratio` of the inliers the last keyframe was tracked with;
/// - `poor_spread`: the inliers occupy less than `min_spread` of a coarse image grid;
/// - `kl_jump`: after `min_spacing_s`, the KL divergence between the histogram of tracked
///   points over the keyframes they belong to, in this frame and in the previous one, exceeds
///   `kl_threshold` (tracked points suddenly belong to other keyframes: a revisit);
/// - `max_spacing`: `max_spacing_s` since the last keyframe (`rgbd_max_spacing_s` in RGB-D
///   mode, see KeyframePolicyOptions::for_mode).
/// Spacing is in time (frame timestamps), so the policy behaves the same at 10 and 30 Hz.
/// Parallax gate (monocular): while the camera has moved less than `min_baseline_ratio` of the
/// tracked points' median depth since the last keyframe, only the absolute inlier count (and
/// `max_spacing`) may fire. A keyframe closer than that to the previous one adds points
/// triangulated under little parallax and poses the back end can barely separate (rotation
/// against sideways translation); the gate is in units of the scene, not of time, so it
/// passes at once for a car at 10 Hz and waits a few frames for a slow handheld camera.
/// The histogram has a fixed number of bins; keyframes beyond it share one "other" bin.

#include <array>
#include <cstdint>
#include <span>
#include <string_view>

#include <Eigen/Core>

#include "core/options.h"
#include "core/sensor_mode.h"

namespace mer::frontend {

/// Options of the keyframe decision (config section `tracking.keyframe`).
struct KeyframePolicyOptions {
  int min_inliers = 100;
  double min_inlier_ratio = 0.6;
  double min_spread = 0.45;
  int spread_grid_cols = 8;
  int spread_grid_rows = 6;
  double min_spacing_s = 0.1;
  double max_spacing_s = 1.5;
  double kl_threshold = 0.8;
  double kl_epsilon = 1e-3;
  double min_baseline_ratio = 0.03;
  double rgbd_max_spacing_s = 0.8;

  /// The options in effect for a sensor mode: RGB-D takes rgbd_max_spacing_s and no
  /// parallax gate (its depth does not come from the poses).
  KeyframePolicyOptions for_mode(SensorMode mode) const {
    KeyframePolicyOptions o = *this;
    if (mode == SensorMode::kRgbd) {
      o.max_spacing_s = rgbd_max_spacing_s;
      o.min_baseline_ratio = 0.0;
    }
    return o;
  }

  template <class V>
  void visit(V& v) {
    v.field("min_inliers", min_inliers, "fewer tracked inliers than this makes a keyframe",
            options::Range<int>{0, 100000});
    v.field("min_inlier_ratio", min_inlier_ratio,
            "inliers below this fraction of the last keyframe's make a keyframe",
            options::Range<double>{0.0, 1.0});
    v.field("min_spread", min_spread,
            "occupied fraction of the spread grid below this makes a keyframe",
            options::Range<double>{0.0, 1.0});
    v.field("spread_grid_cols", spread_grid_cols, "spread grid columns",
            options::Range<int>{1, 64});
    v.field("spread_grid_rows", spread_grid_rows, "spread grid rows", options::Range<int>{1, 64});
    v.field("min_spacing_s", min_spacing_s,
            "time after a keyframe before the count, spread and KL criteria may fire, s",
            options::Range<double>{0.0, 1e6});
    v.field("max_spacing_s", max_spacing_s,
            "a keyframe at least this often while tracking (mono; RGB-D: rgbd_max_spacing_s), s",
            options::Range<double>{0.001, 1e6});
    v.field("kl_threshold", kl_threshold,
            "KL divergence (nats) between consecutive tracked-point histograms that fires",
            options::Range<double>{0.0, 100.0});
    v.field("kl_epsilon", kl_epsilon, "probability floor of an empty histogram bin",
            options::Range<double>{1e-9, 0.1});
    v.field("min_baseline_ratio", min_baseline_ratio,
            "camera travel since the last keyframe, over the tracked points' median depth, "
            "below which only min_inliers (and max_spacing) may fire (monocular; 0: off)",
            options::Range<double>{0.0, 10.0});
    v.field("rgbd_max_spacing_s", rgbd_max_spacing_s,
            "RGB-D: a keyframe at least this often while tracking, instead of max_spacing_s "
            "(sensor depth makes keyframes cheap, and each one anchors the map), s",
            options::Range<double>{0.001, 1e6});
  }
};

/// Which criterion made a keyframe.
enum class KeyframeReason : std::uint8_t {
  kNone = 0,
  kTooFewInliers,
  kPoorSpread,
  kKlJump,
  kMaxSpacing,
  kInitialization,
  kRelocalization,  ///< the first frame tracked again from a relocalizer's pose
};

/// Printable name of a KeyframeReason.
const char* to_string(KeyframeReason r);

/// Histogram of tracked points over the keyframes they belong to.
class KeyframeHistogram {
 public:
  /// Bins for distinct keyframes; the rest go to one overflow bin.
  static constexpr int kBins = 32;

  void clear();
  /// Counts one tracked point belonging to keyframe `kf`.
  void add(std::uint32_t kf);
  /// KL(p || q) with probabilities floored at `eps` (nats); 0 when either is empty.
  static double kl_divergence(const KeyframeHistogram& p, const KeyframeHistogram& q, double eps);
  int total() const { return total_; }
  int size() const { return used_; }
  std::uint32_t keyframe(int i) const { return ids_[static_cast<std::size_t>(i)]; }
  int count(int i) const { return counts_[static_cast<std::size_t>(i)]; }
  int overflow() const { return overflow_; }
  /// Count for keyframe `kf` (0 if absent).
  int count_of(std::uint32_t kf) const;

 private:
  std::array<std::uint32_t, kBins> ids_{};
  std::array<int, kBins> counts_{};
  int used_ = 0;
  int overflow_ = 0;
  int total_ = 0;
};

/// Everything the policy looks at for one tracked frame.
struct KeyframeEvidence {
  std::int64_t t_ns = 0;                               ///< frame timestamp
  int inliers = 0;                                     ///< tracked inliers
  std::span<const float> inlier_x;                     ///< inlier pixel columns
  std::span<const float> inlier_y;                     ///< inlier pixel rows
  const KeyframeHistogram* histogram = nullptr;        ///< tracked points over keyframes
  Eigen::Vector3d centre_w = Eigen::Vector3d::Zero();  ///< camera centre in the world
  double median_depth = 0.0;  ///< tracked points' median depth (<= 0: unknown, no gate)
};

/// The keyframe decision (state: spacing, previous histogram, inliers at the last keyframe).
class KeyframePolicy {
 public:
  KeyframePolicy(const KeyframePolicyOptions& opts, int width, int height);

  /// Decides for one tracked frame. Does not change state (call on_keyframe / on_frame).
  KeyframeReason decide(const KeyframeEvidence& e);
  /// Records the outcome of the frame the last decide() was about.
  void on_frame(const KeyframeEvidence& e, bool became_keyframe);
  /// Resets after (re)initialization: the init keyframe (at `t_ns`, camera centre
  /// `centre_w`) counts as a keyframe with `inliers`.
  void reset(int inliers, std::int64_t t_ns = 0,
             const Eigen::Vector3d& centre_w = Eigen::Vector3d::Zero());

  double last_kl() const { return last_kl_; }
  double last_spread() const { return last_spread_; }
  /// Baseline / median depth of the last decide() (negative: unknown).
  double last_baseline_ratio() const { return last_baseline_ratio_; }

 private:
  double spread(const KeyframeEvidence& e);

  KeyframePolicyOptions opts_;
  int width_;
  int height_;
  std::int64_t t_keyframe_ns_ = 0;
  int inliers_at_keyframe_ = 0;
  Eigen::Vector3d centre_at_keyframe_ = Eigen::Vector3d::Zero();
  double last_baseline_ratio_ = -1.0;
  KeyframeHistogram previous_;
  bool have_previous_ = false;
  double last_kl_ = 0.0;
  double last_spread_ = 0.0;
  std::array<std::uint8_t, 64 * 64> occupied_{};
};

}  // namespace mer::frontend
