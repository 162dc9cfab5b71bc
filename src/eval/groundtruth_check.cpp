#include "eval/groundtruth_check.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdlib>
#include <iterator>
#include <limits>
#include <map>
#include <utility>

#include <Eigen/Geometry>

#include "features/keypoint.h"
#include "geometry/triangulation.h"

namespace mer::eval {
namespace {

constexpr int kRefitIterations = 10;         // Gauss-Newton steps of a point re-fit
constexpr double kMinDepth = 1e-6;           // a point nearer the camera plane is left out
constexpr double kRmsCutLevelPx = 5.0;       // errors beyond this are counted, not in the RMS
constexpr double kMinCentreSpread2 = 1e-12;  // sum of squared offsets of the ground-truth
                                             // centres from their mean below this (m^2): no
                                             // motion
constexpr std::size_t kMaxLevels = 32;       // pyramid levels accounted (more share the last)

// One observation of a re-fitted point: its ground-truth projection and the keypoint's error
// against it, level-0 px.
struct CheckedObservation {
  map::KeyframeId kf = map::kNoId;
  std::uint32_t kp = 0;
  int level = 0;
  Eigen::Vector2d truth_uv = Eigen::Vector2d::Zero();
  Eigen::Vector2d error = Eigen::Vector2d::Zero();
  bool anchored = false;
};

// splitmix64: a small, seedable generator (the shuffle must not depend on the platform).
std::uint64_t next_random(std::uint64_t& state) {
  std::uint64_t z = (state += 0x9E3779B97F4A7C15ULL);
  z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ULL;
  z = (z ^ (z >> 27)) * 0x94D049BB133111EBULL;
  return z ^ (z >> 31);
}

const StampedPose* nearest(std::span<const StampedPose> gt, std::int64_t t_ns,
                           std::int64_t max_dt_ns) {
  auto it = std::lower_bound(gt.begin(), gt.end(), t_ns,
                             [](const StampedPose& p, std::int64_t t) { return p.t_ns < t; });
  const StampedPose* best = nullptr;
  std::int64_t best_dt = std::numeric_limits<std::int64_t>::max();
  for (auto c : {it, it == gt.begin() ? it : std::prev(it)}) {
    if (c == gt.end()) continue;
    const std::int64_t dt = std::abs(c->t_ns - t_ns);
    if (dt <= max_dt_ns && dt < best_dt) {
      best = &*c;
      best_dt = dt;
    }
  }
  return best;
}

// Gauss-Newton on the sigma-weighted reprojection error of X over the observations, with
// the keyframes where the map has them. False when X ends behind a camera or degenerate.
bool refit_point(const map::Map& map, const geometry::Pinhole& K,
                 std::span<const std::pair<map::KeyframeId, std::uint32_t>> obs,
                 Eigen::Vector3d& X) {
  for (int it = 0; it < kRefitIterations; ++it) {
    Eigen::Matrix3d H = Eigen::Matrix3d::Zero();
    Eigen::Vector3d g = Eigen::Vector3d::Zero();
    for (const auto& [kf, kp_id] : obs) {
      SE3d T_w_c;
      if (!map.keyframe_pose(kf, T_w_c)) return false;
      const features::Keypoint& kp = map.keyframe_keypoints(kf)[kp_id];
      const Eigen::Matrix3d R_c_w = T_w_c.linear().transpose();
      const Eigen::Vector3d p_c = R_c_w * (X - T_w_c.translation());
      if (p_c.z() < kMinDepth) return false;
      const Eigen::Vector2d r = K.project(p_c) - Eigen::Vector2d(kp.x, kp.y);
      const double iz = 1.0 / p_c.z();
      Eigen::Matrix<double, 2, 3> d_uv_d_pc;
      d_uv_d_pc << K.fx * iz, 0.0, -K.fx * p_c.x() * iz * iz, 0.0, K.fy * iz,
          -K.fy * p_c.y() * iz * iz;
      const Eigen::Matrix<double, 2, 3> J = d_uv_d_pc * R_c_w;
      const double w = 1.0 / (static_cast<double>(kp.scale) * kp.scale);
      H += w * J.transpose() * J;
      g += w * J.transpose() * r;
    }
    const Eigen::Vector3d step = H.ldlt().solve(g);
    if (!step.allFinite()) return false;
    X -= step;
    if (step.norm() < 1e-12 * std::max(1.0, X.norm())) break;
  }
  return X.allFinite();
}

// Largest parallax angle at X between two of the observing keyframes' centres, degrees.
double max_parallax_deg(const map::Map& map,
                        std::span<const std::pair<map::KeyframeId, std::uint32_t>> obs,
                        const Eigen::Vector3d& X) {
  double best = 0.0;
  for (std::size_t i = 0; i < obs.size(); ++i) {
    SE3d Ti;
    if (!map.keyframe_pose(obs[i].first, Ti)) continue;
    for (std::size_t j = i + 1; j < obs.size(); ++j) {
      SE3d Tj;
      if (!map.keyframe_pose(obs[j].first, Tj)) continue;
      best = std::max(best, geometry::parallax_deg(X, Ti.translation(), Tj.translation()));
    }
  }
  return best;
}

struct KeyframeMove {
  SE3d T_w_c_map;    // where the run left it
  SE3d T_w_c_truth;  // its ground truth in the map frame
};

/// Step 1: the keyframes, their ground truth, and the alignment ground truth -> map; the
/// points ride with their reference keyframe (read before it moves), then the keyframes move
/// to the truth. False (rep.note says why) when the map cannot be aligned.
bool move_to_truth(map::Map& map, std::span<const StampedPose> groundtruth, std::int64_t max_dt_ns,
                   bool with_scale, GroundTruthCheckReport& rep,
                   std::map<map::KeyframeId, KeyframeMove>& moves,
                   std::vector<map::PointId>& points) {
  std::vector<map::KeyframeId> ids;
  std::vector<SE3d> est;
  std::vector<SE3d> gt;
  for (map::KeyframeId id = 0; id < map.num_keyframes(); ++id) {
    SE3d T;
    if (!map.keyframe_is_live(id) || !map.keyframe_pose(id, T)) continue;
    const StampedPose* g = nearest(groundtruth, map.keyframe_t_ns(id), max_dt_ns);
    if (g == nullptr) {
      rep.note =
          "keyframe of frame " + std::to_string(map.keyframe_seq(id)) + " has no ground-truth pose";
      return false;
    }
    ids.push_back(id);
    est.push_back(T);
    gt.push_back(g->T_w_c);
  }
  rep.keyframes = static_cast<int>(ids.size());
  if (ids.size() < 3) {
    rep.note = "fewer than 3 keyframes";
    return false;
  }
  Eigen::Matrix3Xd src(3, ids.size());
  Eigen::Matrix3Xd dst(3, ids.size());
  for (std::size_t i = 0; i < ids.size(); ++i) {
    src.col(static_cast<Eigen::Index>(i)) = gt[i].translation();
    dst.col(static_cast<Eigen::Index>(i)) = est[i].translation();
  }
  const Eigen::Vector3d centre = src.rowwise().mean();
  if ((src.colwise() - centre).squaredNorm() < kMinCentreSpread2) {
    rep.note = "the ground-truth keyframe centres do not move";
    return false;
  }
  const Eigen::Matrix4d S_map_gt = Eigen::umeyama(src, dst, with_scale);
  const double scale = S_map_gt.block<3, 1>(0, 0).norm();
  if (!S_map_gt.allFinite() || !(scale > 0.0)) {
    rep.note = "no alignment maps the ground truth onto the map";
    return false;
  }
  rep.scale = scale;
  const Eigen::Matrix3d R_map_gt = S_map_gt.block<3, 3>(0, 0) / scale;
  const Eigen::Vector3d t_map_gt = S_map_gt.block<3, 1>(0, 3);
  for (std::size_t i = 0; i < ids.size(); ++i) {
    SE3d T_w_c_truth = SE3d::Identity();
    T_w_c_truth.linear() = R_map_gt * gt[i].linear();
    T_w_c_truth.translation() = scale * (R_map_gt * gt[i].translation()) + t_map_gt;
    moves[ids[i]] = {est[i], T_w_c_truth};
  }

  for (map::PointId p = 0; p < map.num_points(); ++p) {
    map::PointView v;
    if (map.point_is_bad(p) || !map.read_point(p, v)) continue;
    const auto m = moves.find(v.ref_keyframe);
    if (m == moves.end()) continue;
    const Eigen::Vector3d p_c = m->second.T_w_c_map.inverse() * v.p_w;
    map.set_point_position(p, m->second.T_w_c_truth * p_c);
    points.push_back(p);
  }
  for (const auto& [id, mv] : moves) map.set_keyframe_pose(id, mv.T_w_c_truth);
  return true;
}

/// Step 2: each point re-fitted at the truth, and its observations' errors against their
/// ground-truth projections (rep's error statistics). Returns the checked observations.
std::vector<CheckedObservation> check_observations(map::Map& map, const geometry::Pinhole& K,
                                                   std::span<const map::PointId> points,
                                                   GroundTruthCheckReport& rep) {
  std::vector<std::pair<map::KeyframeId, std::uint32_t>> obs(
      static_cast<std::size_t>(std::max(1, map.options().max_observations_per_point)));
  std::vector<CheckedObservation> checked;
  std::array<double, kMaxLevels> sum2{};
  std::array<int, kMaxLevels> count{};
  std::array<int, kMaxLevels> in_rms{};
  int beyond_1 = 0;
  int beyond_2 = 0;
  std::array<double, 2> flag_sum2{};  // [0]: detected, [1]: anchored
  std::array<int, 2> flag_in_rms{};
  for (const map::PointId p : points) {
    const std::size_t n = map.point_observations(p, obs);
    if (n < 2) continue;
    map::PointView v;
    if (!map.read_point(p, v)) continue;
    Eigen::Vector3d X = v.p_w;
    const std::span<const std::pair<map::KeyframeId, std::uint32_t>> o(obs.data(), n);
    if (max_parallax_deg(map, o, X) < kMinRefitParallaxDeg || !refit_point(map, K, o, X)) {
      ++rep.refit_rejected;  // keeps the position it rode to and its keypoints
      continue;
    }
    map.set_point_position(p, X);
    ++rep.points;
    for (const auto& [kf, kp_id] : o) {
      SE3d T_w_c;
      if (!map.keyframe_pose(kf, T_w_c)) continue;
      const features::Keypoint& kp = map.keyframe_keypoints(kf)[kp_id];
      const Eigen::Vector3d p_c = T_w_c.inverse() * X;
      if (p_c.z() < kMinDepth) {  // no projection: keeps its keypoint
        ++rep.unprojected;
        continue;
      }
      CheckedObservation c;
      c.kf = kf;
      c.kp = kp_id;
      c.level = std::clamp(static_cast<int>(kp.level), 0, static_cast<int>(kMaxLevels) - 1);
      c.truth_uv = K.project(p_c);
      c.error = Eigen::Vector2d(kp.x, kp.y) - c.truth_uv;
      c.anchored = kp.anchored != 0;
      const double e_level = c.error.norm() / static_cast<double>(kp.scale);
      beyond_1 += e_level > 1.0 ? 1 : 0;
      beyond_2 += e_level > 2.0 ? 1 : 0;
      const auto level = static_cast<std::size_t>(c.level);
      ++count[level];
      const std::size_t flag = kp.anchored != 0 ? 1 : 0;
      rep.anchored_observations += static_cast<int>(flag);
      if (e_level <= kRmsCutLevelPx) {
        const double e2 = c.error.squaredNorm() / (static_cast<double>(kp.scale) * kp.scale);
        sum2[level] += e2;
        ++in_rms[level];
        flag_sum2[flag] += e2;
        ++flag_in_rms[flag];
      }
      checked.push_back(c);
    }
  }
  rep.observations = static_cast<int>(checked.size());
  if (checked.empty()) return checked;
  rep.beyond_1_level_px = static_cast<double>(beyond_1) / static_cast<double>(checked.size());
  rep.beyond_2_level_px = static_cast<double>(beyond_2) / static_cast<double>(checked.size());
  auto rms = [](double s2, int n) { return n > 0 ? std::sqrt(s2 / (2.0 * n)) : 0.0; };
  rep.detected_rms_level_px = rms(flag_sum2[0], flag_in_rms[0]);
  rep.anchored_rms_level_px = rms(flag_sum2[1], flag_in_rms[1]);
  std::size_t top = 0;
  for (std::size_t level = 0; level < kMaxLevels; ++level) top = count[level] > 0 ? level + 1 : top;
  for (std::size_t level = 0; level < top; ++level) {
    GroundTruthLevelError e;
    e.observations = count[level];
    e.rms_level_px = rms(sum2[level], in_rms[level]);
    rep.levels.push_back(e);
  }
  return checked;
}

}  // namespace

GroundTruthCheckReport check_against_groundtruth(map::Map& map, backend::LocalBundleAdjuster& ba,
                                                 const geometry::Pinhole& K,
                                                 std::span<const StampedPose> groundtruth,
                                                 std::int64_t max_dt_ns, bool with_scale,
                                                 int max_iterations, std::uint64_t seed) {
  GroundTruthCheckReport rep;
  // 1. The map moved to the truth.
  std::map<map::KeyframeId, KeyframeMove> moves;
  std::vector<map::PointId> points;
  if (!move_to_truth(map, groundtruth, max_dt_ns, with_scale, rep, moves, points)) return rep;

  // 2. Re-fit each point at the truth; its observations' errors.
  const std::vector<CheckedObservation> checked = check_observations(map, K, points, rep);
  if (checked.empty()) {
    rep.note = "no point with two observations and enough parallax";
    return rep;
  }
  // Where step 3 starts, for step 4 to start there too.
  std::vector<std::pair<map::PointId, Eigen::Vector3d>> start;
  for (const map::PointId p : points) {
    map::PointView v;
    if (map.read_point(p, v)) start.emplace_back(p, v.p_w);
  }

  // 3. The full BA from the truth, on the map's own observations.
  backend::LocalBaReport r = ba.optimize_full(K, max_iterations, /*cull_points=*/false);
  rep.iterations_converged = r.iterations;
  rep.converged = map.live_keyframe_poses();

  // 4. Errors shuffled within each level; back to the start; the full BA again. With
  //    `detected_only`, only the keypoints that are not anchored trade errors, among
  //    themselves; anchored ones keep theirs (5.).
  auto shuffle_and_solve = [&](bool detected_only, std::vector<StampedPose>& poses) {
    auto shuffled = [&](const CheckedObservation& c) { return !detected_only || !c.anchored; };
    std::array<std::vector<Eigen::Vector2d>, kMaxLevels> pool;
    for (const CheckedObservation& c : checked) {
      if (shuffled(c)) pool[static_cast<std::size_t>(c.level)].push_back(c.error);
    }
    std::uint64_t state = seed;
    for (auto& errors : pool) {
      for (std::size_t i = errors.size(); i > 1; --i) {
        std::swap(errors[i - 1], errors[next_random(state) % i]);
      }
    }
    std::array<std::size_t, kMaxLevels> used{};
    for (const CheckedObservation& c : checked) {
      const auto level = static_cast<std::size_t>(c.level);
      const Eigen::Vector2d uv = c.truth_uv + (shuffled(c) ? pool[level][used[level]++] : c.error);
      map.set_keypoint_position(c.kf, c.kp, static_cast<float>(uv.x()), static_cast<float>(uv.y()));
    }
    for (const auto& [id, mv] : moves) map.set_keyframe_pose(id, mv.T_w_c_truth);
    for (const auto& [p, X] : start) map.set_point_position(p, X);
    const backend::LocalBaReport rs = ba.optimize_full(K, max_iterations, /*cull_points=*/false);
    poses = map.live_keyframe_poses();
    return rs.iterations;
  };
  rep.iterations_shuffled = shuffle_and_solve(false, rep.shuffled);
  // 5. Only the detected keypoints' errors shuffled: where the pattern of step 4 lives.
  if (rep.anchored_observations > 0 && rep.anchored_observations < rep.observations) {
    rep.iterations_shuffled_detected = shuffle_and_solve(true, rep.shuffled_detected);
  }
  rep.ran = true;
  return rep;
}

}  // namespace mer::eval
