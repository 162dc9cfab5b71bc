// The steps of one local bundle adjustment run (LocalBundleAdjuster::optimize, local_ba.cpp):
// the window read from the map, the Ceres problem, the solves, the outliers and the
// write-back. The contract and threading are in local_ba.h.
#include <algorithm>
#include <array>
#include <cmath>
#include <mutex>

#include <Eigen/Geometry>
#include <ceres/ceres.h>

#include "backend/local_ba.h"
#include "backend/local_ba_run.h"
#include "platform/clock.h"

namespace mer::backend {
namespace {

constexpr double kMsPerS = 1000.0;
constexpr double kNsPerMs = 1e6;
constexpr std::size_t kMaxDenseSchurKeyframes = 64;  // larger windows: sparse Schur
constexpr double kMinDepth = 1e-6;  // camera z below which an observation is not evaluable
/// Per run, the time held back from the solves for the work after them decays by this factor
/// towards the latest measurement (it follows a shrinking window within a few runs).
constexpr double kTailReserveDecay = 0.8;

double ns_to_ms(std::int64_t ns) {
  return static_cast<double>(ns) * local_ba_detail::kNsToMs;
}

}  // namespace

bool LocalBundleAdjuster::load_pose(map::KeyframeId id, bool fixed) {
  auto& poses = ws_->poses;
  SE3d T_w_c;
  if (!map_.keyframe_pose(id, T_w_c)) return false;
  const SE3d T_c_w = T_w_c.inverse();
  local_ba_detail::PoseBlock b;
  const Eigen::Quaterniond q(T_c_w.linear());
  b.q = {q.x(), q.y(), q.z(), q.w()};
  b.t = {T_c_w.translation().x(), T_c_w.translation().y(), T_c_w.translation().z()};
  b.fixed = fixed;
  b.generation = map_.keyframe_generation(id);
  b.T_w_c_read = T_w_c;
  if (poses.size() == poses.capacity() || !ws_->pose_index.emplace(id, poses.size()).second) {
    return false;
  }
  poses.emplace_back(id, b);
  return true;
}

bool LocalBundleAdjuster::load_window(Run& run, const std::vector<map::KeyframeId>& window) {
  Workspace& ws = *ws_;
  local_ba_detail::StopCallback& stop = run.stop;
  LocalBaReport& rep = run.rep;
  // Parameter blocks live in arrays, in insertion order: Ceres orders a group of the given
  // elimination ordering by address, which must not depend on the heap for lockstep runs to
  // be repeatable. The capacities are reserved: the blocks' addresses must not move.
  auto& poses = ws.poses;
  auto& pose_index = ws.pose_index;
  poses.reserve(window.size() + static_cast<std::size_t>(std::max(0, opts_.max_fixed_keyframes)));
  for (const map::KeyframeId id : window) (void)load_pose(id, false);
  if (poses.size() < 2) return false;

  // 2. Points seen by the window, and the keyframes outside it that see them.
  auto& points = ws.points;
  auto& point_index = ws.point_index;
  std::size_t max_points = 0;
  for (const map::KeyframeId id : window) max_points += map_.keyframe_keypoints(id).size();
  points.reserve(max_points);
  auto& outside = ws.outside;  // keyframe -> shared points
  auto& obs = ws.obs;
  for (const map::KeyframeId id : window) {
    if (stop.check(LocalBaPoll::kLoad)) break;
    const auto n = static_cast<std::uint32_t>(map_.keyframe_keypoints(id).size());
    for (std::uint32_t k = 0; k < n; ++k) {
      const map::PointId p = map_.keyframe_point(id, k);
      if (p == map::kNoId || point_index.count(p) != 0) continue;
      map::PointView pv;
      if (!map_.read_point(p, pv)) continue;
      point_index.emplace(p, points.size());
      points.emplace_back(p, local_ba_detail::PointBlock{{pv.p_w.x(), pv.p_w.y(), pv.p_w.z()},
                                                         pv.p_w,
                                                         pv.generation,
                                                         map_.point_num_observations(p)});
      const std::size_t no = map_.point_observations(p, obs);
      run.max_blocks += no;
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
  return true;
}

void LocalBundleAdjuster::build_problem(Run& run, const geometry::Pinhole& K) {
  Workspace& ws = *ws_;
  local_ba_detail::StopCallback& stop = run.stop;
  LocalBaReport& rep = run.rep;
  auto& poses = ws.poses;
  auto& pose_index = ws.pose_index;
  auto& obs = ws.obs;
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
  reprojection_costs.reset(run.max_blocks);
  depth_costs.reset(use_depth ? run.max_blocks : 0);
  ceres::HuberLoss& huber = ws.huber;
  ceres::Problem::Options popts;
  popts.cost_function_ownership = ceres::DO_NOT_TAKE_OWNERSHIP;
  popts.manifold_ownership = ceres::DO_NOT_TAKE_OWNERSHIP;
  popts.loss_function_ownership = ceres::DO_NOT_TAKE_OWNERSHIP;
  popts.enable_fast_removal = false;
  popts.evaluation_callback = &stop;
  ceres::Problem& problem = ws.problem.emplace(popts);
  auto& residuals = ws.residuals;
  residuals.reserve(run.max_blocks * (use_depth ? 2 : 1));
  int until_poll = kBuildPollEvery;
  for (auto& [p, pt] : ws.points) {
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
      local_ba_detail::PoseBlock& b = poses[it->second].second;
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
  // Aborted (or out of time) while building: nothing is optimized (the caller returns).
  if (stop.stop()) return;
  for (auto& [id, b] : poses) {
    if (!problem.HasParameterBlock(b.q.data())) continue;
    problem.SetManifold(b.q.data(), &ws.quat_manifold);
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
  rep.points = static_cast<int>(ws.points.size());
  rep.observations = static_cast<int>(residuals.size()) - rep.depth_edges;
}

LocalBaReport LocalBundleAdjuster::stopped_early(Run& run) const {
  LocalBaReport& rep = run.rep;
  (void)run.stop.mark();
  rep.ran = true;
  rep.max_poll_gap_ms = run.stop.max_gap_ms;
  rep.aborted = run.stop.aborted;
  rep.timed_out = run.stop.timed_out;
  rep.ms = platform::elapsed_ms(run.t0_ns);
  return rep;
}

double LocalBundleAdjuster::remaining_s(const Run& run) const {
  return std::max(0.0, opts_.max_time_ms - platform::elapsed_ms(run.t0_ns)) / kMsPerS;
}

void LocalBundleAdjuster::solve(Run& run) {
  run.stop.in_solve = true;
  run.stop.solve_started();
  ceres::Solve(run.solver, &*ws_->problem, &run.summary);
  run.stop.in_solve = false;
  (void)run.stop.check(LocalBaPoll::kSolve);  // Ceres' post-processing is a stretch too
}

bool LocalBundleAdjuster::first_solve(Run& run, int max_iterations, std::size_t window_keyframes) {
  Workspace& ws = *ws_;
  ceres::Problem& problem = *ws.problem;
  ceres::Solver::Options& sopts = run.solver;
  // A local window's reduced camera system is small and dense; a full graph's is large and
  // sparse (each keyframe shares points with a few others only).
  sopts.linear_solver_type =
      window_keyframes <= kMaxDenseSchurKeyframes ? ceres::DENSE_SCHUR : ceres::SPARSE_SCHUR;
  // Eigen's sparse Cholesky for the large ones: SuiteSparse's runs OpenMP regions (a thread
  // pool of its own) on the back-end thread, which also runs the full BA after a loop.
  if (ceres::IsSparseLinearAlgebraLibraryTypeAvailable(ceres::EIGEN_SPARSE)) {
    sopts.sparse_linear_algebra_library_type = ceres::EIGEN_SPARSE;
  }
  sopts.max_num_iterations = max_iterations;
  sopts.num_threads = 1;
  sopts.logging_type = ceres::SILENT;
  sopts.callbacks.push_back(&run.stop);
  // The Schur elimination ordering, given: points first, then the keyframe blocks. Ceres
  // would otherwise find it itself (a graph search over all blocks in its preprocessing).
  const std::shared_ptr<ceres::ParameterBlockOrdering>& ordering = ws.ordering;
  for (auto& [p, pt] : ws.points) {
    if (problem.HasParameterBlock(pt.X.data())) ordering->AddElementToGroup(pt.X.data(), 0);
  }
  for (auto& [id, b] : ws.poses) {
    if (!problem.HasParameterBlock(b.q.data())) continue;
    ordering->AddElementToGroup(b.q.data(), 1);
    ordering->AddElementToGroup(b.t.data(), 1);
    if (problem.HasParameterBlock(&b.depth_scale)) {
      ordering->AddElementToGroup(&b.depth_scale, 1);
    }
  }
  sopts.linear_solver_ordering = ordering;
  if (run.stop.check(LocalBaPoll::kSolve)) return false;
  if (run.budgeted) sopts.max_solver_time_in_seconds = remaining_s(run);
  run.stop.set_solve_deadline(
      run.t0_ns + run.budget_ns -
      static_cast<std::int64_t>(std::min(tail_reserve_ms_, opts_.max_time_ms) * kNsPerMs));
  solve(run);
  run.stop.first_solve = false;
  run.rep.initial_cost = run.stop.initial_cost;
  run.tail_t_ns = platform::monotonic_now_ns();  // the work after the solves, timed
  return true;
}

void LocalBundleAdjuster::remove_outliers(Run& run, bool resolve) {
  Workspace& ws = *ws_;
  ceres::Problem& problem = *ws.problem;
  local_ba_detail::StopCallback& stop = run.stop;
  LocalBaReport& rep = run.rep;
  // 4. Outliers out, solve again (`resolve`; without it they are only classified, for the
  //    culling). Not after a pre-empted solve: unconverged residuals would make inliers look
  //    like outliers; the progress made is written back as it is. All blocks are checked
  //    before any is removed, so that an abort in between leaves no partial classification.
  auto& point_obs = ws.point_obs;  // inliers, outliers
  auto& outliers = ws.outliers;
  // (Past the deadline a started classification is finished, as the deadline is only
  // checked between solves; an abort request ends it.)
  const bool classify = !stop.stop();
  int until_poll = kClassifyPollEvery;
  for (const local_ba_detail::Observation& o : ws.residuals) {
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
    if (run.budgeted && remaining_s(run) * kMsPerS < resolve_ms_) {
      rep.resolve_skipped = true;
      resolve_ms_ *= kTailReserveDecay;
    } else {
      if (run.budgeted) run.solver.max_solver_time_in_seconds = remaining_s(run);
      const std::int64_t t_solve = platform::monotonic_now_ns();
      solve(run);
      run.second_solve_ns = platform::monotonic_now_ns() - t_solve;
      rep.resolved = true;
      if (run.budgeted) {
        resolve_ms_ = std::max(ns_to_ms(run.second_solve_ns), kTailReserveDecay * resolve_ms_);
      }
    }
  }
  rep.final_cost = stop.cost_known ? stop.cost : 0.0;
}

void LocalBundleAdjuster::write_back(Run& run, bool cull_points) {
  Workspace& ws = *ws_;
  ceres::Problem& problem = *ws.problem;
  LocalBaReport& rep = run.rep;
  // 5. Write back, under the lock again. The builder may have inserted keyframes, points and
  //    observations meanwhile and moved points it re-observed; culling of this thread does
  //    not run between. A keyframe or point freed (or its slot reused: generation) is not
  //    written; a point the builder moved keeps the builder's position (newer evidence), and
  //    a point that gained observations is not culled (they were not judged). A keyframe
  //    another writer moved meanwhile (the loop thread: a loop correction, a segment merge,
  //    the full BA after them) keeps that pose: this run's result is in the frame before.
  const std::int64_t t_wait = platform::monotonic_now_ns();
  run.lock.lock();
  rep.lock_wait_ms += platform::elapsed_ms(t_wait);
  for (const auto& [id, b] : ws.poses) {
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
  auto& point_obs = ws.point_obs;
  const bool classified = !run.stop.stop() || !point_obs.empty();
  for (const auto& [p, pt] : ws.points) {
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
  (void)run.stop.mark();  // the write-back is part of the latency an abort can see
  if (run.budgeted) {
    // What a run needs after its solves (outlier classification, the second solve's set-up,
    // the write-back): the largest recent figure, decaying, is held back from the solves.
    const double tail_ms =
        ns_to_ms(platform::monotonic_now_ns() - run.tail_t_ns - run.second_solve_ns);
    tail_reserve_ms_ = std::max(tail_ms, kTailReserveDecay * tail_reserve_ms_);
  }
  rep.ran = true;
  rep.max_poll_gap_ms = run.stop.max_gap_ms;
  rep.aborted = run.stop.aborted;
  rep.iterations = iterations_.load(std::memory_order_relaxed);
  rep.timed_out = run.stop.timed_out;
  rep.ms = platform::elapsed_ms(run.t0_ns);
}

}  // namespace mer::backend
