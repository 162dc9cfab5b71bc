// Loop correction (LoopCloser, loop_closer.h): a merge of two map segments, the pose graph of
// the loop's segment solved with the loop's edges, the correction applied to keyframes and
// points, and the loop's points fused.
#include <algorithm>
#include <array>
#include <cmath>
#include <vector>

#include <ceres/ceres.h>

#include "loop/descriptor_match.h"
#include "loop/loop_closer.h"
#include "platform/log_ring.h"

namespace mer::loop {
namespace {

using geometry::Sim3d;

/// Relative similarity error of a pose-graph edge (i, j): parameters are S_w_i and S_w_j as
/// (unit quaternion x y z w, translation, log scale); the measurement is S_i_j. The residual
/// is (2 vec(q_e), t_e, log s_e) of E = S_i_j_meas^-1 * S_w_i^-1 * S_w_j (identity when the
/// edge holds), with unit information, as in the usual essential-graph formulation.
struct Sim3EdgeCost {
  explicit Sim3EdgeCost(const Sim3d& S_i_j) {
    const Sim3d inv = S_i_j.inverse();
    q_inv = Eigen::Quaterniond(inv.R);
    t_inv = inv.t;
    log_s_inv = std::log(inv.s);
  }
  template <class T>
  bool operator()(const T* qi, const T* ti, const T* li, const T* qj, const T* tj, const T* lj,
                  T* res) const {
    const Eigen::Map<const Eigen::Quaternion<T>> Qi(qi);
    const Eigen::Map<const Eigen::Quaternion<T>> Qj(qj);
    const Eigen::Map<const Eigen::Matrix<T, 3, 1>> Ti(ti);
    const Eigen::Map<const Eigen::Matrix<T, 3, 1>> Tj(tj);
    // P = S_w_i^-1 * S_w_j.
    const Eigen::Quaternion<T> qi_inv = Qi.conjugate();
    const Eigen::Quaternion<T> q_p = qi_inv * Qj;
    const Eigen::Matrix<T, 3, 1> t_p = (qi_inv * (Tj - Ti)) * exp(-li[0]);
    const T log_s_p = lj[0] - li[0];
    // E = M^-1 * P.
    const Eigen::Quaternion<T> q_m = q_inv.cast<T>();
    Eigen::Quaternion<T> q_e = q_m * q_p;
    const Eigen::Matrix<T, 3, 1> t_e = (q_m * t_p) * T(std::exp(log_s_inv)) + t_inv.cast<T>();
    if (q_e.w() < T(0)) q_e.coeffs() = -q_e.coeffs();
    res[0] = T(2) * q_e.x();
    res[1] = T(2) * q_e.y();
    res[2] = T(2) * q_e.z();
    res[3] = t_e.x();
    res[4] = t_e.y();
    res[5] = t_e.z();
    res[6] = log_s_p + T(log_s_inv);
    return true;
  }
  Eigen::Quaterniond q_inv;
  Eigen::Vector3d t_inv;
  double log_s_inv = 0.0;
};

struct GraphNode {
  map::KeyframeId id = map::kNoId;
  std::uint64_t serial = 0;
  Sim3d sim_old;              // S_w_k before the correction
  std::array<double, 4> q{};  // x y z w of S_w_k
  std::array<double, 3> t{};
  double log_s = 0.0;
  Sim3d value() const {
    Sim3d S;
    S.R = Eigen::Quaterniond(q[3], q[0], q[1], q[2]).normalized().toRotationMatrix();
    S.t = {t[0], t[1], t[2]};
    S.s = std::exp(log_s);
    return S;
  }
  void set(const Sim3d& S) {
    const Eigen::Quaterniond qq(S.R);
    q = {qq.x(), qq.y(), qq.z(), qq.w()};
    t = {S.t.x(), S.t.y(), S.t.z()};
    log_s = std::log(S.s);
  }
};

}  // namespace

/// The pose graph of one loop correction: the loop segment's keyframes (nodes, in creation
/// order), the window moved with the new keyframe and the candidate's side of the loop.
struct LoopCloser::PoseGraph {
  std::vector<GraphNode> nodes;
  std::vector<int> node_of;      // keyframe id -> node, -1: not in the graph
  int i_new = -1;                // the new keyframe's node
  int i_cand = -1;               // the candidate's node (held fixed: the gauge)
  std::vector<int> window;       // nodes moved rigidly with the new keyframe's correction
  std::vector<int> loop_side;    // the candidate and its neighbours, tied to the window
  std::vector<Sim3d> sim_start;  // S_w_k the solve starts from
};

void LoopCloser::merge_segments(map::KeyframeId kf, map::KeyframeId cand, Sim3d& S_cand_new,
                                LoopReport& rep) {
  const std::uint16_t seg_new = map_.keyframe_segment(kf);
  const std::uint16_t seg_cand = map_.keyframe_segment(cand);
  SE3d T_w_new;
  SE3d T_w_cand;
  if (seg_new == seg_cand || !map_.keyframe_pose(kf, T_w_new) ||
      !map_.keyframe_pose(cand, T_w_cand)) {
    return;
  }
  // The new keyframe's world -> the candidate's: through the two cameras the match relates.
  const Sim3d S_wcand_wnew =
      Sim3d::from_se3(T_w_cand) * S_cand_new * Sim3d::from_se3(T_w_new).inverse();
  // The older segment (the smaller id) keeps its frame; the newer one moves into it.
  const bool new_moves = seg_new > seg_cand;
  const std::uint16_t from = new_moves ? seg_new : seg_cand;
  const std::uint16_t into = new_moves ? seg_cand : seg_new;
  const Sim3d S_into_from = new_moves ? S_wcand_wnew : S_wcand_wnew.inverse();
  const std::uint32_t moved = map_.merge_segment(from, into, S_into_from);
  if (moved == 0) return;
  // The moved side's camera coordinates scaled with its map: the new keyframe's by s (x_old =
  // s R x + t = R (s x) + t) or the candidate's by 1 / s (x_old / s = R x + t / s).
  if (!new_moves) S_cand_new.t /= S_cand_new.s;
  S_cand_new.s = 1.0;
  rep.merged_from = from;
  rep.merged_into = into;
  rep.merge_keyframes = static_cast<int>(moved);
  rep.merge_similarity = S_into_from;
  MER_LOG_INFO("map segment %u merged into segment %u (%u keyframes, scale %.4f)", unsigned{from},
               unsigned{into}, moved, S_into_from.s);
}

int LoopCloser::correct(map::KeyframeId kf, map::KeyframeId cand, const Sim3d& S_cand_new,
                        const geometry::Pinhole& K, LoopReport& rep) {
  PoseGraph g;
  if (!load_pose_graph(kf, cand, S_cand_new, g)) return 0;
  solve_pose_graph(g);
  return apply_correction(g, cand, K, rep);
}

bool LoopCloser::load_pose_graph(map::KeyframeId kf, map::KeyframeId cand, const Sim3d& S_cand_new,
                                 PoseGraph& g) const {
  // Nodes: every live keyframe of the loop's segment, in creation order (another segment's
  // keyframes are in another frame: a correction of this one must not drag them).
  const std::uint16_t segment = map_.keyframe_segment(cand);
  std::vector<GraphNode>& nodes = g.nodes;
  std::vector<int>& node_of = g.node_of;
  node_of.assign(map_.num_keyframes(), -1);
  for (map::KeyframeId id = 0; id < map_.num_keyframes(); ++id) {
    SE3d T;
    if (!map_.keyframe_is_live(id) || map_.keyframe_segment(id) != segment ||
        !map_.keyframe_pose(id, T)) {
      continue;
    }
    GraphNode n;
    n.id = id;
    n.serial = map_.keyframe_serial(id);
    n.sim_old = Sim3d::from_se3(T);
    n.set(n.sim_old);
    nodes.push_back(n);
  }
  std::sort(nodes.begin(), nodes.end(),
            [](const GraphNode& a, const GraphNode& b) { return a.serial < b.serial; });
  for (std::size_t i = 0; i < nodes.size(); ++i) node_of[nodes[i].id] = static_cast<int>(i);
  g.i_new = node_of[kf];
  g.i_cand = node_of[cand];
  if (g.i_new < 0 || g.i_cand < 0) return false;
  const int i_new = g.i_new;
  const int i_cand = g.i_cand;

  // The correction at the new keyframe, and its neighbourhood moved rigidly with it.
  const Sim3d S_w_new_corr = nodes[static_cast<std::size_t>(i_cand)].sim_old * S_cand_new;
  const Sim3d C = S_w_new_corr * nodes[static_cast<std::size_t>(i_new)].sim_old.inverse();
  std::array<map::CovisibleKeyframe, kMaxCovisible> covis{};
  const std::size_t nc = map_.covisible_keyframes(kf, covis);

  // The window: the new keyframe and its recent neighbours (not the old ones it already
  // shares points with: those are the other side of the loop).
  const auto gap = static_cast<std::uint64_t>(opts_.min_keyframe_gap);
  auto recent = [&](int i) {
    return nodes[static_cast<std::size_t>(i)].serial + gap >
           nodes[static_cast<std::size_t>(i_new)].serial;
  };
  std::vector<int>& window = g.window;
  window.assign(1, i_new);
  for (std::size_t k = 0; k < nc; ++k) {
    const int i = node_of[covis[k].id];
    if (i >= 0 && i != i_cand && recent(i)) window.push_back(i);
  }
  std::vector<Sim3d>& S_init = g.sim_start;
  S_init.resize(nodes.size());
  for (std::size_t i = 0; i < nodes.size(); ++i) S_init[i] = nodes[i].sim_old;
  for (const int i : window)
    S_init[static_cast<std::size_t>(i)] = C * nodes[static_cast<std::size_t>(i)].sim_old;
  for (std::size_t i = 0; i < nodes.size(); ++i) nodes[i].set(S_init[i]);

  return true;
}

void LoopCloser::solve_pose_graph(PoseGraph& g) {
  std::vector<GraphNode>& nodes = g.nodes;
  const std::vector<int>& node_of = g.node_of;
  const std::vector<int>& window = g.window;
  const std::vector<Sim3d>& S_init = g.sim_start;
  const int i_cand = g.i_cand;
  std::array<map::CovisibleKeyframe, kMaxCovisible> covis{};
  const auto gap = static_cast<std::uint64_t>(opts_.min_keyframe_gap);
  auto long_gap = [&](int i, int j) {
    const std::uint64_t a = nodes[static_cast<std::size_t>(i)].serial;
    const std::uint64_t b = nodes[static_cast<std::size_t>(j)].serial;
    return (a > b ? a - b : b - a) >= gap;
  };
  // Edges.
  ceres::Problem::Options popts;
  ceres::Problem problem(popts);
  ceres::Manifold* quat = new ceres::EigenQuaternionManifold;  // owned by the problem
  bool quat_used = false;
  auto add_edge = [&](int i, int j, const Sim3d& S_i_j) {
    auto* cost =
        new ceres::AutoDiffCostFunction<Sim3EdgeCost, 7, 4, 3, 1, 4, 3, 1>(new Sim3EdgeCost(S_i_j));
    GraphNode& a = nodes[static_cast<std::size_t>(i)];
    GraphNode& b = nodes[static_cast<std::size_t>(j)];
    problem.AddResidualBlock(cost, nullptr, a.q.data(), a.t.data(), &a.log_s, b.q.data(),
                             b.t.data(), &b.log_s);
  };
  auto old_relative = [&](int i, int j) {
    return nodes[static_cast<std::size_t>(i)].sim_old.inverse() *
           nodes[static_cast<std::size_t>(j)].sim_old;
  };
  int edges = 0;
  for (std::size_t i = 0; i < nodes.size(); ++i) {
    if (i > 0) {
      add_edge(static_cast<int>(i - 1), static_cast<int>(i),
               old_relative(static_cast<int>(i - 1), static_cast<int>(i)));
      ++edges;
    }
    const std::size_t m = map_.covisible_keyframes(nodes[i].id, covis);
    for (std::size_t k = 0; k < m; ++k) {
      const int j = node_of[covis[k].id];
      // Each pair once (the older first), consecutive pairs already have their edge.
      // Pairs far apart in time are loop edges: the ones of earlier loops are added below,
      // others hold the drift this loop removes.
      if (j < 0 || static_cast<std::size_t>(j) >= i || static_cast<std::size_t>(j) + 1 == i ||
          covis[k].weight < static_cast<std::uint32_t>(opts_.min_edge_weight) ||
          long_gap(j, static_cast<int>(i))) {
        continue;
      }
      add_edge(j, static_cast<int>(i), old_relative(j, static_cast<int>(i)));
      ++edges;
    }
  }
  // Loop edges: the corrected neighbourhood of the new keyframe to the candidate's.
  std::vector<int>& loop_side = g.loop_side;
  loop_side.assign(1, i_cand);
  const std::size_t ncc =
      map_.covisible_keyframes(nodes[static_cast<std::size_t>(i_cand)].id, covis);
  for (std::size_t k = 0; k < ncc && loop_side.size() < kLoopNeighbours; ++k) {
    const int j = node_of[covis[k].id];
    if (j >= 0 && std::find(window.begin(), window.end(), j) == window.end())
      loop_side.push_back(j);
  }
  // Edges of the loops closed before (consistent since their correction).
  for (const LoopEdge& e : loop_edges_) {
    if (e.a >= node_of.size() || e.b >= node_of.size() ||
        map_.keyframe_generation(e.a) != e.gen_a || map_.keyframe_generation(e.b) != e.gen_b) {
      continue;
    }
    const int i = node_of[e.a];
    const int j = node_of[e.b];
    if (i < 0 || j < 0) continue;
    add_edge(i, j, old_relative(i, j));
    ++edges;
  }
  for (const int w : window) {
    for (const int l : loop_side) {
      add_edge(l, w,
               S_init[static_cast<std::size_t>(l)].inverse() * S_init[static_cast<std::size_t>(w)]);
      ++edges;
      const map::KeyframeId a = nodes[static_cast<std::size_t>(l)].id;
      const map::KeyframeId b = nodes[static_cast<std::size_t>(w)].id;
      if (loop_edges_.size() < loop_edges_.capacity()) {
        loop_edges_.push_back(
            LoopEdge{a, map_.keyframe_generation(a), b, map_.keyframe_generation(b)});
      }
    }
  }
  for (GraphNode& n : nodes) {
    if (problem.HasParameterBlock(n.q.data())) {
      problem.SetManifold(n.q.data(), quat);
      quat_used = true;
      if (metric_) problem.SetParameterBlockConstant(&n.log_s);
    }
  }
  GraphNode& anchor = nodes[static_cast<std::size_t>(i_cand)];
  problem.SetParameterBlockConstant(anchor.q.data());
  problem.SetParameterBlockConstant(anchor.t.data());
  problem.SetParameterBlockConstant(&anchor.log_s);
  if (!quat_used) delete quat;

  ceres::Solver::Options sopts;
  sopts.linear_solver_type = ceres::SPARSE_NORMAL_CHOLESKY;
  // Eigen's sparse Cholesky: SuiteSparse's runs OpenMP regions on this real-time thread.
  if (ceres::IsSparseLinearAlgebraLibraryTypeAvailable(ceres::EIGEN_SPARSE)) {
    sopts.sparse_linear_algebra_library_type = ceres::EIGEN_SPARSE;
  }
  sopts.max_num_iterations = opts_.pose_graph_iterations;
  sopts.num_threads = 1;
  sopts.logging_type = ceres::SILENT;
  ceres::Solver::Summary summary;
  ceres::Solve(sopts, &problem, &summary);
  MER_LOG_DEBUG("loop pose graph: %zu keyframes, %d edges, cost %.3g -> %.3g, %d iterations",
                nodes.size(), edges, summary.initial_cost, summary.final_cost,
                static_cast<int>(summary.iterations.size()));
}

int LoopCloser::apply_correction(PoseGraph& g, map::KeyframeId cand, const geometry::Pinhole& K,
                                 LoopReport& rep) {
  std::vector<GraphNode>& nodes = g.nodes;
  const std::vector<int>& node_of = g.node_of;
  const int i_new = g.i_new;
  // Apply: keyframe poses and depths, then every point with its reference keyframe.
  std::vector<Sim3d> D(nodes.size());
  for (std::size_t i = 0; i < nodes.size(); ++i) {
    const Sim3d S_new = nodes[i].value();
    D[i] = S_new * nodes[i].sim_old.inverse();
    double kf_scale = 1.0;
    SE3d T_unused;
    (void)map_.keyframe_pose(nodes[i].id, T_unused, &kf_scale);
    map_.set_keyframe_pose(nodes[i].id, S_new.rigid(), kf_scale);
    if (!metric_) {
      const std::uint32_t nk = map_.keyframe_num_keypoints(nodes[i].id);
      for (std::uint32_t kp = 0; kp < nk; ++kp) {
        const float d = map_.keyframe_depth(nodes[i].id, kp);
        if (d > 0.0F) {
          map_.set_keyframe_depth(nodes[i].id, kp, static_cast<float>(d * S_new.s),
                                  map_.keyframe_depth_confidence(nodes[i].id, kp));
        }
      }
    }
  }
  const map::PointId np = map_.num_points();
  map::PointView v;
  for (map::PointId p = 0; p < np; ++p) {
    if (!map_.read_point(p, v) || v.ref_keyframe >= node_of.size()) continue;
    const int r = node_of[v.ref_keyframe];
    if (r < 0) continue;
    map_.set_point_position(p, D[static_cast<std::size_t>(r)] * v.p_w);
  }
  // Merge the matched points (the loop keyframe's is kept: the old map is the reference).
  int merged = 0;
  for (std::size_t i = 0; i < matches_.size(); ++i) {
    if (!inlier_[i]) continue;
    if (map_.merge_points(matches_[i].p_old, matches_[i].p_new) >= 0) ++merged;
  }
  // Loop fusion: the old side's points projected into the corrected window keyframes.
  std::vector<map::KeyframeId> window_ids;
  std::vector<map::KeyframeId> old_ids;
  for (const int w : g.window) window_ids.push_back(nodes[static_cast<std::size_t>(w)].id);
  for (const int l : g.loop_side) old_ids.push_back(nodes[static_cast<std::size_t>(l)].id);
  merged += fuse_loop(window_ids, old_ids, K, rep);
  for (const int w : g.window) map_.update_covisibility(nodes[static_cast<std::size_t>(w)].id);
  map_.update_covisibility(cand);
  const Sim3d& D_new = D[static_cast<std::size_t>(i_new)];
  map_.publish_correction(map_.keyframe_segment(cand), D_new);
  rep.scale = D_new.s;
  rep.shift = (nodes[static_cast<std::size_t>(i_new)].value().t -
               nodes[static_cast<std::size_t>(i_new)].sim_old.t)
                  .norm();
  rep.keyframes = static_cast<int>(nodes.size());
  return merged;
}

int LoopCloser::fuse_loop(const std::vector<map::KeyframeId>& window,
                          const std::vector<map::KeyframeId>& old_kfs, const geometry::Pinhole& K,
                          LoopReport& rep) {
  std::vector<map::PointId> old_pts;
  for (const map::KeyframeId id : old_kfs) {
    const std::uint32_t nk = map_.keyframe_num_keypoints(id);
    for (std::uint32_t j = 0; j < nk; ++j) {
      const map::PointId q = map_.keyframe_point(id, j);
      if (q != map::kNoId && !map_.point_is_bad(q)) old_pts.push_back(q);
    }
  }
  std::sort(old_pts.begin(), old_pts.end());
  old_pts.erase(std::unique(old_pts.begin(), old_pts.end()), old_pts.end());
  int merged = 0;
  std::vector<int> best_dist;
  std::vector<map::PointId> best_pt;
  for (const map::KeyframeId w : window) {
    SE3d T_w_c;
    if (!map_.keyframe_is_live(w) || !map_.keyframe_pose(w, T_w_c)) continue;
    const SE3d T_c_w = T_w_c.inverse();
    const auto kps = map_.keyframe_keypoints(w);
    const auto descs = map_.keyframe_descriptors(w);
    const std::uint32_t nk = map_.keyframe_num_keypoints(w);
    best_dist.assign(nk, std::numeric_limits<int>::max());
    best_pt.assign(nk, map::kNoId);
    map::PointView pv;
    for (const map::PointId q : old_pts) {
      if (!map_.read_point(q, pv)) continue;
      const Eigen::Vector3d p_c = T_c_w * pv.p_w;
      if (p_c.z() <= 0.0) continue;
      const Eigen::Vector2d uv = K.project(p_c);
      int best = std::numeric_limits<int>::max();
      std::uint32_t best_k = nk;
      for (std::uint32_t k = 0; k < nk; ++k) {
        const features::Keypoint& kp = kps[k];
        const double e2 = (Eigen::Vector2d(kp.x, kp.y) - uv).squaredNorm();
        if (e2 > opts_.fuse_radius_px * opts_.fuse_radius_px * sigma2(kp)) continue;
        const int d = features::hamming(pv.descriptor, descs[k]);
        if (d < best) {
          best = d;
          best_k = k;
        }
      }
      if (best_k == nk || best > opts_.max_descriptor_distance || best >= best_dist[best_k]) {
        continue;
      }
      best_dist[best_k] = best;
      best_pt[best_k] = q;
    }
    for (std::uint32_t k = 0; k < nk; ++k) {
      const map::PointId q = best_pt[k];
      if (q == map::kNoId || map_.point_is_bad(q)) continue;
      const map::PointId p = map_.keyframe_point(w, k);
      if (p == q) continue;
      if (p == map::kNoId) {
        if (map_.add_observation(q, w, k)) {
          map_.update_point(q);
          ++rep.fused_observations;
        }
      } else if (!map_.point_is_bad(p) && map_.merge_points(q, p) >= 0) {
        ++merged;
      }
    }
  }
  return merged;
}

}  // namespace mer::loop
