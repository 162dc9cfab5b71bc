#include "backend/local_ba.h"

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <memory>
#include <mutex>
#include <optional>
#include <unordered_map>
#include <utility>

#include <Eigen/Geometry>
#include <ceres/ceres.h>

#include "backend/ba_residuals.h"

namespace mer::backend {
namespace {

constexpr std::size_t kMaxCovisibleRead = 128;    // covisible neighbours read per keyframe
constexpr std::size_t kMaxObservationsRead = 64;  // observations read per point
constexpr double kMsPerS = 1000.0;
constexpr double kRadToDeg = 57.29577951308232;
constexpr std::size_t kMaxDenseSchurKeyframes = 64;  // larger windows: sparse Schur
constexpr double kMinDepth = 1e-6;  // camera z below which an observation is not evaluable
/// Per run, the time held back from the solves for the work after them decays by this factor
/// towards the latest measurement (it follows a shrinking window within a few runs).
constexpr double kTailReserveDecay = 0.8;

/// Polls the abort request and the run's deadline: at the window loading and problem
/// building steps (check), as the solver's iteration callback (between iterations) and as its
/// evaluation callback (an evaluation starts; the cost functions poll the request inside it).
/// Times the stretches between polls (max_gap_ms).
class StopCallback final : public ceres::IterationCallback, public ceres::EvaluationCallback {
 public:
  using Clock = std::chrono::steady_clock;
  StopCallback(const std::atomic<bool>& abort, std::atomic<int>& iterations, Clock::time_point t0,
               Clock::time_point deadline, bool use_deadline,
               const std::function<void(LocalBaPoll)>& observer)
      : abort_(abort),
        iterations_(iterations),
        last_poll_(t0),
        deadline_(deadline),
        use_deadline_(use_deadline),
        observer_(observer) {}

  ceres::CallbackReturnType operator()(const ceres::IterationSummary& summary) override {
    if (summary.iteration > 0) iterations_.fetch_add(1, std::memory_order_relaxed);
    // The cost of the best point so far. An evaluation cut by an abort leaves summary.cost
    // meaningless; cost_change comes from the complete cost-only evaluation of the accepted
    // step (see ba_residuals.h).
    const bool cut = abort_.load(std::memory_order_relaxed);
    if (summary.iteration == 0) {
      cost_known = !cut;
      cost = cut ? 0.0 : summary.cost;
      if (first_solve) initial_cost = cost;
    } else if (summary.step_is_successful) {
      cost = cut ? cost - summary.cost_change : summary.cost;
    }
    // SOLVER_TERMINATE_SUCCESSFULLY keeps the parameters of the last accepted iteration.
    if (check(LocalBaPoll::kIteration)) return ceres::SOLVER_TERMINATE_SUCCESSFULLY;
    // Deadline, predicted: an iteration is not interrupted, so one that would end past the
    // solves' deadline (the run's, less the time the run needs after its solves) is not begun.
    const Clock::time_point now = last_poll_;  // check() just marked it
    if (summary.iteration > 0)
      longest_iteration_ = std::max(longest_iteration_, now - iteration_t_);
    iteration_t_ = now;
    if (use_deadline_ && now + longest_iteration_ >= solve_deadline_) {
      timed_out = true;
      return ceres::SOLVER_TERMINATE_SUCCESSFULLY;
    }
    return ceres::SOLVER_CONTINUE;
  }
  /// The solves end by this time (before the run's deadline: the run's work after them).
  void set_solve_deadline(Clock::time_point t) { solve_deadline_ = t; }
  /// Marks the start of a solve (its first iteration is timed from here).
  void solve_started() { iteration_t_ = Clock::now(); }
  void PrepareForEvaluation(bool evaluate_jacobians, bool /*new_evaluation_point*/) override {
    if (!in_solve) return;  // Problem::EvaluateResidualBlock outside a solve
    if (observer_) {
      observer_(evaluate_jacobians ? LocalBaPoll::kJacobianEvaluation
                                   : LocalBaPoll::kCostEvaluation);
    }
    (void)mark();
    in_evaluation_ = true;  // the cost functions poll from here on
  }
  /// Polls the abort request and the deadline; true (and sticky) once the run must stop.
  bool check(LocalBaPoll where) {
    if (observer_) observer_(where);
    const Clock::time_point now = mark();
    if (!aborted && abort_.load(std::memory_order_relaxed)) aborted = true;
    if (!timed_out && use_deadline_ && now >= deadline_) timed_out = true;
    return stop();
  }
  /// Times the stretch since the previous poll (max_gap_ms); an evaluation counts as polled.
  Clock::time_point mark() {
    const Clock::time_point now = Clock::now();
    if (!in_evaluation_) {
      max_gap_ms =
          std::max(max_gap_ms, std::chrono::duration<double, std::milli>(now - last_poll_).count());
    }
    in_evaluation_ = false;
    last_poll_ = now;
    return now;
  }
  /// True once the run must not start another solve.
  bool stop() const { return aborted || timed_out; }

