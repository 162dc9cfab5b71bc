#include "loop/loop_closer.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <mutex>
#include <numeric>
#include <utility>

#include <ceres/ceres.h>

#include "backend/local_ba.h"
#include "core/median.h"
#include "geometry/random.h"
#include "loop/descriptor_match.h"
#include "platform/clock.h"
#include "platform/log_ring.h"

namespace mer::loop {

namespace {

using geometry::Sim3d;

/// A pending loop expires when this many keyframes pass without it being seen again.
constexpr std::uint64_t kConsistencyWindowKeyframes = 3;
/// Loop edges remembered for the pose graphs of later loops.
constexpr std::size_t kMaxLoopEdges = 4096;
/// A Sim(3) fit's scale outside [1/k, k] is not drift, it is a wrong match.
constexpr double kMaxLoopScale = 2.0;
/// Between two monocular segments the scale is not drift but the ratio of the scales their
/// initializations chose (each from its own first views' depths): any ratio is possible, and
/// the bound only keeps degenerate fits out.
constexpr double kMaxMergeScale = 100.0;
/// Refits of a loop similarity on its inliers before the inlier set is taken as settled.
constexpr int kRefitRounds = 3;
/// Nanoseconds per second (min_time_gap_s).
constexpr double kNsPerS = 1e9;
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

LoopCloser::LoopCloser(const LoopOptions& opts, map::Map& map, std::vector<float> level_sigma2,
                       bool metric, backend::LocalBundleAdjuster* ba)
    : opts_(opts),
      map_(map),
      level_sigma2_(std::move(level_sigma2)),
      metric_(metric),
      ba_(ba),
      db_(map),
      rng_(static_cast<std::uint32_t>(opts.seed)) {
  const auto nk = static_cast<std::size_t>(map.options().max_keypoints_per_keyframe);
  matches_.reserve(nk);
  best_matches_.reserve(nk);
  loop_edges_.reserve(kMaxLoopEdges);
  inlier_.reserve(nk);
  best_inlier_.reserve(nk);
  x_new_.reserve(nk);
  x_old_.reserve(nk);
}

float LoopCloser::sigma2(const features::Keypoint& k) const {
  return features::level_sigma2(level_sigma2_, k.level);
}

LoopReport LoopCloser::spin_once(map::KeyframeId kf, const geometry::Pinhole& K) {
  LoopReport rep;
  if (!opts_.enabled || kf == map::kNoId) return rep;
  const auto t0 = platform::monotonic_now_ns();
  std::unique_lock<platform::PiMutex> lock(map_.writer_lock());
  // A discarded segment's keyframe (a failed start) is never a loop's or a merge's.
  if (!map_.keyframe_is_live(kf) || kf >= db_.capacity() ||
      map_.segment_discarded(map_.keyframe_segment(kf))) {
    return rep;
  }
  const std::uint64_t serial = map_.keyframe_serial(kf);
  if (any_loop_ &&
      serial < last_loop_serial_ + static_cast<std::uint64_t>(opts_.cooldown_keyframes)) {
    return rep;
  }
  ++totals_.keyframes_checked;
  const std::uint16_t segment = map_.keyframe_segment(kf);
  retrieve_candidates(kf, serial, segment);
  Hypothesis best = check_candidates(kf, segment, K, rep);
  decide(kf, serial, segment, best, K, rep);
  rep.ms = platform::elapsed_ms(t0);
  lock.unlock();
  if (rep.closed) finish_closure(kf, serial, K, rep);
  totals_.max_ms = std::max(totals_.max_ms, rep.ms);
  return rep;
}

void LoopCloser::retrieve_candidates(map::KeyframeId kf, std::uint64_t serial,
                                     std::uint16_t segment) {
  // 1. Retrieval. Old keyframes the new one already shares points with (tracking found
  // their points again) come first, by shared points; then those whose key score passes the
  // bar, by score.
  std::vector<Candidate>& ranked = ranked_;
  ranked.clear();
  std::vector<Candidate> scored;
  std::unique_lock<platform::PiMutex> db_lock(db_.mutex());  // until key_scores is read
  (void)db_.refresh(kf);
  db_.refresh_live();  // key frequencies first
  const std::span<const double> key_scores = db_.score_keyframe(kf);
  const map::KeyframeId n = map_.num_keyframes();
  const std::int64_t t_kf = map_.keyframe_t_ns(kf);
  const auto min_gap_ns = static_cast<std::int64_t>(opts_.min_time_gap_s * kNsPerS);
  for (map::KeyframeId id = 0; id < n && id < db_.capacity(); ++id) {
    if (id == kf || !map_.keyframe_is_live(id) ||
        map_.segment_discarded(map_.keyframe_segment(id))) {
      continue;
    }
    // Another segment's keyframes are in an unrelated world frame: a match with one merges
    // the two segments (merge_segments), whenever they were made.
    if (map_.keyframe_segment(id) != segment) {
      if (opts_.merge_segments) scored.push_back(Candidate{false, key_scores[id], id});
      continue;
    }
    if (map_.keyframe_serial(id) + static_cast<std::uint64_t>(opts_.min_keyframe_gap) > serial ||
        map_.keyframe_t_ns(id) + min_gap_ns > t_kf) {
      continue;
    }
    if (const std::uint32_t w =
            std::max(map_.covisibility_weight(kf, id), map_.covisibility_weight(id, kf));
        w > 0) {
      // Joined to the new keyframe through shared points already: the same place as far as
      // the map knows, nothing for a loop to add (exclude_connected).
      if (opts_.exclude_connected) {
        ++totals_.excluded_connected;
        continue;
      }
      ranked.push_back(Candidate{true, static_cast<double>(w), id});
    } else {
      scored.push_back(Candidate{false, key_scores[id], id});
    }
  }
  db_lock.unlock();
  double bar = 0.0;
  if (!scored.empty()) {
    std::vector<double> v;
    v.reserve(scored.size());
    for (const Candidate& c : scored) v.push_back(c.score);
    bar = opts_.min_key_score_ratio * upper_median(v);
    for (const Candidate& c : scored) {
      if (c.score >= bar) ranked.push_back(c);
    }
  }
  std::sort(ranked.begin(), ranked.end(), [](const Candidate& a, const Candidate& b) {
    if (a.covisible != b.covisible) return a.covisible;
    if (a.score != b.score) return a.score > b.score;
    return a.id < b.id;
  });
  MER_LOG_DEBUG("loop: keyframe of frame %llu: %zu candidates (key score bar %.1f)",
                static_cast<unsigned long long>(map_.keyframe_seq(kf)), ranked.size(), bar);
  if (ranked.size() > static_cast<std::size_t>(opts_.max_candidates)) {
    ranked.resize(static_cast<std::size_t>(opts_.max_candidates));
  }
}

LoopCloser::Hypothesis LoopCloser::check_candidates(map::KeyframeId kf, std::uint16_t segment,
                                                    const geometry::Pinhole& K, LoopReport& rep) {
  // 2. Geometric check of every candidate; the one whose similarity explains the most
  //    matches wins (the first to pass may be a weaker hypothesis of a neighbouring place,
  //    made to pass by the guided search).
  Hypothesis best;
  double usual = -1.0;  // usual_found_share(kf), computed when first needed
  for (const Candidate& c : ranked_) {
    const map::KeyframeId cand = c.id;
    max_scale_ = map_.keyframe_segment(cand) != segment ? kMaxMergeScale : kMaxLoopScale;
    ++rep.candidates;
    ++totals_.candidates_checked;
    int m = match_points(kf, cand);
    MER_LOG_DEBUG("loop: keyframe %llu vs %llu: %s %.1f, %d point matches",
                  static_cast<unsigned long long>(map_.keyframe_seq(kf)),
                  static_cast<unsigned long long>(map_.keyframe_seq(cand)),
                  c.covisible ? "shared points" : "key score", c.score, m);
    if (m < opts_.min_matches) {
      ++totals_.rejected.few_matches;
      continue;
    }
    Sim3d S_cand_new;
    int inliers = ransac_sim3(kf, cand, K, S_cand_new);
    MER_LOG_DEBUG("loop: %d of %d matches agree (scale %.3f)", inliers, m, S_cand_new.s);
    if (opts_.guided_min_inliers > 0 && inliers >= opts_.guided_min_inliers) {
      const int added = guided_matches(kf, cand, S_cand_new, K);
      if (added > 0) {
        inliers = refit_sim3(kf, K, S_cand_new);
        m = static_cast<int>(matches_.size());
      }
      MER_LOG_DEBUG("loop: guided search: %d more matches, %d of %d agree (scale %.3f)", added,
                    inliers, m, S_cand_new.s);
    }
    if (inliers >= opts_.min_inliers) {
      const double s_fit = S_cand_new.s;
      inliers = refine_sim3(kf, K, inliers, S_cand_new);
      MER_LOG_DEBUG("loop: refined on reprojection: %d agree (scale %.4f, 3D fit %.4f)", inliers,
                    S_cand_new.s, s_fit);
    }
    if (inliers < opts_.min_inliers) {
      ++totals_.rejected.few_inliers;
      continue;
    }
    if (inliers <= best.inliers) continue;
    // Drift bound: the correction at the new keyframe cannot exceed a fraction of the path
    // travelled since the old one (perceptual aliasing: a similar place far away). Another
    // segment's frame is unrelated: no path, no bound (the checks below still apply).
    const bool merge = map_.keyframe_segment(cand) != segment;
    const double drift = merge ? 0.0 : implied_drift(kf, cand, S_cand_new);
    if (drift > opts_.max_drift_fraction) {
      MER_LOG_DEBUG("loop: refused, it implies %.1f %% drift", 100.0 * drift);
      ++rep.refused_drift;
      ++totals_.rejected.drift;
      continue;
    }
    // Both ways: the similarity must find the surroundings too, not only what the two places
    // share (a repeated poster matches its copy; the walls around it do not).
    double found_new = 0.0;
    double found_old = 0.0;
    found_both_ways(kf, cand, S_cand_new, K, found_new, found_old);
    if (usual < 0.0) usual = usual_found_share(kf, K);
    MER_LOG_DEBUG(
        "loop: found both ways: %.2f of the old points in the new view, %.2f of the "
        "new in the old view (%.2f with its own neighbour)",
        found_new, found_old, usual);
    if (std::min(found_new, found_old) < opts_.min_found_fraction * usual) {
      ++rep.refused_found;
      ++totals_.rejected.not_found;
      continue;
    }
    best =
        Hypothesis{cand, m, inliers, S_cand_new, drift, found_new, found_old, c.covisible, usual};
    best_matches_.swap(matches_);
    best_inlier_.swap(inlier_);
    best_old_views_.swap(old_views_);
  }
  return best;
}

void LoopCloser::decide(map::KeyframeId kf, std::uint64_t serial, std::uint16_t segment,
                        Hypothesis& best, const geometry::Pinhole& K, LoopReport& rep) {
  if (best.cand == map::kNoId && pending_.count > 0 &&
      serial > pending_.serial + kConsistencyWindowKeyframes) {
    ++totals_.rejected.inconsistent;  // not seen again in time
    pending_ = Pending{};
  }
  if (best.cand != map::kNoId) {
    const map::KeyframeId cand = best.cand;
    // Consistency: the loop must be seen again by the next keyframes, on the same old place
    // (the candidate or a keyframe covisible with it), before the map is corrected. A place
    // that only looks like an old one rarely does so twice in a row.
    const bool same_place =
        pending_.count > 0 && serial <= pending_.serial + kConsistencyWindowKeyframes &&
        (cand == pending_.cand || map_.covisibility_weight(cand, pending_.cand) > 0 ||
         map_.covisibility_weight(pending_.cand, cand) > 0);
    const int agreeing = same_place ? pending_.count + 1 : 1;
    if (!same_place && pending_.count > 0) ++totals_.rejected.inconsistent;
    const int needed = map_.keyframe_segment(cand) != segment ? opts_.merge_consistent_checks
                                                              : opts_.consistent_checks;
    MER_LOG_DEBUG("loop: %d of %d consecutive checks agree", agreeing, needed);
    if (agreeing < needed) {
      pending_ = Pending{cand, serial, agreeing};
      ++rep.pending;
    } else {
      pending_ = Pending{};
      matches_.swap(best_matches_);
      inlier_.swap(best_inlier_);
      old_views_.swap(best_old_views_);
      rep.matches = best.matches;
      rep.inliers = best.inliers;
      rep.loop_keyframe = cand;
      rep.loop_seq = map_.keyframe_seq(cand);
      rep.loop_t_ns = map_.keyframe_t_ns(cand);
      rep.similarity = best.sim;
      rep.found_new = best.found_new;
      rep.found_old = best.found_old;
      rep.drift = best.drift;
      rep.connected = best.connected;
      rep.found_usual = best.usual;
      if (map_.keyframe_segment(cand) != segment) {
        merge_segments(kf, cand, best.sim, rep);
        // Refused by the map (the tracker discarded a segment meanwhile, lock-free): the two
        // are still in unrelated frames, nothing to correct.
        if (rep.merged_from == map::kNoSegment) {
          ++totals_.rejected.merge_refused;
          return;
        }
      }
      rep.merged_points = correct(kf, cand, best.sim, K, rep);
      rep.closed = true;
    }
  }
}

void LoopCloser::finish_closure(map::KeyframeId kf, std::uint64_t serial,
                                const geometry::Pinhole& K, LoopReport& rep) {
  any_loop_ = true;
  last_loop_serial_ = serial;
  MER_LOG_INFO(
      "loop closed: keyframe of frame %llu onto frame %llu, %d of %d matches, scale %.4f, "
      "shift %.3f, %d keyframes, %d points merged, %d observations fused, %.1f ms",
      static_cast<unsigned long long>(map_.keyframe_seq(kf)),
      static_cast<unsigned long long>(rep.loop_seq), rep.inliers, rep.matches, rep.scale, rep.shift,
      rep.keyframes, rep.merged_points, rep.fused_observations, rep.ms);
  if (ba_ != nullptr && opts_.full_ba_iterations > 0) {
    const auto t1 = platform::monotonic_now_ns();
    (void)ba_->optimize_full(K, opts_.full_ba_iterations);
    rep.full_ba_ms = platform::elapsed_ms(t1);
  }
  ++totals_.loops_closed;
  if (rep.merged_from != map::kNoSegment) {
    ++totals_.segments_merged;
    if (totals_.merges.size() < kMaxLoopEvents) {
      totals_.merges.push_back(SegmentMergeEvent{
          map_.keyframe_seq(kf), map_.keyframe_t_ns(kf), rep.loop_seq, rep.merged_from,
          rep.merged_into, rep.merge_keyframes, rep.inliers, rep.merge_similarity});
    }
  }
  totals_.merged_points += static_cast<std::uint64_t>(rep.merged_points);
  totals_.last_loop = rep;
  if (totals_.closures.size() < kMaxLoopEvents) {
    totals_.closures.push_back(
        LoopClosureEvent{map_.keyframe_seq(kf), map_.keyframe_t_ns(kf), rep.loop_seq, rep.loop_t_ns,
                         map_.keyframe_segment(kf), rep.inliers, rep.found_new, rep.found_old,
                         rep.found_usual, rep.drift, rep.connected, rep.similarity});
  }
  totals_.max_full_ba_ms = std::max(totals_.max_full_ba_ms, rep.full_ba_ms);
}

double LoopCloser::implied_drift(map::KeyframeId kf, map::KeyframeId cand,
                                 const Sim3d& S_cand_new) const {
  SE3d T_w_new;
  SE3d T_w_cand;
  if (!map_.keyframe_pose(kf, T_w_new) || !map_.keyframe_pose(cand, T_w_cand)) {
    return std::numeric_limits<double>::infinity();
  }
  const Sim3d S_w_corrected = Sim3d::from_se3(T_w_cand) * S_cand_new;
  // What the new keyframe sees moves by the centre's shift plus, at its median depth, the
  // rotation of the correction (a look-alike on another wall asks for a large turn).
  const double angle = Eigen::AngleAxisd(T_w_new.linear().transpose() * S_w_corrected.R).angle();
  const double shift = (S_w_corrected.t - T_w_new.translation()).norm() +
                       angle * keyframe_median_depth(kf, T_w_new.inverse());
  // Path from the old keyframe to the new one through the live keyframes between them.
  const std::uint64_t s0 = map_.keyframe_serial(cand);
  const std::uint64_t s1 = map_.keyframe_serial(kf);
  std::vector<std::pair<std::uint64_t, Eigen::Vector3d>> centres;
  for (map::KeyframeId id = 0; id < map_.num_keyframes(); ++id) {
    SE3d T;
    if (!map_.keyframe_is_live(id) || !map_.keyframe_pose(id, T)) continue;
    const std::uint64_t s = map_.keyframe_serial(id);
    if (s >= s0 && s <= s1) centres.emplace_back(s, T.translation());
  }
  std::sort(centres.begin(), centres.end(),
            [](const auto& a, const auto& b) { return a.first < b.first; });
  double path = 0.0;
  for (std::size_t i = 1; i < centres.size(); ++i) {
    path += (centres[i].second - centres[i - 1].second).norm();
  }
  return path > 0.0 ? shift / path : std::numeric_limits<double>::infinity();
}

void LoopCloser::append_points(map::KeyframeId kf, std::vector<map::PointId>& out) const {
  const std::uint32_t n = map_.keyframe_num_keypoints(kf);
  for (std::uint32_t i = 0; i < n; ++i) {
    const map::PointId p = map_.keyframe_point(kf, i);
    if (p != map::kNoId && !map_.point_is_bad(p)) out.push_back(p);
  }
}

double LoopCloser::keyframe_median_depth(map::KeyframeId kf, const SE3d& T_c_w) const {
  std::vector<double> z;
  const std::uint32_t n = map_.keyframe_num_keypoints(kf);
  z.reserve(n);
  map::PointView pv;
  for (std::uint32_t i = 0; i < n; ++i) {
    const map::PointId p = map_.keyframe_point(kf, i);
    if (p == map::kNoId || !map_.read_point(p, pv)) continue;
    const double d = (T_c_w * pv.p_w).z();
    if (d > 0.0) z.push_back(d);
  }
  return upper_median(z);
}

double LoopCloser::found_share(map::KeyframeId view, const Sim3d& S_view_w,
                               const std::vector<map::PointId>& pts, const geometry::Pinhole& K,
                               int& in_view) const {
  const auto kps = map_.keyframe_keypoints(view);
  const auto descs = map_.keyframe_descriptors(view);
  const std::size_t n = std::min(kps.size(), descs.size());
  in_view = 0;
  int found = 0;
  map::PointView pv;
  for (const map::PointId q : pts) {
    if (!map_.read_point(q, pv)) continue;
    const Eigen::Vector3d x = S_view_w * pv.p_w;
    if (x.z() <= 0.0) continue;
    const Eigen::Vector2d uv = K.project(x);
    // In view: inside the image, taken as twice the principal point (the intrinsics carry no
    // image size).
    if (uv.x() < 0.0 || uv.y() < 0.0 || uv.x() >= 2.0 * K.cx || uv.y() >= 2.0 * K.cy) continue;
    ++in_view;
    for (std::size_t k = 0; k < n; ++k) {
      const features::Keypoint& kp = kps[k];
      const double e2 = (Eigen::Vector2d(kp.x, kp.y) - uv).squaredNorm();
      if (e2 <= opts_.fuse_radius_px * opts_.fuse_radius_px * sigma2(kp) &&
          features::hamming(pv.descriptor, descs[k]) <= opts_.max_descriptor_distance) {
        ++found;
        break;
      }
    }
  }
  return in_view > 0 ? static_cast<double>(found) / in_view : 0.0;
}

void LoopCloser::found_both_ways(map::KeyframeId kf, map::KeyframeId cand, const Sim3d& S_cand_new,
                                 const geometry::Pinhole& K, double& found_new,
                                 double& found_old) const {
  found_new = 0.0;
  found_old = 0.0;
  SE3d T_w_new;
  SE3d T_w_cand;
  if (!map_.keyframe_pose(kf, T_w_new) || !map_.keyframe_pose(cand, T_w_cand)) return;
  // Points of a keyframe (each once), the new keyframe's own ones excluded from the old side.
  std::vector<map::PointId> old_pts;
  for (const OldView& v : old_views_) append_points(v.kf, old_pts);
  std::sort(old_pts.begin(), old_pts.end());
  old_pts.erase(std::unique(old_pts.begin(), old_pts.end()), old_pts.end());
  std::vector<map::PointId> new_pts;
  append_points(kf, new_pts);
  // Old points into the new camera: S_new_cand * T_cand_w; new points into the old camera:
  // S_cand_new * T_new_w.
  const Sim3d S_new_w = S_cand_new.inverse() * Sim3d::from_se3(T_w_cand.inverse());
  const Sim3d S_cand_w = S_cand_new * Sim3d::from_se3(T_w_new.inverse());
  int n_new_view = 0;
  int n_old_view = 0;
  found_new = found_share(kf, S_new_w, old_pts, K, n_new_view);
  found_old = found_share(cand, S_cand_w, new_pts, K, n_old_view);
}

double LoopCloser::usual_found_share(map::KeyframeId kf, const geometry::Pinhole& K) const {
  // The new keyframe's most covisible older keyframe of its segment: the same place seen a
  // moment before, through the map's own relative pose.
  std::array<map::CovisibleKeyframe, kMaxCovisible> covis{};
  const std::size_t nc = map_.covisible_keyframes(kf, covis);
  const std::uint64_t serial = map_.keyframe_serial(kf);
  const std::uint16_t segment = map_.keyframe_segment(kf);
  for (std::size_t k = 0; k < nc; ++k) {
    const map::KeyframeId nb = covis[k].id;
    SE3d T_w_nb;
    if (map_.keyframe_segment(nb) != segment || map_.keyframe_serial(nb) >= serial ||
        !map_.keyframe_pose(nb, T_w_nb)) {
      continue;
    }
    std::vector<map::PointId> pts;
    append_points(kf, pts);
    int in_view = 0;
    return found_share(nb, Sim3d::from_se3(T_w_nb.inverse()), pts, K, in_view);
  }
  return 0.0;  // no older neighbour: nothing to compare with (the check passes)
}

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
