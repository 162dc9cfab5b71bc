#pragma once
/// @file local_ba.h
/// Local bundle adjustment of the covisibility window around a new keyframe, on Ceres:
/// the newest keyframe and its most covisible neighbours (`window_keyframes`) and every
/// map-point they observe are optimized; other keyframes observing those points
/// (`max_fixed_keyframes`, most shared points first) are held fixed and anchor the gauge.
/// Residuals are 3D-2D reprojection errors weighted by the keypoint's pyramid sigma and
/// 3D-3D edges between a keyframe's local point (its depth-inference depth at the keypoint)
/// and the map-point, along the viewing ray (the lateral part is the 3D-2D edge), weighted by
/// the depth confidence; both with a Huber kernel. In `scaled` mode each keyframe's local
/// depth carries its own scale, optimized with the poses (the Sim(3)-style handling of
/// monocular depth whose scale is only known up to the alignment). A first solve with all
/// observations is followed by a second one without the observations it found to be outliers;
/// points with too few consistent observations are culled. Bounded by iterations and wall time
/// (`max_time_ms`, threaded mode): Ceres cannot interrupt an iteration, so an iteration is not
/// begun when the run's longest one so far would end past the solves' deadline, which is the
/// run's less the time the work after the solves took in recent runs (outlier classification,
/// the second solve's set-up, the write-back). The optimized poses and positions are written
/// back to the map (which the tracker reads at its next frame).
///
/// Threading: in threaded mode it runs on the back-end thread (high priority, below tracking)
/// for the newest keyframe the keyframe builder (depth thread) inserted; in lockstep, right
/// after the builder on the same thread. It holds the map's writer lock (map.h) while it
/// reads the window from the map and builds the problem, releases it while Ceres solves
/// (the problem holds copies), and takes it again to write back: whatever the builder did
/// meanwhile is respected (a keyframe or point freed or reused is skipped by generation, a
/// point the builder moved keeps its new position, a keyframe another writer moved — the
/// loop thread's correction, merge or full BA — keeps its new pose, a point that gained
/// observations is not culled; counted in `stale_writes`). In lockstep nothing changes in between,
/// so results are the same as with one lock span.
///
/// Abort latency (request_abort until the run returns): the request is polled per window
/// keyframe while the window is read, once it is read, every kBuildPollEvery residual blocks
/// while the problem is built, by every cost function on every evaluation (see
/// ba_residuals.h), between solver iterations and every few outlier checks. What is left
/// unpolled is Ceres' preprocessing (given the elimination ordering, so it skips its own), one
/// linear solve (fixed-size Schur specialization), Ceres' clean-up after a solve and the
/// write-back: a few ms at the largest windows. What a run builds (the problem, its cost
/// functions, the window's containers) is kept until the next run starts, which releases it
/// (after clearing the request, before its first poll): its destruction is not on the way
/// out of an aborted run, and the containers keep their capacity from run to run.

#include <array>
#include <atomic>
#include <cstdint>
#include <functional>
#include <memory>
#include <mutex>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "core/chi2.h"
#include "core/options.h"
#include "geometry/camera_model.h"
#include "map/map.h"
#include "platform/pi_mutex.h"

