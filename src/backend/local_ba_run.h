#pragma once
/// @file local_ba_run.h
/// Internal to the local bundle adjustment (local_ba.cpp, local_ba_steps.cpp): the abort and
/// deadline polling, the parameter blocks and cost storage a run builds, and the state its
/// steps share. Not part of the back end's interface.

#include <algorithm>
#include <array>
#include <atomic>
#include <cstdint>
#include <functional>
#include <memory>
#include <mutex>
#include <optional>
#include <unordered_map>
#include <utility>
#include <vector>

#include <ceres/ceres.h>

#include "backend/ba_residuals.h"
#include "backend/local_ba.h"
#include "platform/clock.h"

namespace mer::backend {
namespace local_ba_detail {

inline constexpr std::size_t kMaxObservationsRead = 64;  // observations read per point
inline constexpr double kNsToMs = 1e-6;

/// Polls the abort request and the run's deadline: at the window loading and problem
/// building steps (check), as the solver's iteration callback (between iterations) and as its
/// evaluation callback (an evaluation starts; the cost functions poll the request inside it).
/// Times the stretches between polls (max_gap_ms).
class StopCallback final : public ceres::IterationCallback, public ceres::EvaluationCallback {
 public:
  /// Times are platform::monotonic_now_ns() readings.
  StopCallback(const std::atomic<bool>& abort, std::atomic<int>& iterations, std::int64_t t0_ns,
               std::int64_t deadline_ns, bool use_deadline,
               const std::function<void(LocalBaPoll)>& observer)
      : abort_(abort),
        iterations_(iterations),
        last_poll_(t0_ns),
        deadline_(deadline_ns),
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
    const std::int64_t now = last_poll_;  // check() just marked it
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
  void set_solve_deadline(std::int64_t t_ns) { solve_deadline_ = t_ns; }
  /// Marks the start of a solve (its first iteration is timed from here).
  void solve_started() { iteration_t_ = platform::monotonic_now_ns(); }
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
    const std::int64_t now = mark();
    if (!aborted && abort_.load(std::memory_order_relaxed)) aborted = true;
    if (!timed_out && use_deadline_ && now >= deadline_) timed_out = true;
    return stop();
  }
  /// Times the stretch since the previous poll (max_gap_ms); an evaluation counts as polled.
  std::int64_t mark() {
    const std::int64_t now = platform::monotonic_now_ns();
    if (!in_evaluation_) {
      max_gap_ms = std::max(max_gap_ms, static_cast<double>(now - last_poll_) * kNsToMs);
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
  std::int64_t last_poll_;
  std::int64_t deadline_;
  std::int64_t solve_deadline_ = deadline_;
  std::int64_t iteration_t_ = 0;        // the last iteration ended (or began)
  std::int64_t longest_iteration_ = 0;  // of this run, ns
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

}  // namespace local_ba_detail

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
  std::vector<std::pair<map::KeyframeId, local_ba_detail::PoseBlock>> poses;
  std::unordered_map<map::KeyframeId, std::size_t> pose_index;
  std::vector<std::pair<map::PointId, local_ba_detail::PointBlock>> points;
  std::unordered_map<map::PointId, std::size_t> point_index;
  std::unordered_map<map::KeyframeId, int> outside;  // keyframe -> shared points
  std::vector<std::pair<map::KeyframeId, int>> fixed_list;
  std::vector<std::pair<map::KeyframeId, std::uint32_t>> obs =
      std::vector<std::pair<map::KeyframeId, std::uint32_t>>(local_ba_detail::kMaxObservationsRead);
  // The problem and what it refers to.
  local_ba_detail::CostArena<ReprojectionCost> reprojection_costs;
  local_ba_detail::CostArena<DepthCost> depth_costs;
  RotationManifold quat_manifold;
  ceres::HuberLoss huber;
  // For a keypoint weighted by anchored_sigma_scale: its residual is divided by the scaled
  // sigma, so a kernel this much narrower bends at the same error in pixels as `huber`.
  ceres::HuberLoss huber_anchored;
  std::optional<ceres::Problem> problem;
  std::shared_ptr<ceres::ParameterBlockOrdering> ordering =
      std::make_shared<ceres::ParameterBlockOrdering>();
  std::vector<local_ba_detail::Observation> residuals;
  // Outlier classification.
  std::unordered_map<map::PointId, std::pair<int, int>> point_obs;  // inliers, outliers
  std::vector<ceres::ResidualBlockId> outliers;
};

/// One run of optimize(): what its steps share (local_ba.cpp, local_ba_steps.cpp).
struct LocalBundleAdjuster::Run {
  Run(const std::atomic<bool>& abort, std::atomic<int>& iterations, std::int64_t start_ns,
      std::int64_t run_budget_ns, bool use_budget, const std::function<void(LocalBaPoll)>& observer,
      std::unique_lock<platform::PiMutex>& writer_lock)
      : t0_ns(start_ns),
        budget_ns(run_budget_ns),
        budgeted(use_budget),
        lock(writer_lock),
        stop(abort, iterations, start_ns, start_ns + run_budget_ns, use_budget, observer) {}

  std::int64_t t0_ns;      // the run started (begin_run)
  std::int64_t budget_ns;  // its wall-time budget (max_time_ms)
  bool budgeted;           // the budget applies (not in lockstep, not the full BA)
  std::unique_lock<platform::PiMutex>& lock;  // the map's writer lock
  local_ba_detail::StopCallback stop;
  LocalBaReport rep;
  std::size_t max_blocks = 0;  // upper bound of the residual blocks (cost functions' storage)
  ceres::Solver::Options solver;
  ceres::Solver::Summary summary;
  std::int64_t tail_t_ns = 0;        // the solves ended: the work after them is timed
  std::int64_t second_solve_ns = 0;  // of which the second solve
};

}  // namespace mer::backend