  bool aborted = false;
  bool timed_out = false;
  bool in_solve = false;    // forward evaluation callbacks (set around ceres::Solve)
  bool first_solve = true;  // iteration 0 gives initial_cost
  double max_gap_ms = 0.0;  // longest interval between two polls: the worst abort latency
  bool cost_known = false;  // initial_cost and cost are valid (the first solve evaluated)
  double initial_cost = 0.0;
  double cost = 0.0;  // of the best point of the last solve

 private:
  const std::atomic<bool>& abort_;
  std::atomic<int>& iterations_;
  Clock::time_point last_poll_;
  Clock::time_point deadline_;
  Clock::time_point solve_deadline_ = deadline_;
  Clock::time_point iteration_t_;  // the last iteration ended (or began)
  Clock::duration longest_iteration_ = Clock::duration::zero();  // of this run
  bool use_deadline_;
  const std::function<void(LocalBaPoll)>& observer_;
  bool in_evaluation_ = false;
};

/// Storage of cost functions (Ceres' are neither copyable nor movable): one allocation for
/// all blocks instead of one per block, kept from run to run (grown when a run needs more).
/// Addresses stay put until the next reset.
template <class T>
class CostArena {
 public:
  /// Destroys the cost functions of the previous run and makes room for `capacity`.
  void reset(std::size_t capacity) {
    for (std::size_t i = 0; i < size_; ++i) slots_[i].reset();
    size_ = 0;
    if (capacity > capacity_) {
      slots_ = std::make_unique<std::optional<T>[]>(capacity);
      capacity_ = capacity;
    }
  }
  /// nullptr when full.
  template <class... Args>
  T* emplace(Args&&... args) {
    if (size_ == capacity_) return nullptr;
    return &slots_[size_++].emplace(std::forward<Args>(args)...);
  }

 private:
  std::unique_ptr<std::optional<T>[]> slots_;
  std::size_t capacity_ = 0;
  std::size_t size_ = 0;
};

struct PoseBlock {
  std::array<double, 4> q{};  // x, y, z, w (Eigen storage order)
  std::array<double, 3> t{};
  double depth_scale = 1.0;  // s of the keyframe's local depth
  bool fixed = false;
  map::Generation generation = map::kNoGeneration;  // occupant the pose was read from
  SE3d T_w_c_read = SE3d::Identity();               // read from the map (moved: not written)
};

struct PointBlock {
  std::array<double, 3> X{};                           // optimized position
  Eigen::Vector3d p_w_read = Eigen::Vector3d::Zero();  // read from the map (moved: not written)
  map::Generation generation = map::kNoGeneration;     // occupant of the slot when read
  std::size_t observations = 0;  // observations when read (new ones: not judged, not culled)
};

struct Observation {
  map::KeyframeId kf;
  map::PointId p;
  ceres::ResidualBlockId id;
  bool depth = false;  // a 3D-3D edge (else 3D-2D)
  // The keypoint's sigma over its level's (anchored_sigma_scale, or 1): the outlier gate
  // tests the error against the level's sigma, whatever weight the keypoint has.
  double sigma_scale = 1.0;
};

}  // namespace

/// What a run builds, kept from one run to the next: the containers keep their capacity (no
/// first touch of fresh memory once the windows stopped growing), and the previous run's
/// problem, cost functions and containers are released at the start of the next run rather
/// than before a run returns, which keeps their destruction out of the abort latency.
struct LocalBundleAdjuster::Workspace {
  Workspace(double huber_width, double anchored_sigma_scale)
      : huber(huber_width), huber_anchored(huber_width / anchored_sigma_scale) {}