namespace mer::backend {

/// How keyframe depth enters the optimization, as configured (`backend.depth_edges`).
enum class DepthEdgeSetting : std::uint8_t { kAuto, kOff, kMetric, kScaled };
/// Names of DepthEdgeSetting in config, by value.
inline constexpr std::array<std::string_view, 4> kDepthEdgeSettingNames{"auto", "off", "metric",
                                                                        "scaled"};

/// backend.depth_edges in effect (`auto` resolved by the depth's scale).
enum class DepthEdgeMode : std::uint8_t { kOff, kMetric, kScaled };
/// "off", "metric" or "scaled".
std::string_view to_string(DepthEdgeMode m);
/// The mode backend.depth_edges sets: `auto` is metric when the keyframe depth is metric
/// (rgbd mode), off otherwise.
DepthEdgeMode resolve_depth_edges(DepthEdgeSetting s, bool metric_depth);

/// Options of the local optimization (config section `backend`).
struct LocalBaOptions {
  bool enabled = true;
  int window_keyframes = 8;
  int max_fixed_keyframes = 16;
  int max_iterations = 10;
  double max_time_ms = 50.0;
  double huber_sigmas = 2.45;
  double anchored_sigma_scale = 0.15;
  int anchored_min_observations = 3;
  double outlier_chi2 = kChi2TwoDof95;
  bool resolve_without_outliers = true;
  int min_inlier_observations = 2;
  int full_max_iterations = 100;
  DepthEdgeSetting depth_edges = DepthEdgeSetting::kAuto;
  double depth_sigma_rel = 0.01;
  double depth_outlier_chi2 = kChi2OneDof95;

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
            "wall-time budget of one run, all solves included, ms; runs over it are counted "
            "(not applied in lockstep: results stay deterministic)",
            options::Range<double>{1.0, 100000.0});
    v.field("huber_sigmas", huber_sigmas, "Huber kernel width, keypoint sigmas",
            options::Range<double>{0.1, 100.0});
    v.field("outlier_chi2", outlier_chi2, "squared error / sigma^2 above this is an outlier",
            options::Range<double>{0.1, 1000.0});
    v.field("resolve_without_outliers", resolve_without_outliers,
            "local runs: after the first solve, remove the observations beyond outlier_chi2 and "
            "solve again (off: they are counted and their points culled, the Huber kernel "
            "having weighed them down in the one solve; full-graph optimizations always solve "
            "again). Outside lockstep a second solve is not started with less of max_time_ms "
            "left than one recently took (backend.resolves_skipped in summary.json)");
    v.field("anchored_sigma_scale", anchored_sigma_scale,
            "sigma of a keypoint that measures its point's anchor (depth.align_keypoints: the "
            "anchor's detection or aligned to it), as a multiple of its pyramid level's sigma; "
            "below 1 such keypoints weigh more than independent detections, whose errors "
            "across views are correlated; the Huber kernel and the outlier gate stay at the "
            "level's sigma in pixels (1: no weighting)",
            options::Range<double>{0.05, 10.0});
    v.field("anchored_min_observations", anchored_min_observations,
            "anchored keypoints a point needs among its observations before "
            "anchored_sigma_scale applies to them (a young point has one or two)",
            options::Range<int>{1, 100});
    v.field("min_inlier_observations", min_inlier_observations,
            "points with fewer consistent observations are culled", options::Range<int>{1, 100});
    v.field("full_max_iterations", full_max_iterations,
            "Levenberg-Marquardt iterations of a full-graph optimization (pipeline.final_ba)",
            options::Range<int>{1, 100000});
    v.field("depth_edges", depth_edges,
            "3D-3D edges from keyframe depth: auto (metric in rgbd mode, off in mono), off, "
            "metric (depth taken as is), scaled (each keyframe's depth scale optimized)",
            options::Names<DepthEdgeSetting>{kDepthEdgeSettingNames});
    v.field("depth_sigma_rel", depth_sigma_rel,
            "sigma of a 3D-3D edge at depth confidence 1, as a fraction of the depth "
            "(divided by sqrt(confidence))",
            options::Range<double>{1e-5, 10.0});
    v.field("depth_outlier_chi2", depth_outlier_chi2,
            "squared 3D-3D error / sigma^2 above this is an outlier",
            options::Range<double>{0.1, 1000.0});
  }
};

/// What one run did.
struct LocalBaReport {
  bool ran = false;
  int keyframes = 0;  ///< optimized
  int fixed_keyframes = 0;
  int points = 0;
  int observations = 0;
  int skipped_observations = 0;  ///< left out: the point is behind the observing camera
  int depth_edges = 0;           ///< 3D-3D edges in the problem
  int outliers = 0;              ///< 3D-2D and 3D-3D edges removed as outliers
  int culled_points = 0;
  double initial_cost = 0.0;
  double final_cost = 0.0;
  double ms = 0.0;
  int iterations = 0;            ///< solver iterations, all solves
  double max_poll_gap_ms = 0.0;  ///< longest stretch without polling abort / deadline (solver
                                 ///< evaluations poll per residual block and count as polled):
                                 ///< the worst-case latency of request_abort in this run, ms
  bool aborted = false;          ///< stopped by request_abort: the progress made (the last
                                 ///< completed iteration) is kept, outliers are not classified
  bool timed_out = false;        ///< stopped by the wall-time budget (the progress made is kept)
  bool resolved = false;         ///< a second solve ran, without the outliers
  bool resolve_skipped = false;  ///< it would have, but the budget left was below what one
                                 ///< recently took (budgeted runs)
  int stale_writes = 0;          ///< results not written back: the keyframe / point changed
                                 ///< while the solver ran without the writer lock
  double lock_wait_ms = 0.0;     ///< time spent waiting for the map's writer lock (in `ms`)
};

