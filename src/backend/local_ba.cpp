#include "backend/local_ba.h"

#include <algorithm>
#include <cmath>
#include <mutex>
#include <utility>

#include <Eigen/Geometry>

#include "backend/local_ba_run.h"
#include "platform/clock.h"

namespace mer::backend {
namespace {

constexpr std::size_t kMaxCovisibleRead = 128;  // covisible neighbours read per keyframe
constexpr double kRadToDeg = 57.29577951308232;
constexpr double kNsPerMs = 1e6;

}  // namespace

std::string_view to_string(DepthEdgeMode m) {
  switch (m) {
    case DepthEdgeMode::kMetric:
      return "metric";
    case DepthEdgeMode::kScaled:
      return "scaled";
    case DepthEdgeMode::kOff:
      break;
  }
  return "off";
}

DepthEdgeMode resolve_depth_edges(DepthEdgeSetting s, bool metric_depth) {
  switch (s) {
    case DepthEdgeSetting::kMetric:
      return DepthEdgeMode::kMetric;
    case DepthEdgeSetting::kScaled:
      return DepthEdgeMode::kScaled;
    case DepthEdgeSetting::kAuto:
      return metric_depth ? DepthEdgeMode::kMetric : DepthEdgeMode::kOff;
    case DepthEdgeSetting::kOff:
      break;
  }
  return DepthEdgeMode::kOff;
}

LocalBundleAdjuster::~LocalBundleAdjuster() = default;

LocalBundleAdjuster::LocalBundleAdjuster(const LocalBaOptions& opts, map::Map& map,
                                         std::vector<float> level_sigma2, bool deterministic,
                                         bool metric_depth)
    : opts_(opts),
      map_(map),
      level_sigma2_(std::move(level_sigma2)),
      deterministic_(deterministic),
      depth_mode_(resolve_depth_edges(opts.depth_edges, metric_depth)),
      ws_(std::make_unique<Workspace>(opts.huber_sigmas, opts.anchored_sigma_scale)) {
  // The window's poses and points: reserved for the configured window sizes up front.
  const auto window = static_cast<std::size_t>(std::max(0, opts_.window_keyframes));
  const auto fixed = static_cast<std::size_t>(std::max(0, opts_.max_fixed_keyframes));
  const auto keypoints =
      static_cast<std::size_t>(std::max(0, map_.options().max_keypoints_per_keyframe));
  ws_->poses.reserve(window + fixed);
  ws_->pose_index.reserve(window + fixed);
  ws_->points.reserve(window * keypoints);
  ws_->point_index.reserve(window * keypoints);
  ws_->outside.reserve(static_cast<std::size_t>(std::max(0, map_.options().max_keyframes)));
}

LocalBaReport LocalBundleAdjuster::spin_once(map::KeyframeId kf, const geometry::Pinhole& K) {
  if (!opts_.enabled) return {};
  const std::int64_t t0 = begin_run();
  const std::int64_t t_wait = platform::monotonic_now_ns();
  std::unique_lock<platform::PiMutex> lock(map_.writer_lock());
  const double wait_ms = platform::elapsed_ms(t_wait);
  // Window: the new keyframe and its most covisible neighbours.
  std::vector<map::CovisibleKeyframe> covis(kMaxCovisibleRead);
  const std::size_t nc = map_.covisible_keyframes(kf, covis);
  std::vector<map::KeyframeId> window{kf};
  for (std::size_t i = 0; i < nc && static_cast<int>(window.size()) < opts_.window_keyframes; ++i) {
    window.push_back(covis[i].id);
  }
  // A new keyframe's tracked pose and its step from the previous run's keyframe.
  SE3d T_w_new = SE3d::Identity();
  SE3d T_w_last = SE3d::Identity();
  const bool first_run = kf != last_kf_ || map_.keyframe_t_ns(kf) != last_kf_t_ns_;
  const bool measure_step =
      first_run && last_kf_ != map::kNoId && map_.keyframe_t_ns(last_kf_) == last_kf_t_ns_ &&
      map_.keyframe_pose(kf, T_w_new) && map_.keyframe_pose(last_kf_, T_w_last);
  LocalBaReport rep = optimize(window, K, opts_.max_iterations, !deterministic_, t0, lock,
                               /*cull_points=*/true, opts_.resolve_without_outliers);
  rep.lock_wait_ms += wait_ms;
  if (!rep.ran) return rep;
  if (first_run) {
    const double step = (T_w_new.translation() - T_w_last.translation()).norm();
    SE3d T_w_new_after = SE3d::Identity();
    SE3d T_w_last_after = SE3d::Identity();
    const double step_after =
        measure_step && map_.keyframe_pose(kf, T_w_new_after) &&
                map_.keyframe_pose(last_kf_, T_w_last_after)
            ? (T_w_new_after.translation() - T_w_last_after.translation()).norm()
            : 0.0;
    if (step > 0.0 && step_after > 0.0) {
      const Eigen::AngleAxisd turn(T_w_new.linear().transpose() * T_w_new_after.linear());
      ++totals_.new_keyframe_runs;
      totals_.sum_log_step_ratio += std::log(step_after / step);
      totals_.sum_shift_fraction +=
          (T_w_new_after.translation() - T_w_new.translation()).norm() / step;
      totals_.sum_rotation_deg += turn.angle() * kRadToDeg;
    }
    last_kf_ = kf;
    last_kf_t_ns_ = map_.keyframe_t_ns(kf);
  }
  ++totals_.runs;
  totals_.aborted += rep.aborted ? 1U : 0U;
  totals_.timed_out += rep.timed_out ? 1U : 0U;
  totals_.overruns += rep.ms > opts_.max_time_ms ? 1U : 0U;
  totals_.resolves += rep.resolved ? 1U : 0U;
  totals_.resolves_skipped += rep.resolve_skipped ? 1U : 0U;
  totals_.culled_points += static_cast<std::uint64_t>(rep.culled_points);
  totals_.outliers += static_cast<std::uint64_t>(rep.outliers);
  totals_.depth_edges += static_cast<std::uint64_t>(rep.depth_edges);
  totals_.total_ms += rep.ms;
  totals_.max_ms = std::max(totals_.max_ms, rep.ms);
  totals_.stale_writes += static_cast<std::uint64_t>(rep.stale_writes);
  totals_.lock_wait_ms += rep.lock_wait_ms;
  totals_.max_lock_wait_ms = std::max(totals_.max_lock_wait_ms, rep.lock_wait_ms);
  return rep;
}

LocalBaReport LocalBundleAdjuster::optimize_full(const geometry::Pinhole& K, int max_iterations,
                                                 bool cull_points) {
  const std::int64_t t0 = begin_run();
  std::unique_lock<platform::PiMutex> lock(map_.writer_lock());
  std::vector<map::KeyframeId> window;
  const map::KeyframeId n = map_.num_keyframes();
  for (map::KeyframeId id = 0; id < n; ++id) {
    if (map_.keyframe_is_live(id)) window.push_back(id);
  }
  return optimize(window, K, max_iterations, false, t0, lock, cull_points, /*resolve=*/true);
}

std::int64_t LocalBundleAdjuster::begin_run() {
  abort_.store(false, std::memory_order_relaxed);
  iterations_.store(0, std::memory_order_relaxed);
  const std::int64_t t0 = platform::monotonic_now_ns();
  ws_->reset();
  return t0;
}

LocalBaReport LocalBundleAdjuster::optimize(const std::vector<map::KeyframeId>& window,
                                            const geometry::Pinhole& K, int max_iterations,
                                            bool budgeted, std::int64_t t0_ns,
                                            std::unique_lock<platform::PiMutex>& lock,
                                            bool cull_points, bool resolve) {
  Run run(abort_, iterations_, t0_ns, static_cast<std::int64_t>(opts_.max_time_ms * kNsPerMs),
          budgeted, observer_, lock);
  if (!load_window(run, window)) return run.rep;
  build_problem(run, K);
  if (run.stop.stop()) return stopped_early(run);
  run.rep.keyframes = static_cast<int>(window.size());
  if (ws_->residuals.empty()) return run.rep;
  // The problem holds copies (poses, positions, keypoints): the map is not needed while Ceres
  // solves, so the other writer (the keyframe builder) may run meanwhile.
  lock.unlock();
  if (!first_solve(run, max_iterations, window.size())) return stopped_early(run);
  remove_outliers(run, resolve);
  write_back(run, cull_points);
  return run.rep;
}

}  // namespace mer::backend
