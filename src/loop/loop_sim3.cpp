// The similarity of a loop (LoopCloser, loop_closer.h): the new keyframe's points matched to a
// candidate's, a RANSAC Sim(3) on them, its refit and reprojection refinement, and the guided
// matches it then finds.
#include <algorithm>
#include <cmath>
#include <limits>
#include <numeric>
#include <utility>

#include <ceres/ceres.h>

#include "core/median.h"
#include "geometry/random.h"
#include "loop/descriptor_match.h"
#include "loop/loop_closer.h"

namespace mer::loop {
namespace {

using geometry::Sim3d;

/// Refits of a loop similarity on its inliers before the inlier set is taken as settled.
constexpr int kRefitRounds = 3;
/// A point this close to a camera's plane (map units) stops a refinement step.
constexpr double kMinRefineDepth = 1e-6;

Sim3d fit_sim3(const std::vector<Eigen::Vector3d>& x_new, const std::vector<Eigen::Vector3d>& x_old,
               const std::vector<std::size_t>& idx, bool metric) {
  Eigen::Matrix3Xd src(3, static_cast<Eigen::Index>(idx.size()));
  Eigen::Matrix3Xd dst(3, static_cast<Eigen::Index>(idx.size()));
  for (std::size_t k = 0; k < idx.size(); ++k) {
    src.col(static_cast<Eigen::Index>(k)) = x_new[idx[k]];
    dst.col(static_cast<Eigen::Index>(k)) = x_old[idx[k]];
  }
  return geometry::umeyama_sim3(src, dst, !metric);
}

bool plausible_sim3(const Sim3d& S, double max_scale) {
  return std::isfinite(S.s) && S.s > 1.0 / max_scale && S.s < max_scale && S.R.allFinite() &&
         S.t.allFinite();
}

/// Reprojection error of one loop match under S_cand_new = (q, t, exp(log_s)): the new
/// keyframe's point moved into the old view that observed its match, and the old point moved
/// into the new keyframe, each against its keypoint in sigmas (4 residuals). The points stay
/// where the map has them: only the similarity is refined.
struct Sim3ReprojectionCost {
  Eigen::Vector3d x_new;  // the new keyframe's point, new camera frame
  Eigen::Vector3d x_old;  // the old point, candidate camera frame
  Eigen::Quaterniond q_view_cand;
  Eigen::Vector3d t_view_cand;
  Eigen::Vector2d kp_old;  // its keypoint in the old view
  Eigen::Vector2d kp_new;
  double inv_sigma_old = 1.0;
  double inv_sigma_new = 1.0;
  geometry::Pinhole K;