/// Totals over a run (summary.json `backend`).
struct LocalBaTotals {
  std::uint64_t runs = 0;
  std::uint64_t culled_points = 0;
  std::uint64_t outliers = 0;
  std::uint64_t depth_edges = 0;
  std::uint64_t aborted = 0;           ///< runs pre-empted by request_abort
  std::uint64_t timed_out = 0;         ///< runs stopped by the wall-time budget
  std::uint64_t overruns = 0;          ///< runs that took longer than max_time_ms
  std::uint64_t resolves = 0;          ///< runs with a second solve (LocalBaReport::resolved)
  std::uint64_t resolves_skipped = 0;  ///< runs that skipped it for the budget
  double total_ms = 0.0;
  double max_ms = 0.0;
  std::uint64_t stale_writes = 0;  ///< results dropped at write-back (LocalBaReport)
  double lock_wait_ms = 0.0;       ///< total wait for the map's writer lock
  double max_lock_wait_ms = 0.0;   ///< longest wait of one run
  /// A new keyframe's first run, against its tracked pose (the step: its offset from the
  /// keyframe the previous run was for): how much the run moves it, a measure of what
  /// tracking missed that the map then knows (0 for the map's own frame of reference).
  std::uint64_t new_keyframe_runs = 0;  ///< runs counted below
  double sum_log_step_ratio = 0.0;      ///< sum of log(step length after / before)
  double sum_shift_fraction = 0.0;      ///< sum of |position after - before| / step length
  double sum_rotation_deg = 0.0;        ///< sum of the rotation between before and after
};

/// Where a run polls its abort request (LocalBundleAdjuster::set_poll_observer).
enum class LocalBaPoll : std::uint8_t {
  kLoad,                ///< reading the window from the map (per keyframe)
  kBuild,               ///< building the problem (every kBuildPollEvery residual blocks)
  kSolve,               ///< before a solve
  kCostEvaluation,      ///< a solver cost-only evaluation starts (cost functions poll in it)
  kJacobianEvaluation,  ///< a solver cost + Jacobian evaluation starts (cost functions poll)
  kIteration,           ///< a solver iteration ended
  kClassify,            ///< outlier checks and removals (kClassifyPollEvery, kRemovePollEvery)
};

/// Residual blocks added between two polls of the abort request while building the problem.
inline constexpr int kBuildPollEvery = 256;
/// Outlier checks between two polls of the abort request.
inline constexpr int kClassifyPollEvery = 256;
/// Outlier removals between two polls (each scans the problem's residual blocks).
inline constexpr int kRemovePollEvery = 32;

/// Local bundle adjustment stage: `spin_once(new keyframe) -> LocalBaReport`.
class LocalBundleAdjuster {
 public:
  /// `deterministic` (lockstep replay) drops the wall-time cap: a solve cut by the clock
  /// would make the result depend on the machine's load. `metric_depth`: keyframe depth is
  /// in map units from a sensor (rgbd mode), which `depth_edges: auto` uses as is.
  LocalBundleAdjuster(const LocalBaOptions& opts, map::Map& map, std::vector<float> level_sigma2,
                      bool deterministic = false, bool metric_depth = false);
  ~LocalBundleAdjuster();
  LocalBundleAdjuster(const LocalBundleAdjuster&) = delete;
  LocalBundleAdjuster& operator=(const LocalBundleAdjuster&) = delete;

  /// The 3D-3D edge mode in effect (`auto` resolved): "off", "metric" or "scaled".
  std::string_view depth_edge_mode() const { return to_string(depth_mode_); }

  /// Optimizes the window around `kf` with intrinsics `K`. Takes the map's writer lock itself
  /// (the caller must not hold it).
  LocalBaReport spin_once(map::KeyframeId kf, const geometry::Pinhole& K);

  /// Full-graph optimization: every keyframe and map-point, the first keyframe held fixed
  /// (the gauge), no wall-time budget; `request_abort` still stops it. Totals are not
  /// touched. Used offline (`mer_slam --final-ba`) and by loop closure. Takes the writer lock
  /// (the caller must not hold it). `cull_points` false: points with too few inlier
  /// observations stay (the ground-truth check runs two BAs on one point set).
  LocalBaReport optimize_full(const geometry::Pinhole& K, int max_iterations,
                              bool cull_points = true);

