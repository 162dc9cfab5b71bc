// A merge measured from keyframes (LoopCloser, loop_closer.h, merge_by_relocalization): the
// keyframes of the candidate's segment made nearest to it are relocalized against the new
// keyframe's local map, and the similarity between the two segments' world frames is fitted
// to the poses of those placed. It needs the keypoints of the candidate's side and the
// map-points of the new keyframe's side: a segment that was being lost keeps too few
// map-points for the 3D similarity, but all its keyframes' keypoints.
#include <algorithm>
#include <cmath>
#include <limits>
#include <numbers>
#include <utility>
#include <vector>

#include "core/median.h"
#include "loop/loop_closer.h"
#include "platform/log_ring.h"

namespace mer::loop {
namespace {

using geometry::Sim3d;

/// Degrees per radian.
constexpr double kRadToDeg = 180.0 / std::numbers::pi;
/// Parameters of a similarity fitted to camera positions with its rotation known (translation,
/// scale): the residual degrees of freedom of n placed centres are 3 n - kPositionFitDof.
constexpr double kPositionFitDof = 4.0;
/// Median absolute deviation -> standard deviation of a normal distribution.
constexpr double kMadToSigma = 1.4826;
/// Depth ratios the depth-based scale needs, at least (fewer: the positions alone measure it).
constexpr std::size_t kMinDepthRatios = 8;
/// Two measures of one scale that differ by more than this many combined standard deviations
/// disagree: a placed keyframe is wrong.
constexpr double kScaleAgreementSigmas = 3.0;

/// A keyframe of the candidate's segment placed in the new keyframe's world frame.
struct Placed {
  map::KeyframeId id = map::kNoId;
  std::size_t weld_begin = 0;  ///< its inliers in LoopCloser::weld_: [begin, end)
  std::size_t weld_end = 0;
  SE3d T_own_c = SE3d::Identity();    ///< camera -> its own segment's world
  SE3d T_other_c = SE3d::Identity();  ///< camera -> the new keyframe's segment's world
  int inliers = 0;
  double depth = 0.0;              ///< median depth of its inliers in the new frame
  std::vector<double> log_ratios;  ///< log(depth there / depth of its own point), per keypoint
};

/// A similarity fitted to placed keyframes and how well it holds.
struct PlacedFit {
  Sim3d S;                        ///< world of the placed keyframes -> the new keyframe's
  double scale_sigma = 0.0;       ///< standard deviation of log S.s
  bool scales_agree = true;       ///< positions and depth ratios give the same scale
  double max_residual_deg = 0.0;  ///< the worst keyframe's pose error (orientation, position)
  std::size_t worst = 0;          ///< that keyframe
  double sigma_pos = 0.0;         ///< log-scale standard deviation by the centres
  double sigma_depth = 0.0;       ///< by the depth ratios
  std::size_t ratios = 0;         ///< depth ratios
};

/// Rotation: the chordal mean of the keyframes'; scale: the centres' spread and the depth
/// ratios, combined by their uncertainties; translation: least squares on the centres.
PlacedFit fit_placed(const std::vector<Placed>& placed, bool metric) {
  PlacedFit f;
  std::vector<SE3d> from;
  std::vector<SE3d> to;
  for (const Placed& p : placed) {
    from.push_back(p.T_own_c);
    to.push_back(p.T_other_c);
  }
  const Sim3d S_pos = geometry::fit_similarity_to_poses(from, to, !metric);
  const auto n = static_cast<double>(placed.size());
  Eigen::Vector3d p_mean = Eigen::Vector3d::Zero();
  Eigen::Vector3d q_mean = Eigen::Vector3d::Zero();
  for (const Placed& p : placed) {
    p_mean += p.T_own_c.translation();
    q_mean += p.T_other_c.translation();
  }
  p_mean /= n;
  q_mean /= n;
  double log_s = 0.0;
  f.scale_sigma = 0.0;
  if (!metric) {
    // The centres: the residual of the positions over their spread (the placed keyframes'
    // own centres, in the new frame's units: a scale is measured only along a baseline).
    double spread2 = 0.0;
    double resid2 = 0.0;
    for (const Placed& p : placed) {
      spread2 += (p.T_own_c.translation() - p_mean).squaredNorm();
      resid2 += (S_pos * p.T_own_c.translation() - p.T_other_c.translation()).squaredNorm();
    }
    const double sigma_xyz = std::sqrt(resid2 / std::max(1.0, 3.0 * n - kPositionFitDof));
    const double sigma_pos = spread2 > 0.0 ? sigma_xyz / (S_pos.s * std::sqrt(spread2))
                                           : std::numeric_limits<double>::infinity();
    // The depth ratios: median and its spread.
    std::vector<double> ratios;
    for (const Placed& p : placed)
      ratios.insert(ratios.end(), p.log_ratios.begin(), p.log_ratios.end());
    double sigma_depth = std::numeric_limits<double>::infinity();
    double log_depth = 0.0;
    if (ratios.size() >= kMinDepthRatios) {
      log_depth = upper_median(ratios);
      std::vector<double> dev;
      dev.reserve(ratios.size());
      for (const double r : ratios) dev.push_back(std::abs(r - log_depth));
      sigma_depth = kMadToSigma * upper_median(dev) / std::sqrt(static_cast<double>(ratios.size()));
    }
    const double log_pos = std::log(S_pos.s);
    f.sigma_pos = sigma_pos;
    f.sigma_depth = sigma_depth;
    f.ratios = ratios.size();
    const double w_pos =
        std::isfinite(sigma_pos) && sigma_pos > 0.0 ? 1.0 / (sigma_pos * sigma_pos) : 0.0;
    const double w_depth =
        std::isfinite(sigma_depth) && sigma_depth > 0.0 ? 1.0 / (sigma_depth * sigma_depth) : 0.0;
    if (w_pos > 0.0 && w_depth > 0.0) {
      f.scales_agree =
          std::abs(log_pos - log_depth) <=
          kScaleAgreementSigmas * std::sqrt(sigma_pos * sigma_pos + sigma_depth * sigma_depth);
    }
    if (w_pos + w_depth > 0.0) {
      log_s = (w_pos * log_pos + w_depth * log_depth) / (w_pos + w_depth);
      f.scale_sigma = 1.0 / std::sqrt(w_pos + w_depth);
    } else {
      f.scale_sigma = std::numeric_limits<double>::infinity();
    }
  }
  f.S.R = S_pos.R;
  f.S.s = std::exp(log_s);
  f.S.t = q_mean - f.S.s * (f.S.R * p_mean);
  // Each keyframe: orientation error, and position error as the angle it subtends at the
  // keyframe's median scene depth.
  double worst = -1.0;
  for (std::size_t i = 0; i < placed.size(); ++i) {
    const SE3d T = geometry::apply_to_pose(f.S, placed[i].T_own_c);
    const double rot =
        kRadToDeg *
        Eigen::AngleAxisd(T.linear().transpose() * placed[i].T_other_c.linear()).angle();
    const double pos = placed[i].depth > 0.0
                           ? kRadToDeg *
                                 (T.translation() - placed[i].T_other_c.translation()).norm() /
                                 placed[i].depth
                           : std::numeric_limits<double>::infinity();
    const double e = std::max(rot, pos);
    f.max_residual_deg = std::max(f.max_residual_deg, e);
    if (e > worst) {
      worst = e;
      f.worst = i;
    }
  }
  return f;
}

}  // namespace

int LoopCloser::sim3_from_relocalized_keyframes(map::KeyframeId kf, map::KeyframeId cand,
                                                const geometry::Pinhole& K, Sim3d& S_cand_new,
                                                int& inliers) {
  inliers = 0;
  SE3d T_w_new;
  SE3d T_w_cand;
  if (!merge_reloc_ || !map_.keyframe_pose(kf, T_w_new) || !map_.keyframe_pose(cand, T_w_cand)) {
    return 0;
  }
  // The candidate and the keyframes of its segment made nearest to it, nearest first.
  const std::uint16_t seg = map_.keyframe_segment(cand);
  const std::uint64_t s_cand = map_.keyframe_serial(cand);
  std::vector<std::pair<std::uint64_t, map::KeyframeId>> order;
  for (map::KeyframeId id = 0; id < map_.num_keyframes(); ++id) {
    if (!map_.keyframe_is_live(id) || map_.keyframe_segment(id) != seg) continue;
    const std::uint64_t s = map_.keyframe_serial(id);
    order.emplace_back(s > s_cand ? s - s_cand : s_cand - s, id);
  }
  std::sort(order.begin(), order.end());
  const auto tries =
      std::min(order.size(), static_cast<std::size_t>(opts_.merge_relocalize_keyframes));
  const auto need = static_cast<std::size_t>(opts_.merge_min_keyframes);
  std::vector<Placed> placed;
  std::vector<std::uint32_t> kps_in;
  std::vector<Eigen::Vector3d> X_in;
  std::vector<double> depths;
  std::vector<map::PointId> pts_in;
  std::vector<Weld> all_welds;
  for (std::size_t i = 0; i < tries; ++i) {
    // Not enough left to reach merge_min_keyframes: stop (bounds a look that fails).
    if (placed.size() + (tries - i) < need) break;
    const map::KeyframeId id = order[i].second;
    const auto kps = map_.keyframe_keypoints(id);
    const auto descs = map_.keyframe_descriptors(id);
    const std::size_t n = std::min<std::size_t>(
        {kps.size(), descs.size(), static_cast<std::size_t>(map_.keyframe_num_keypoints(id))});
    RelocQuery q;
    q.seq = map_.keyframe_seq(id);
    q.t_ns = map_.keyframe_t_ns(id);
    q.keypoints = kps.first(n);
    q.descriptors = descs.first(n);
    q.K = K;
    const RelocResult r = merge_reloc_->localize_against(q, kf);
    MER_LOG_DEBUG(
        "loop: merge by relocalization: keyframe of frame %llu against %llu: %s (%d matches, %d "
        "inliers)",
        static_cast<unsigned long long>(q.seq),
        static_cast<unsigned long long>(map_.keyframe_seq(kf)), r.success ? "placed" : "not placed",
        r.matches, r.inliers);
    if (id == cand && !r.success) break;  // the place retrieval found is not this one
    SE3d T_from;
    if (!r.success || !map_.keyframe_pose(id, T_from)) continue;
    Placed p{id, 0, 0, T_from, r.T_c_w.inverse(), r.inliers, 0.0, {}};
    // Depths of the inliers in the new frame, and their ratios to the depths of the points
    // the keyframe's own segment holds for the same keypoints.
    kps_in.clear();
    X_in.clear();
    pts_in.clear();
    depths.clear();
    merge_reloc_->last_inliers(kps_in, X_in, &pts_in);
    p.weld_begin = all_welds.size();
    for (std::size_t k = 0; k < kps_in.size(); ++k)
      all_welds.push_back(Weld{id, kps_in[k], pts_in[k]});
    p.weld_end = all_welds.size();
    const SE3d T_from_inv = T_from.inverse();
    map::PointView pv;
    for (std::size_t k = 0; k < kps_in.size(); ++k) {
      const double z_to = (r.T_c_w * X_in[k]).z();
      if (!(z_to > 0.0)) continue;
      depths.push_back(z_to);
      const map::PointId own = map_.keyframe_point(id, kps_in[k]);
      if (own == map::kNoId || map_.point_is_bad(own) || !map_.read_point(own, pv)) continue;
      const double z_from = (T_from_inv * pv.p_w).z();
      if (z_from > 0.0) p.log_ratios.push_back(std::log(z_to / z_from));
    }
    p.depth = upper_median(depths);
    placed.push_back(std::move(p));
  }
  // Fit, dropping the keyframe that disagrees most while the fit does not hold.
  PlacedFit f;
  bool ok = false;
  while (placed.size() >= need) {
    f = fit_placed(placed, metric_);
    MER_LOG_DEBUG(
        "loop: merge by relocalization: %zu keyframes placed, scale %.4f (log sigma %.3f: centres "
        "%.3f, %zu depth ratios %.3f; %s), pose residual up to %.2f deg",
        placed.size(), f.S.s, f.scale_sigma, f.sigma_pos, f.ratios, f.sigma_depth,
        f.scales_agree ? "measures agree" : "measures differ", f.max_residual_deg);
    if (f.scales_agree && f.scale_sigma <= opts_.merge_max_scale_uncertainty &&
        f.max_residual_deg <= opts_.merge_max_pose_residual_deg && f.S.s <= max_scale_ &&
        f.S.s >= 1.0 / max_scale_) {
      ok = true;
      break;
    }
    placed.erase(placed.begin() + static_cast<std::ptrdiff_t>(f.worst));
  }
  if (!ok) return 0;
  weld_.clear();
  for (const Placed& p : placed) {
    if (p.id == cand) inliers = p.inliers;
    weld_.insert(weld_.end(), all_welds.begin() + static_cast<std::ptrdiff_t>(p.weld_begin),
                 all_welds.begin() + static_cast<std::ptrdiff_t>(p.weld_end));
  }
  if (inliers == 0) {  // the candidate itself was dropped from the fit
    for (const Placed& p : placed) inliers = std::max(inliers, p.inliers);
  }
  // The candidate's camera from the new keyframe's: through the two worlds.
  S_cand_new = Sim3d::from_se3(T_w_cand.inverse()) * f.S.inverse() * Sim3d::from_se3(T_w_new);
  return static_cast<int>(placed.size());
}

int LoopCloser::weld(LoopReport& rep) {
  int merged = 0;
  std::vector<map::KeyframeId> touched;
  map::PointView pv;
  for (const Weld& w : weld_) {
    // Both sides must be of one segment now (the merge joined them).
    if (!map_.keyframe_is_live(w.kf) || map_.point_is_bad(w.point) ||
        !map_.read_point(w.point, pv) ||
        map_.keyframe_segment(w.kf) != map_.keyframe_segment(pv.ref_keyframe)) {
      continue;
    }
    const map::PointId own = map_.keyframe_point(w.kf, w.kp);
    if (own == w.point) continue;
    if (own == map::kNoId) {
      if (!map_.add_observation(w.point, w.kf, w.kp)) continue;
      map_.update_point(w.point);
      ++rep.fused_observations;
    } else if (map_.point_is_bad(own) || map_.merge_points(w.point, own) < 0) {
      continue;
    } else {
      ++merged;
    }
    if (touched.empty() || touched.back() != w.kf) touched.push_back(w.kf);
  }
  for (const map::KeyframeId kf : touched) map_.update_covisibility(kf);
  weld_.clear();
  return merged;
}

}  // namespace mer::loop