  template <class T>
  bool operator()(const T* q, const T* t, const T* log_s, T* res) const {
    const Eigen::Map<const Eigen::Quaternion<T>> Q(q);
    const Eigen::Map<const Eigen::Matrix<T, 3, 1>> Tr(t);
    const T s = exp(log_s[0]);
    const Eigen::Matrix<T, 3, 1> a = Q * x_new.cast<T>() * s + Tr;  // candidate frame
    const Eigen::Matrix<T, 3, 1> av = q_view_cand.cast<T>() * a + t_view_cand.cast<T>();
    const Eigen::Matrix<T, 3, 1> b = Q.conjugate() * (x_old.cast<T>() - Tr) / s;  // new frame
    if (!(av.z() > T(kMinRefineDepth)) || !(b.z() > T(kMinRefineDepth))) return false;
    res[0] = (T(K.fx) * av.x() / av.z() + T(K.cx) - T(kp_old.x())) * T(inv_sigma_old);
    res[1] = (T(K.fy) * av.y() / av.z() + T(K.cy) - T(kp_old.y())) * T(inv_sigma_old);
    res[2] = (T(K.fx) * b.x() / b.z() + T(K.cx) - T(kp_new.x())) * T(inv_sigma_new);
    res[3] = (T(K.fy) * b.y() / b.z() + T(K.cy) - T(kp_new.y())) * T(inv_sigma_new);
    return true;
  }
};

}  // namespace

int LoopCloser::match_points(map::KeyframeId kf, map::KeyframeId cand) {
  matches_.clear();
  old_views_.clear();
  const std::uint64_t serial = map_.keyframe_serial(kf);
  const auto gap = static_cast<std::uint64_t>(opts_.min_keyframe_gap);
  // The old side: the candidate and its old covisible neighbours; each point once.
  SE3d T_w_cand;
  if (!map_.keyframe_pose(cand, T_w_cand)) return 0;
  old_views_.push_back(OldView{cand, SE3d::Identity()});
  std::array<map::CovisibleKeyframe, kMaxCovisible> covis{};
  const std::size_t nc = map_.covisible_keyframes(cand, covis);
  for (std::size_t k = 0; k < nc && old_views_.size() < kLoopNeighbours; ++k) {
    SE3d T_w_v;
    if (map_.keyframe_serial(covis[k].id) + gap > serial ||
        !map_.keyframe_pose(covis[k].id, T_w_v)) {
      continue;
    }
    old_views_.push_back(OldView{covis[k].id, T_w_v.inverse() * T_w_cand});
  }
  struct OldPoint {
    std::uint32_t view = 0;
    std::uint32_t kp = 0;
    map::PointId p = map::kNoId;
    features::Descriptor desc{};  // of keypoint kp in that view
  };
  std::vector<OldPoint> old_pts;
  for (std::uint32_t v = 0; v < old_views_.size(); ++v) {
    const map::KeyframeId id = old_views_[v].kf;
    const auto descs = map_.keyframe_descriptors(id);
    const std::uint32_t n_old = map_.keyframe_num_keypoints(id);
    for (std::uint32_t j = 0; j < n_old; ++j) {
      const map::PointId q = map_.keyframe_point(id, j);
      if (q != map::kNoId && !map_.point_is_bad(q)) old_pts.push_back(OldPoint{v, j, q, descs[j]});
    }
  }
  // Each point once, from the first view that has it (the candidate's first).
  {
    std::vector<std::size_t> order(old_pts.size());
    std::iota(order.begin(), order.end(), std::size_t{0});
    std::stable_sort(order.begin(), order.end(),
                     [&](std::size_t a, std::size_t b) { return old_pts[a].p < old_pts[b].p; });
    std::vector<std::uint8_t> repeat(old_pts.size(), 0);
    for (std::size_t i = 1; i < order.size(); ++i) {
      if (old_pts[order[i]].p == old_pts[order[i - 1]].p) repeat[order[i]] = 1;
    }
    std::size_t w = 0;
    for (std::size_t i = 0; i < old_pts.size(); ++i) {
      if (!repeat[i]) old_pts[w++] = old_pts[i];
    }
    old_pts.resize(w);
  }
  const auto descs_new = map_.keyframe_descriptors(kf);
  const std::uint32_t n_new = map_.keyframe_num_keypoints(kf);
  // Best new keypoint per old point (one-to-one): distance, index in matches_.
  std::vector<std::pair<int, int>> taken(old_pts.size(), {std::numeric_limits<int>::max(), -1});
  for (std::uint32_t i = 0; i < n_new; ++i) {
    const map::PointId p = map_.keyframe_point(kf, i);
    if (p == map::kNoId || map_.point_is_bad(p)) continue;
    const NearestTwo nn = nearest_two(
        descs_new[i],
        old_pts.size(), [&](std::size_t k) -> const auto& { return old_pts[k].desc; });
    if (!nn.passes(opts_.max_descriptor_distance, opts_.ratio)) continue;
    const int best = nn.best;
    const std::size_t best_k = nn.index;
    if (old_pts[best_k].p == p) continue;  // already one point: nothing to close
    auto& [dist, idx] = taken[best_k];
    if (best >= dist) continue;
    if (idx >= 0) {
      matches_[static_cast<std::size_t>(idx)].p_new = map::kNoId;  // displaced
    } else {
      idx = static_cast<int>(matches_.size());
      matches_.emplace_back();
    }
    dist = best;
    matches_[static_cast<std::size_t>(idx)] =
        Match{i, old_pts[best_k].kp, p, old_pts[best_k].p, old_pts[best_k].view};
  }
  std::erase_if(matches_, [](const Match& m) { return m.p_new == map::kNoId; });
  return static_cast<int>(matches_.size());
}

bool LoopCloser::match_positions(map::KeyframeId kf, map::KeyframeId cand) {
  SE3d T_w_new;
  SE3d T_w_old;
  if (!map_.keyframe_pose(kf, T_w_new) || !map_.keyframe_pose(cand, T_w_old)) return false;
  const SE3d T_new_w = T_w_new.inverse();
  const SE3d T_old_w = T_w_old.inverse();
  x_new_.clear();
  x_old_.clear();
  std::erase_if(matches_, [&](const Match& m) {
    map::PointView a;
    map::PointView b;
    if (!map_.read_point(m.p_new, a) || !map_.read_point(m.p_old, b)) return true;
    const Eigen::Vector3d xa = T_new_w * a.p_w;
    const Eigen::Vector3d xb = T_old_w * b.p_w;
    if (xa.z() <= 0.0 || xb.z() <= 0.0) return true;
    x_new_.push_back(xa);
    x_old_.push_back(xb);
    return false;
  });
  return true;
}

int LoopCloser::count_sim3_inliers(map::KeyframeId kf, const Sim3d& S_cand_new,
                                   const geometry::Pinhole& K,
                                   std::vector<std::uint8_t>* mask) const {
  const auto kps_new = map_.keyframe_keypoints(kf);
  const Sim3d S_inv = S_cand_new.inverse();
  int count = 0;
  for (std::size_t i = 0; i < matches_.size(); ++i) {
    const Eigen::Vector3d a = S_cand_new * x_new_[i];  // in the old camera
    const Eigen::Vector3d b = S_inv * x_old_[i];       // in the new camera
    bool ok = a.z() > 0.0 && b.z() > 0.0;
    if (ok) {
      const OldView& view = old_views_[matches_[i].old_view];
      const features::Keypoint& ko = map_.keyframe_keypoints(view.kf)[matches_[i].kp_old];
      const features::Keypoint& kn = kps_new[matches_[i].kp_new];
      const Eigen::Vector3d av = view.T_view_cand * a;
      const double eo =
          av.z() <= 0.0 ? std::numeric_limits<double>::infinity()
                        : (K.project(av) - Eigen::Vector2d(ko.x, ko.y)).squaredNorm() / sigma2(ko);
      const double en = (K.project(b) - Eigen::Vector2d(kn.x, kn.y)).squaredNorm() / sigma2(kn);
      ok = eo < opts_.inlier_chi2 && en < opts_.inlier_chi2;
    }
    if (mask != nullptr) (*mask)[i] = ok ? 1 : 0;
    count += ok ? 1 : 0;
  }
  return count;
}

int LoopCloser::refit_sim3(map::KeyframeId kf, const geometry::Pinhole& K, Sim3d& S_cand_new) {
  const std::size_t n = matches_.size();
  inlier_.assign(n, 0);
  int best = count_sim3_inliers(kf, S_cand_new, K, &inlier_);
  for (int round = 0; round < kRefitRounds; ++round) {
    std::vector<std::size_t> idx;
    for (std::size_t i = 0; i < n; ++i) {
      if (inlier_[i]) idx.push_back(i);
    }
    if (idx.size() < 3) break;
    const Sim3d S = fit_sim3(x_new_, x_old_, idx, metric_);
    if (!plausible_sim3(S, max_scale_)) break;
    std::vector<std::uint8_t> mask(n, 0);
    const int c = count_sim3_inliers(kf, S, K, &mask);
    if (c < best) break;
    best = c;
    S_cand_new = S;
    const bool same = mask == inlier_;
    inlier_.swap(mask);
    if (same) break;
  }
  return best;  // inlier_ describes S_cand_new (a refit that lost inliers was not taken)
}

int LoopCloser::refine_sim3(map::KeyframeId kf, const geometry::Pinhole& K, int inliers,
                            Sim3d& S_cand_new) {
  if (opts_.refine_iterations <= 0 || inliers < 3) return inliers;
  const auto kps_new = map_.keyframe_keypoints(kf);
  Eigen::Quaterniond q(S_cand_new.R);
  std::array<double, 4> qv{q.x(), q.y(), q.z(), q.w()};
  std::array<double, 3> tv{S_cand_new.t.x(), S_cand_new.t.y(), S_cand_new.t.z()};
  double log_s = std::log(S_cand_new.s);
  ceres::Problem problem;
  ceres::HuberLoss* huber = new ceres::HuberLoss(std::sqrt(opts_.inlier_chi2));  // owned
  for (std::size_t i = 0; i < matches_.size(); ++i) {
    if (!inlier_[i]) continue;
    const Match& m = matches_[i];
    const OldView& view = old_views_[m.old_view];
    const features::Keypoint& ko = map_.keyframe_keypoints(view.kf)[m.kp_old];
    const features::Keypoint& kn = kps_new[m.kp_new];
    auto* c = new Sim3ReprojectionCost;
    c->x_new = x_new_[i];
    c->x_old = x_old_[i];
    c->q_view_cand = Eigen::Quaterniond(view.T_view_cand.linear());
    c->t_view_cand = view.T_view_cand.translation();
    c->kp_old = {ko.x, ko.y};
    c->kp_new = {kn.x, kn.y};
    c->inv_sigma_old = 1.0 / std::sqrt(static_cast<double>(sigma2(ko)));
    c->inv_sigma_new = 1.0 / std::sqrt(static_cast<double>(sigma2(kn)));
    c->K = K;
    problem.AddResidualBlock(new ceres::AutoDiffCostFunction<Sim3ReprojectionCost, 4, 4, 3, 1>(c),
                             huber, qv.data(), tv.data(), &log_s);
  }
  if (problem.NumResidualBlocks() < 3) return inliers;
  problem.SetManifold(qv.data(), new ceres::EigenQuaternionManifold);
  if (metric_) problem.SetParameterBlockConstant(&log_s);
  ceres::Solver::Options sopts;
  sopts.linear_solver_type = ceres::DENSE_QR;
  sopts.max_num_iterations = opts_.refine_iterations;
  sopts.num_threads = 1;
  sopts.logging_type = ceres::SILENT;
  ceres::Solver::Summary summary;
  ceres::Solve(sopts, &problem, &summary);
  if (!summary.IsSolutionUsable()) return inliers;
  Sim3d S;
  S.R = Eigen::Quaterniond(qv[3], qv[0], qv[1], qv[2]).normalized().toRotationMatrix();
  S.t = {tv[0], tv[1], tv[2]};
  S.s = std::exp(log_s);
  if (!plausible_sim3(S, max_scale_)) return inliers;
  std::vector<std::uint8_t> mask(matches_.size(), 0);
  const int c = count_sim3_inliers(kf, S, K, &mask);
  if (c < inliers) return inliers;
  S_cand_new = S;
  inlier_.swap(mask);
  return c;
}

int LoopCloser::ransac_sim3(map::KeyframeId kf, map::KeyframeId cand, const geometry::Pinhole& K,
                            Sim3d& S_cand_new) {
  if (!match_positions(kf, cand)) return 0;
  const std::size_t n = matches_.size();
  if (n < 3) return 0;
  geometry::Rng rng(rng_);
  int best = 0;
  Sim3d best_sim;
  std::vector<std::size_t> sample(3);
  for (int it = 0; it < opts_.ransac_iterations; ++it) {
    sample[0] = rng.uniform_index(static_cast<std::uint32_t>(n));
    sample[1] = rng.uniform_index(static_cast<std::uint32_t>(n));
    sample[2] = rng.uniform_index(static_cast<std::uint32_t>(n));
    if (sample[0] == sample[1] || sample[0] == sample[2] || sample[1] == sample[2]) continue;
    const Sim3d S = fit_sim3(x_new_, x_old_, sample, metric_);
    if (!plausible_sim3(S, max_scale_)) continue;
    const int c = count_sim3_inliers(kf, S, K, nullptr);
    if (c > best) {
      best = c;
      best_sim = S;
    }
  }
  ++rng_;
  if (best < 3) return 0;
  S_cand_new = best_sim;
  return refit_sim3(kf, K, S_cand_new);
}

int LoopCloser::guided_matches(map::KeyframeId kf, map::KeyframeId cand, const Sim3d& S_cand_new,
                               const geometry::Pinhole& K) {
  SE3d T_w_old;
  if (!map_.keyframe_pose(cand, T_w_old)) return 0;
  const SE3d T_old_w = T_w_old.inverse();
  const Sim3d S_new_cand = S_cand_new.inverse();
  const auto kps_new = map_.keyframe_keypoints(kf);
  const auto descs_new = map_.keyframe_descriptors(kf);
  const std::uint32_t n_new = map_.keyframe_num_keypoints(kf);
  // New keypoints already matched are not matched again, nor old points.
  std::vector<std::uint8_t> new_taken(n_new, 0);
  std::vector<map::PointId> old_done;
  old_done.reserve(matches_.size());
  for (const Match& m : matches_) {
    if (m.kp_new < n_new) new_taken[m.kp_new] = 1;
    old_done.push_back(m.p_old);
  }
  std::sort(old_done.begin(), old_done.end());
  struct Best {
    int dist = std::numeric_limits<int>::max();
    Match match;
  };
  std::vector<Best> best_of(n_new);
  map::PointView pv;
  for (std::uint32_t v = 0; v < old_views_.size(); ++v) {
    const map::KeyframeId id = old_views_[v].kf;
    const std::uint32_t n_old = map_.keyframe_num_keypoints(id);
    for (std::uint32_t j = 0; j < n_old; ++j) {
      const map::PointId q = map_.keyframe_point(id, j);
      if (q == map::kNoId || !map_.read_point(q, pv)) continue;
      if (std::binary_search(old_done.begin(), old_done.end(), q)) continue;
      old_done.insert(std::upper_bound(old_done.begin(), old_done.end(), q), q);
      const Eigen::Vector3d x_new = S_new_cand * (T_old_w * pv.p_w);
      if (x_new.z() <= 0.0) continue;
      const Eigen::Vector2d uv = K.project(x_new);
      int best = std::numeric_limits<int>::max();
      std::uint32_t best_k = n_new;
      for (std::uint32_t k = 0; k < n_new; ++k) {
        if (new_taken[k]) continue;
        const features::Keypoint& kn = kps_new[k];
        const double e2 = (Eigen::Vector2d(kn.x, kn.y) - uv).squaredNorm();
        if (e2 > opts_.fuse_radius_px * opts_.fuse_radius_px * sigma2(kn)) continue;
        const map::PointId p = map_.keyframe_point(kf, k);
        if (p == map::kNoId || p == q || map_.point_is_bad(p)) continue;
        const int d = features::hamming(pv.descriptor, descs_new[k]);
        if (d < best) {
          best = d;
          best_k = k;
        }
      }
      if (best_k == n_new || best > opts_.max_descriptor_distance || best >= best_of[best_k].dist) {
        continue;
      }
      best_of[best_k] = Best{best, Match{best_k, j, map_.keyframe_point(kf, best_k), q, v}};
    }
  }
  const std::size_t before = matches_.size();
  for (std::uint32_t k = 0; k < n_new; ++k) {
    if (best_of[k].dist != std::numeric_limits<int>::max()) matches_.push_back(best_of[k].match);
  }
  if (matches_.size() == before || !match_positions(kf, cand)) return 0;
  return static_cast<int>(matches_.size()) - static_cast<int>(before);
}

}  // namespace mer::loop