  /// Pre-empts the run in progress (any thread; lock-free): it stops at the next poll (see the
  /// file comment; within the solver iteration in progress), keeps the progress made (the last
  /// completed iteration) and returns. A run clears the request when it starts (on entry to
  /// spin_once / optimize_full, before it waits for the writer lock), so a request between
  /// runs is dropped: it only ever shortens the current run.
  void request_abort() noexcept { abort_.store(true, std::memory_order_relaxed); }

  /// Solver iterations completed so far by the current (or last) run; any thread.
  int iterations_in_run() const noexcept { return iterations_.load(std::memory_order_relaxed); }

  const LocalBaTotals& totals() const { return totals_; }

  /// Test hook: called on the running thread at every poll of the abort request, before the
  /// request is read (a request made from the observer is seen by that very poll; at the start
  /// of a solver evaluation, by the cost functions of that evaluation). Empty: none.
  void set_poll_observer(std::function<void(LocalBaPoll)> observer) {
    observer_ = std::move(observer);
  }

 private:
  struct Workspace;  // what a run builds, kept for the next (local_ba_run.h)
  struct Run;        // what the steps of one run share (local_ba_run.h)

  /// Starts a run: clears the abort request and the iteration count, releases what the
  /// previous run built; returns the run's start time (platform::monotonic_now_ns).
  std::int64_t begin_run();
  /// `t0_ns`: from begin_run. `lock` holds the writer lock on entry; released while Ceres
  /// solves, held on return. `resolve`: solve again once the outliers are removed. The steps
  /// below, in this order (local_ba_steps.cpp).
  LocalBaReport optimize(const std::vector<map::KeyframeId>& window, const geometry::Pinhole& K,
                         int max_iterations, bool budgeted, std::int64_t t0_ns,
                         std::unique_lock<platform::PiMutex>& lock, bool cull_points, bool resolve);
  /// 1-2. Reads the window's poses, the points they see and the fixed keyframes that see the
  /// most of them (or fixes the oldest window keyframe: the gauge). False with fewer than two
  /// poses (nothing to optimize).
  bool load_window(Run& run, const std::vector<map::KeyframeId>& window);
  /// Reads keyframe `id`'s pose into the window (`fixed`: held constant); false when it is
  /// not live, already in the window or the window is full.
  bool load_pose(map::KeyframeId id, bool fixed);
  /// 3. The residual blocks of every observation by a window pose, the poses' manifolds and
  /// constant blocks.
  void build_problem(Run& run, const geometry::Pinhole& K);
  /// The solver options and elimination ordering, then the first solve (Run::solver).
  /// False when the run was stopped before it.
  bool first_solve(Run& run, int max_iterations, std::size_t window_keyframes);
  /// One Ceres solve with the run's options, polled.
  void solve(Run& run);
  /// 4. Outliers classified (for the write-back's culling), and with `resolve` removed and
  /// solved again within what the budget leaves.
  void remove_outliers(Run& run, bool resolve);
  /// 5. The optimized poses and points into the map, under the writer lock again; the run's
  /// report completed.
  void write_back(Run& run, bool cull_points);
  /// The report of a run stopped (aborted or out of time) before a solve: the map untouched.
  LocalBaReport stopped_early(Run& run) const;
  /// Seconds of the run's budget left.
  double remaining_s(const Run& run) const;

  LocalBaOptions opts_;
  map::Map& map_;
  std::vector<float> level_sigma2_;
  bool deterministic_;
  DepthEdgeMode depth_mode_ = DepthEdgeMode::kOff;  // backend.depth_edges, `auto` resolved
  map::KeyframeId last_kf_ = map::kNoId;            ///< the keyframe the previous spin_once was for
  std::int64_t last_kf_t_ns_ = 0;                   ///< its time (a reused slot has another)
  std::atomic<bool> abort_{false};
  std::atomic<int> iterations_{0};
  LocalBaTotals totals_;
  std::function<void(LocalBaPoll)> observer_;
  std::unique_ptr<Workspace> ws_;
  double tail_reserve_ms_ = 0.0;  // budgeted runs: time after the solves (see optimize)
  double resolve_ms_ = 0.0;       // budgeted runs: what a second solve takes (see optimize)
};

}  // namespace mer::backend