  /// Releases the previous run's problem and cost functions and empties the containers
  /// (their capacity is kept). Before any other member is touched: the problem refers to them.
  void reset() {
    problem.reset();
    ordering->Clear();
    reprojection_costs.reset(0);
    depth_costs.reset(0);
    poses.clear();
    pose_index.clear();
    points.clear();
    point_index.clear();
    outside.clear();
    fixed_list.clear();
    residuals.clear();
    point_obs.clear();
    outliers.clear();
  }

  // The window (see optimize): keyframe poses and map-points, in insertion order.
  std::vector<std::pair<map::KeyframeId, PoseBlock>> poses;
  std::unordered_map<map::KeyframeId, std::size_t> pose_index;
  std::vector<std::pair<map::PointId, PointBlock>> points;
  std::unordered_map<map::PointId, std::size_t> point_index;
  std::unordered_map<map::KeyframeId, int> outside;  // keyframe -> shared points
  std::vector<std::pair<map::KeyframeId, int>> fixed_list;
  std::vector<std::pair<map::KeyframeId, std::uint32_t>> obs =
      std::vector<std::pair<map::KeyframeId, std::uint32_t>>(kMaxObservationsRead);
  // The problem and what it refers to.
  CostArena<ReprojectionCost> reprojection_costs;
  CostArena<DepthCost> depth_costs;
  RotationManifold quat_manifold;
  ceres::HuberLoss huber;
  // For a keypoint weighted by anchored_sigma_scale: its residual is divided by the scaled
  // sigma, so a kernel this much narrower bends at the same error in pixels as `huber`.
  ceres::HuberLoss huber_anchored;
  std::optional<ceres::Problem> problem;
  std::shared_ptr<ceres::ParameterBlockOrdering> ordering =
      std::make_shared<ceres::ParameterBlockOrdering>();
  std::vector<Observation> residuals;
  // Outlier classification.
  std::unordered_map<map::PointId, std::pair<int, int>> point_obs;  // inliers, outliers
  std::vector<ceres::ResidualBlockId> outliers;
};

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
  const auto t0 = begin_run();
  const auto t_wait = std::chrono::steady_clock::now();
  std::unique_lock<platform::PiMutex> lock(map_.writer_lock());
  const double wait_ms =
      std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t_wait).count();
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
  const auto t0 = begin_run();
  std::unique_lock<platform::PiMutex> lock(map_.writer_lock());
  std::vector<map::KeyframeId> window;
  const map::KeyframeId n = map_.num_keyframes();
  for (map::KeyframeId id = 0; id < n; ++id) {
    if (map_.keyframe_is_live(id)) window.push_back(id);
  }
  return optimize(window, K, max_iterations, false, t0, lock, cull_points, /*resolve=*/true);
}

std::chrono::steady_clock::time_point LocalBundleAdjuster::begin_run() {
  abort_.store(false, std::memory_order_relaxed);
  iterations_.store(0, std::memory_order_relaxed);
  const auto t0 = std::chrono::steady_clock::now();
  ws_->reset();
  return t0;
}

LocalBaReport LocalBundleAdjuster::optimize(const std::vector<map::KeyframeId>& window,
                                            const geometry::Pinhole& K, int max_iterations,
                                            bool budgeted, std::chrono::steady_clock::time_point t0,
                                            std::unique_lock<platform::PiMutex>& lock,
                                            bool cull_points, bool resolve) {
  LocalBaReport rep;
  Workspace& ws = *ws_;
  const auto budget = std::chrono::duration_cast<std::chrono::steady_clock::duration>(
      std::chrono::duration<double, std::milli>(opts_.max_time_ms));
  StopCallback stop(abort_, iterations_, t0, t0 + budget, budgeted, observer_);

  // Parameter blocks live in arrays, in insertion order: Ceres orders a group of the given
  // elimination ordering by address, which must not depend on the heap for lockstep runs to
  // be repeatable. The capacities are reserved: the blocks' addresses must not move.
  auto& poses = ws.poses;
  auto& pose_index = ws.pose_index;
  poses.reserve(window.size() + static_cast<std::size_t>(std::max(0, opts_.max_fixed_keyframes)));
  auto load_pose = [&](map::KeyframeId id, bool fixed) {
    SE3d T_w_c;
    if (!map_.keyframe_pose(id, T_w_c)) return false;
    const SE3d T_c_w = T_w_c.inverse();
    PoseBlock b;
    const Eigen::Quaterniond q(T_c_w.linear());
    b.q = {q.x(), q.y(), q.z(), q.w()};
    b.t = {T_c_w.translation().x(), T_c_w.translation().y(), T_c_w.translation().z()};
    b.fixed = fixed;
    b.generation = map_.keyframe_generation(id);
    b.T_w_c_read = T_w_c;
    if (poses.size() == poses.capacity() || !pose_index.emplace(id, poses.size()).second) {
      return false;
    }
    poses.emplace_back(id, b);
    return true;
  };
  for (const map::KeyframeId id : window) (void)load_pose(id, false);
  if (poses.size() < 2) return rep;

  // 2. Points seen by the window, and the keyframes outside it that see them.
  auto& points = ws.points;
  auto& point_index = ws.point_index;
  std::size_t max_points = 0;
  for (const map::KeyframeId id : window) max_points += map_.keyframe_keypoints(id).size();
  points.reserve(max_points);
  auto& outside = ws.outside;  // keyframe -> shared points
  auto& obs = ws.obs;
  std::size_t max_blocks = 0;  // upper bound of the residual blocks (cost functions' storage)
  for (const map::KeyframeId id : window) {
    if (stop.check(LocalBaPoll::kLoad)) break;
    const auto n = static_cast<std::uint32_t>(map_.keyframe_keypoints(id).size());
    for (std::uint32_t k = 0; k < n; ++k) {
      const map::PointId p = map_.keyframe_point(id, k);
      if (p == map::kNoId || point_index.count(p) != 0) continue;
      map::PointView pv;
      if (!map_.read_point(p, pv)) continue;
      point_index.emplace(p, points.size());
      points.emplace_back(p, PointBlock{{pv.p_w.x(), pv.p_w.y(), pv.p_w.z()},
                                        pv.p_w,
                                        pv.generation,
                                        map_.point_num_observations(p)});
      const std::size_t no = map_.point_observations(p, obs);
      max_blocks += no;
      for (std::size_t o = 0; o < no; ++o) {
        if (pose_index.count(obs[o].first) == 0) ++outside[obs[o].first];
      }
    }
  }
  // The window is read: a poll before selecting the fixed keyframes and building the problem.
  if (!stop.stop()) (void)stop.check(LocalBaPoll::kLoad);
  auto& fixed_list = ws.fixed_list;
  fixed_list.assign(outside.begin(), outside.end());
  std::sort(fixed_list.begin(), fixed_list.end(), [](const auto& a, const auto& b) {
    return a.second != b.second ? a.second > b.second : a.first < b.first;
  });
  for (const auto& [id, count] : fixed_list) {
    if (rep.fixed_keyframes >= opts_.max_fixed_keyframes || stop.stop()) break;
    if (load_pose(id, true)) ++rep.fixed_keyframes;
  }
  // Gauge: without a fixed keyframe, hold the oldest window keyframe (by frame sequence:
  // slots are reused, so ids are not in time order).
  if (rep.fixed_keyframes == 0) {
    map::KeyframeId oldest = window.front();
    for (const map::KeyframeId id : window) {
      if (pose_index.count(id) != 0 && map_.keyframe_seq(id) < map_.keyframe_seq(oldest)) {
        oldest = id;
      }
    }
    poses[pose_index.at(oldest)].second.fixed = true;
  }

  // 3. Problem. The cost functions live in two arrays sized up front (their addresses must not
  //    move) rather than in one heap block each. Without fast removal the problem keeps no
  //    per-parameter residual sets (half of its construction and destruction); removing an
  //    outlier is then a scan of the residual blocks, done a few hundred times at most,
  //    polled. The problem outlives the run (Workspace): its evaluation callback, `stop`,
  //    does not, which is fine as only its destruction is left, and that does not call it.
  if (!stop.stop()) (void)stop.check(LocalBaPoll::kBuild);
  const bool use_depth = depth_mode_ != DepthEdgeMode::kOff;
  auto& reprojection_costs = ws.reprojection_costs;
  auto& depth_costs = ws.depth_costs;
  reprojection_costs.reset(max_blocks);
  depth_costs.reset(use_depth ? max_blocks : 0);
  RotationManifold& quat_manifold = ws.quat_manifold;
  ceres::HuberLoss& huber = ws.huber;
  ceres::Problem::Options popts;
  popts.cost_function_ownership = ceres::DO_NOT_TAKE_OWNERSHIP;
  popts.manifold_ownership = ceres::DO_NOT_TAKE_OWNERSHIP;
  popts.loss_function_ownership = ceres::DO_NOT_TAKE_OWNERSHIP;
  popts.enable_fast_removal = false;
  popts.evaluation_callback = &stop;
  ceres::Problem& problem = ws.problem.emplace(popts);
  auto& residuals = ws.residuals;
  residuals.reserve(max_blocks * (use_depth ? 2 : 1));
  int until_poll = kBuildPollEvery;
  for (auto& [p, pt] : points) {
    if (stop.stop()) break;
    std::array<double, 3>& X = pt.X;
    const std::size_t no = map_.point_observations(p, obs);
    int anchored = 0;  // the point's anchored keypoints (anchored_min_observations)
    for (std::size_t o = 0; o < no && opts_.anchored_sigma_scale != 1.0; ++o) {
      const auto kps = map_.keyframe_keypoints(obs[o].first);
      anchored += obs[o].second < kps.size() && kps[obs[o].second].anchored != 0 ? 1 : 0;
    }
    const double anchored_scale =
        anchored >= opts_.anchored_min_observations ? opts_.anchored_sigma_scale : 1.0;
    for (std::size_t o = 0; o < no; ++o) {
      auto it = pose_index.find(obs[o].first);
      if (it == pose_index.end()) continue;
      const auto kps = map_.keyframe_keypoints(obs[o].first);
      if (obs[o].second >= kps.size()) continue;
      const features::Keypoint& kp = kps[obs[o].second];
      const double scale = kp.anchored != 0 ? anchored_scale : 1.0;
      const double inv_sigma =
          1.0 /
          (std::sqrt(static_cast<double>(features::level_sigma2(level_sigma2_, kp.level))) * scale);
      PoseBlock& b = poses[it->second].second;
      // A point behind (or on) a camera that observes it cannot be evaluated: leave that
      // observation out (a solve whose first evaluation fails does nothing at all).
      const Eigen::Vector3d p_c =
          Eigen::Map<const Eigen::Quaterniond>(b.q.data()) * Eigen::Vector3d(X[0], X[1], X[2]) +
          Eigen::Vector3d(b.t[0], b.t[1], b.t[2]);
      if (!(p_c.z() > kMinDepth)) {
        ++rep.skipped_observations;
        continue;
      }
      if (--until_poll <= 0) {
        until_poll = kBuildPollEvery;
        if (stop.check(LocalBaPoll::kBuild)) break;
      }
      ReprojectionCost* cost = reprojection_costs.emplace(kp.x, kp.y, inv_sigma, K, &abort_);
      if (cost == nullptr) break;  // (cannot happen: max_blocks bounds the blocks)
      const ceres::ResidualBlockId rid = problem.AddResidualBlock(
          cost, scale != 1.0 ? &ws.huber_anchored : &huber, b.q.data(), b.t.data(), X.data());
      residuals.push_back({obs[o].first, p, rid, false, scale});
      if (!use_depth) continue;
      const float d = map_.keyframe_depth(obs[o].first, obs[o].second);
      const float conf = map_.keyframe_depth_confidence(obs[o].first, obs[o].second);
      if (d <= 0.0F || conf <= 0.0F) continue;
      const double sigma = opts_.depth_sigma_rel * d / std::sqrt(static_cast<double>(conf));
      DepthCost* dcost = depth_costs.emplace(d, 1.0 / sigma, &abort_);
      if (dcost == nullptr) continue;  // (cannot happen)
      const ceres::ResidualBlockId did =
          problem.AddResidualBlock(dcost, &huber, b.q.data(), b.t.data(), X.data(), &b.depth_scale);
      residuals.push_back({obs[o].first, p, did, true});
      ++rep.depth_edges;
    }
  }
  // Aborted (or out of time) while building: nothing was optimized, the map is untouched.
  auto stopped_early = [&] {
    (void)stop.mark();
    rep.ran = true;
    rep.max_poll_gap_ms = stop.max_gap_ms;
    rep.aborted = stop.aborted;
    rep.timed_out = stop.timed_out;
    rep.ms =
        std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
    return rep;
  };
  if (stop.stop()) return stopped_early();
  for (auto& [id, b] : poses) {
    if (!problem.HasParameterBlock(b.q.data())) continue;
    problem.SetManifold(b.q.data(), &quat_manifold);
    if (b.fixed) {
      problem.SetParameterBlockConstant(b.q.data());
      problem.SetParameterBlockConstant(b.t.data());
    }
    // Metric depth keeps its scale; in scaled mode a free keyframe's scale is optimized
    // (a fixed keyframe's scale stays 1: its depth is already aligned to the map).
    if (problem.HasParameterBlock(&b.depth_scale) &&
        (b.fixed || depth_mode_ != DepthEdgeMode::kScaled)) {
      problem.SetParameterBlockConstant(&b.depth_scale);
    }
  }
  rep.keyframes = static_cast<int>(window.size());
  rep.points = static_cast<int>(points.size());
  rep.observations = static_cast<int>(residuals.size()) - rep.depth_edges;
  if (residuals.empty()) return rep;
  // The problem holds copies (poses, positions, keypoints): the map is not needed while Ceres
  // solves, so the other writer (the keyframe builder) may run meanwhile.
  lock.unlock();

  ceres::Solver::Options sopts;
  // A local window's reduced camera system is small and dense; a full graph's is large and
  // sparse (each keyframe shares points with a few others only).
  sopts.linear_solver_type =
      window.size() <= kMaxDenseSchurKeyframes ? ceres::DENSE_SCHUR : ceres::SPARSE_SCHUR;
  // Eigen's sparse Cholesky for the large ones: SuiteSparse's runs OpenMP regions (a thread
  // pool of its own) on the back-end thread, which also runs the full BA after a loop.
  if (ceres::IsSparseLinearAlgebraLibraryTypeAvailable(ceres::EIGEN_SPARSE)) {
    sopts.sparse_linear_algebra_library_type = ceres::EIGEN_SPARSE;
  }
  sopts.max_num_iterations = max_iterations;
  sopts.num_threads = 1;
  sopts.logging_type = ceres::SILENT;
  sopts.callbacks.push_back(&stop);
  // The Schur elimination ordering, given: points first, then the keyframe blocks. Ceres
  // would otherwise find it itself (a graph search over all blocks in its preprocessing).
  const std::shared_ptr<ceres::ParameterBlockOrdering>& ordering = ws.ordering;
  for (auto& [p, pt] : points) {
    if (problem.HasParameterBlock(pt.X.data())) ordering->AddElementToGroup(pt.X.data(), 0);
  }
  for (auto& [id, b] : poses) {
    if (!problem.HasParameterBlock(b.q.data())) continue;
    ordering->AddElementToGroup(b.q.data(), 1);
    ordering->AddElementToGroup(b.t.data(), 1);
    if (problem.HasParameterBlock(&b.depth_scale)) {
      ordering->AddElementToGroup(&b.depth_scale, 1);
    }
  }
  sopts.linear_solver_ordering = ordering;
  if (stop.check(LocalBaPoll::kSolve)) return stopped_early();
  auto remaining_s = [&] {
    const double used_ms =
        std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
    return std::max(0.0, opts_.max_time_ms - used_ms) / kMsPerS;
  };
  if (budgeted) sopts.max_solver_time_in_seconds = remaining_s();
  ceres::Solver::Summary summary;
  stop.set_solve_deadline(t0 + budget -
                          std::chrono::duration_cast<std::chrono::steady_clock::duration>(
                              std::chrono::duration<double, std::milli>(
                                  std::min(tail_reserve_ms_, opts_.max_time_ms))));
  auto solve = [&] {
    stop.in_solve = true;
    stop.solve_started();
    ceres::Solve(sopts, &problem, &summary);
    stop.in_solve = false;
    (void)stop.check(LocalBaPoll::kSolve);  // Ceres' post-processing is a stretch too
  };
  solve();
  stop.first_solve = false;
  rep.initial_cost = stop.initial_cost;
  const auto t_tail = std::chrono::steady_clock::now();  // the work after the solves, timed
  std::chrono::steady_clock::duration second_solve{};

  // 4. Outliers out, solve again (`resolve`; without it they are only classified, for the
  //    culling). Not after a pre-empted solve: unconverged residuals would make inliers look
  //    like outliers; the progress made is written back as it is. All blocks are checked
  //    before any is removed, so that an abort in between leaves no partial classification.
  auto& point_obs = ws.point_obs;  // inliers, outliers
  auto& outliers = ws.outliers;
  // (Past the deadline a started classification is finished, as the deadline is only
  // checked between solves; an abort request ends it.)
  const bool classify = !stop.stop();
  until_poll = kClassifyPollEvery;
  for (const Observation& o : residuals) {
    if (!classify) break;
    if (--until_poll <= 0) {
      until_poll = kClassifyPollEvery;
      (void)stop.check(LocalBaPoll::kClassify);
    }
    if (stop.aborted) break;
    double cost = 0.0;
    const double chi2 = o.depth ? opts_.depth_outlier_chi2 : opts_.outlier_chi2;
    const bool ok = problem.EvaluateResidualBlock(o.id, false, &cost, nullptr, nullptr);
    if (!ok && abort_.load(std::memory_order_relaxed)) {  // the cost function saw the request
      (void)stop.check(LocalBaPoll::kClassify);
      break;
    }
    if (!ok || 2.0 * cost * o.sigma_scale * o.sigma_scale > chi2) {
      outliers.push_back(o.id);
      if (!o.depth) ++point_obs[o.p].second;
    } else if (!o.depth) {
      ++point_obs[o.p].first;
    }
  }
  if (stop.aborted || !classify) {
    point_obs.clear();
    outliers.clear();
  }
  rep.outliers = static_cast<int>(outliers.size());
  until_poll = kRemovePollEvery;
  // Without a second solve they stay in the problem: removing them would only cost time.
  for (std::size_t i = 0; resolve && i < outliers.size(); ++i) {
    if (--until_poll <= 0) {
      until_poll = kRemovePollEvery;
      (void)stop.check(LocalBaPoll::kClassify);
      if (stop.aborted) break;
    }
    problem.RemoveResidualBlock(outliers[i]);
  }
  if (resolve && rep.outliers > 0 && problem.NumResidualBlocks() > 0 &&
      !stop.check(LocalBaPoll::kSolve)) {
    // Most of a second solve is Ceres' set-up and first evaluation, which its time limit
    // does not cut short: one is not started in less time than one recently took (the
    // largest recent figure, decaying); the outliers are removed all the same.
    if (budgeted && remaining_s() * kMsPerS < resolve_ms_) {
      rep.resolve_skipped = true;
      resolve_ms_ *= kTailReserveDecay;
    } else {
      if (budgeted) sopts.max_solver_time_in_seconds = remaining_s();
      const auto t_solve = std::chrono::steady_clock::now();
      solve();
      second_solve = std::chrono::steady_clock::now() - t_solve;
      rep.resolved = true;
      if (budgeted) {
        resolve_ms_ = std::max(std::chrono::duration<double, std::milli>(second_solve).count(),
                               kTailReserveDecay * resolve_ms_);
      }
    }
  }
  rep.final_cost = stop.cost_known ? stop.cost : 0.0;

  // 5. Write back, under the lock again. The builder may have inserted keyframes, points and
  //    observations meanwhile and moved points it re-observed; culling of this thread does
  //    not run between. A keyframe or point freed (or its slot reused: generation) is not
  //    written; a point the builder moved keeps the builder's position (newer evidence), and
  //    a point that gained observations is not culled (they were not judged). A keyframe
  //    another writer moved meanwhile (the loop thread: a loop correction, a segment merge,
  //    the full BA after them) keeps that pose: this run's result is in the frame before.
  const auto t_wait = std::chrono::steady_clock::now();
  lock.lock();
  rep.lock_wait_ms +=
      std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t_wait).count();
  for (const auto& [id, b] : poses) {
    if (b.fixed || !problem.HasParameterBlock(b.q.data())) continue;
    SE3d T_w_c_now;
    if (map_.keyframe_generation(id) != b.generation || !map_.keyframe_pose(id, T_w_c_now) ||
        T_w_c_now.matrix() != b.T_w_c_read.matrix()) {
      ++rep.stale_writes;
      continue;
    }
    SE3d T_c_w = SE3d::Identity();
    T_c_w.linear() =
        Eigen::Quaterniond(b.q[3], b.q[0], b.q[1], b.q[2]).normalized().toRotationMatrix();
    T_c_w.translation() = Eigen::Vector3d(b.t[0], b.t[1], b.t[2]);
    map_.set_keyframe_pose(id, T_c_w.inverse());
    // The optimized depth scale is folded into the keyframe's local depth.
    if (depth_mode_ == DepthEdgeMode::kScaled && b.depth_scale > 0.0 && b.depth_scale != 1.0) {
      const auto nk = static_cast<std::uint32_t>(map_.keyframe_keypoints(id).size());
      for (std::uint32_t k = 0; k < nk; ++k) {
        const float d = map_.keyframe_depth(id, k);
        if (d > 0.0F) {
          map_.set_keyframe_depth(id, k, d * static_cast<float>(b.depth_scale),
                                  map_.keyframe_depth_confidence(id, k));
        }
      }
    }
  }
  const bool classified = !stop.stop() || !point_obs.empty();
  for (const auto& [p, pt] : points) {
    const std::array<double, 3>& X = pt.X;
    map::PointView now;
    if (!map_.read_point(p, now) || now.generation != pt.generation) {
      ++rep.stale_writes;  // freed, or its slot reused, meanwhile
      continue;
    }
    const bool moved = now.p_w != pt.p_w_read;
    if (!classified) {
      if (moved) {
        ++rep.stale_writes;
      } else {
        map_.set_point_position(p, Eigen::Vector3d(X[0], X[1], X[2]));
      }
      continue;
    }
    const auto c = point_obs[p];
    if (cull_points && c.first < opts_.min_inlier_observations && c.second > 0) {
      if (map_.point_num_observations(p) != pt.observations) {
        ++rep.stale_writes;
        continue;
      }
      map_.set_point_bad(p);
      ++rep.culled_points;
      continue;
    }
    if (c.first > 0) {
      if (moved) {
        ++rep.stale_writes;
      } else {
        map_.set_point_position(p, Eigen::Vector3d(X[0], X[1], X[2]));
      }
    }
  }
  (void)stop.mark();  // the write-back is part of the latency an abort can see
  if (budgeted) {
    // What a run needs after its solves (outlier classification, the second solve's set-up,
    // the write-back): the largest recent figure, decaying, is held back from the solves.
    const double tail_ms = std::chrono::duration<double, std::milli>(
                               std::chrono::steady_clock::now() - t_tail - second_solve)
                               .count();
    tail_reserve_ms_ = std::max(tail_ms, kTailReserveDecay * tail_reserve_ms_);
  }
  rep.ran = true;
  rep.max_poll_gap_ms = stop.max_gap_ms;
  rep.aborted = stop.aborted;
  rep.iterations = iterations_.load(std::memory_order_relaxed);
  rep.timed_out = stop.timed_out;
  rep.ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
  return rep;
}

}  // namespace mer::backend
