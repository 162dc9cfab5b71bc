#include "loop/loop_closer.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <mutex>
#include <numeric>
#include <utility>

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
/// Nanoseconds per second (min_time_gap_s).
constexpr double kNsPerS = 1e9;

}  // namespace

LoopCloser::LoopCloser(const LoopOptions& opts, map::Map& map, std::vector<float> level_sigma2,
                       bool metric, backend::LocalBundleAdjuster* ba,
                       const RelocalizerOptions& reloc)
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
  lookalike_.assign(db_.capacity(), Lookalike{});
  if (opts_.merge_segments && opts_.merge_by_relocalization) {
    // Deterministic: no time budget (localize_against never retrieves or times out anyway).
    merge_reloc_ = std::make_unique<Relocalizer>(reloc, map_, db_, -1, true);
    reloc_tried_.reserve(static_cast<std::size_t>(opts_.max_candidates));
  }
}

LoopCloser::~LoopCloser() = default;

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
  // After a loop its own segment rests (cooldown_keyframes); merges with another are still
  // looked for: the camera that returned to a segment sees the one it left there.
  const bool cooling = any_loop_ && serial < last_loop_serial_ + static_cast<std::uint64_t>(
                                                                     opts_.cooldown_keyframes);
  if (cooling && !opts_.merge_segments) return rep;
  ++totals_.keyframes_checked;
  const std::uint16_t segment = map_.keyframe_segment(kf);
  retrieve_candidates(kf, serial, segment, cooling);
  Hypothesis best = check_candidates(kf, segment, K, rep);
  decide(kf, serial, segment, best, K, rep);
  rep.ms = platform::elapsed_ms(t0);
  lock.unlock();
  if (rep.closed) finish_closure(kf, serial, K, rep);
  totals_.max_ms = std::max(totals_.max_ms, rep.ms);
  return rep;
}

void LoopCloser::retrieve_candidates(map::KeyframeId kf, std::uint64_t serial,
                                     std::uint16_t segment, bool merges_only) {
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
    if (merges_only) continue;
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
  const auto max_c = static_cast<std::size_t>(opts_.max_candidates);
  if (opts_.merge_segments && opts_.merge_by_relocalization && ranked.size() > max_c) {
    // Keyframes sharing points with the new one fill the places first; another segment's
    // best-scored keyframe (a merge to measure) takes the last one when none is among them.
    const auto other = [&](const Candidate& c) { return map_.keyframe_segment(c.id) != segment; };
    if (std::none_of(ranked.begin(), ranked.begin() + static_cast<std::ptrdiff_t>(max_c), other)) {
      const auto it =
          std::find_if(ranked.begin() + static_cast<std::ptrdiff_t>(max_c), ranked.end(), other);
      if (it != ranked.end()) ranked[max_c - 1] = *it;
    }
  }
  if (ranked.size() > max_c) ranked.resize(max_c);
}

LoopCloser::Hypothesis LoopCloser::check_candidates(map::KeyframeId kf, std::uint16_t segment,
                                                    const geometry::Pinhole& K, LoopReport& rep) {
  // 2. Geometric check of every candidate; the one whose similarity explains the most
  //    matches wins (the first to pass may be a weaker hypothesis of a neighbouring place,
  //    made to pass by the guided search).
  Hypothesis best;
  double usual = -1.0;  // usual_found_share(kf), computed when first needed
  reloc_tried_.clear();
  best_weld_.clear();
  if (kf < lookalike_.size()) lookalike_[kf] = Lookalike{map_.keyframe_generation(kf), 0};
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
    const bool other_segment = map_.keyframe_segment(cand) != segment;
    Sim3d S_cand_new;
    int inliers = 0;
    if (m < opts_.min_matches) {
      ++totals_.rejected.few_matches;
    } else {
      inliers = ransac_sim3(kf, cand, K, S_cand_new);
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
      if (inliers < opts_.min_inliers) ++totals_.rejected.few_inliers;
    }
    // Another segment's keyframe the map-points could not measure: its keyframes can.
    int relocalized = 0;
    weld_.clear();
    const std::uint16_t cand_segment = map_.keyframe_segment(cand);
    const bool tried =
        std::find(reloc_tried_.begin(), reloc_tried_.end(), cand_segment) != reloc_tried_.end();
    if (inliers < opts_.min_inliers && other_segment && merge_reloc_ && !tried) {
      // Once per segment and keyframe: another candidate of it has nearly the same neighbours.
      reloc_tried_.push_back(cand_segment);
      // The candidate's side placed in the new keyframe's local map; else the new keyframe's
      // side in the candidate's (the thicker map is the one placed against).
      relocalized = sim3_from_relocalized_keyframes(kf, cand, K, S_cand_new, inliers);
      if (relocalized == 0) {
        Sim3d S_new_cand;
        relocalized = sim3_from_relocalized_keyframes(cand, kf, K, S_new_cand, inliers);
        if (relocalized > 0) S_cand_new = S_new_cand.inverse();
      }
      if (relocalized == 0) ++totals_.rejected.relocalized_fit;
      if (relocalized > 0) {
        matches_.clear();  // no point matches to merge: the loop's fusion joins the points
        inlier_.clear();
        m = inliers;
      }
    }
    if (relocalized == 0 && inliers < opts_.min_inliers) continue;
    // Drift bound: the correction at the new keyframe cannot exceed a fraction of the path
    // travelled since the old one (perceptual aliasing: a similar place far away). Another
    // segment's frame is unrelated: no path, no bound (the checks below still apply).
    const double drift = other_segment ? 0.0 : implied_drift(kf, cand, S_cand_new);
    const bool implausible = drift > opts_.max_drift_fraction;
    if (implausible) {
      MER_LOG_DEBUG("loop: refused, it implies %.1f %% drift", 100.0 * drift);
      ++rep.refused_drift;
      ++totals_.rejected.drift;
      // A look-alike only if it passes the other checks: then the view is not unique.
      if (inliers <= rep.lookalike_inliers) continue;
    } else if (inliers <= best.inliers) {
      continue;
    }
    // Both ways: the similarity must find the surroundings too, not only what the two places
    // share (a repeated poster matches its copy; the walls around it do not).
    double found_new = 0.0;
    double found_old = 0.0;
    int in_new_view = 0;
    int in_old_view = 0;
    found_both_ways(kf, cand, S_cand_new, K, found_new, found_old, in_new_view, in_old_view);
    if (usual < 0.0) usual = usual_found_share(kf, K);
    MER_LOG_DEBUG(
        "loop: found both ways: %.2f of the %d old points in the new view, %.2f of the %d "
        "new in the old view (%.2f with its own neighbour)",
        found_new, in_new_view, found_old, in_old_view, usual);
    // Measured from keyframes: the placed side's keypoints found the other side's points; a
    // side with too few points in the other's view (min_matches: a thin segment) is not
    // counted, but one side must be.
    double found = std::min(found_new, found_old);
    if (relocalized > 0) {
      const bool new_ok = in_new_view >= opts_.min_matches;
      const bool old_ok = in_old_view >= opts_.min_matches;
      found = new_ok && old_ok ? found : new_ok ? found_new : old_ok ? found_old : 0.0;
    }
    if (found < opts_.min_found_fraction * usual) {
      if (!implausible) {
        ++rep.refused_found;
        ++totals_.rejected.not_found;
      }
      continue;
    }
    if (implausible) {
      // Every check but the drift bound passed: a look-alike of this view elsewhere.
      rep.lookalike_inliers = inliers;
      if (kf < lookalike_.size() && inliers > lookalike_[kf].inliers) {
        lookalike_[kf].inliers = inliers;
        lookalike_[kf].place = cand;
        lookalike_[kf].place_generation = map_.keyframe_generation(cand);
      }
      MER_LOG_DEBUG("loop: a look-alike: %d inliers", inliers);
      continue;
    }
    best = Hypothesis{cand,      m,         inliers,     S_cand_new, drift,
                      found_new, found_old, c.covisible, usual,      relocalized};
    best_matches_.swap(matches_);
    best_inlier_.swap(inlier_);
    best_old_views_.swap(old_views_);
    best_weld_.swap(weld_);
  }
  // Ambiguity: a look-alike of this view (found by this keyframe or one that sees what it
  // sees) about as strong as the loop leaves the place it matched a guess.
  if (best.cand != map::kNoId && opts_.ambiguity_ratio > 0.0) {
    best.rival = strongest_lookalike(kf, best.cand);
    if (best.rival > 0 && best.rival >= opts_.ambiguity_ratio * best.inliers) {
      MER_LOG_DEBUG("loop: refused as ambiguous: %d inliers, a look-alike with %d", best.inliers,
                    best.rival);
      ++rep.refused_ambiguous;
      ++totals_.rejected.ambiguous;
      best = Hypothesis{};
    }
  }
  return best;
}

int LoopCloser::strongest_lookalike(map::KeyframeId kf, map::KeyframeId loop_cand) const {
  // A slot counts only for the keyframe it was recorded for, and only when its look-alike
  // is of another place than the loop's.
  const auto of = [&](map::KeyframeId id) {
    if (id >= lookalike_.size()) return 0;
    const Lookalike& l = lookalike_[id];
    if (l.inliers == 0 || l.generation != map_.keyframe_generation(id) ||
        l.place_generation != map_.keyframe_generation(l.place)) {
      return 0;
    }
    const bool same_place = l.place == loop_cand ||
                            map_.covisibility_weight(l.place, loop_cand) > 0 ||
                            map_.covisibility_weight(loop_cand, l.place) > 0;
    return same_place ? 0 : l.inliers;
  };
  int strongest = of(kf);
  std::array<map::CovisibleKeyframe, kMaxCovisible> covis{};
  const std::size_t nc = map_.covisible_keyframes(kf, covis);
  for (std::size_t k = 0; k < nc; ++k) {
    if (covis[k].weight >= static_cast<std::uint32_t>(opts_.min_edge_weight)) {
      strongest = std::max(strongest, of(covis[k].id));
    }
  }
  return strongest;
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
      weld_.swap(best_weld_);
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
      rep.rival_inliers = best.rival;
      if (map_.keyframe_segment(cand) != segment) {
        merge_segments(kf, cand, best.sim, rep);
        rep.merge_relocalized = best.relocalized;
        // Refused by the map (the tracker discarded a segment meanwhile, lock-free): the two
        // are still in unrelated frames, nothing to correct.
        if (rep.merged_from == map::kNoSegment) {
          ++totals_.rejected.merge_refused;
          return;
        }
      }
      rep.merged_points = correct(kf, cand, best.sim, K, rep);
      if (rep.merged_from != map::kNoSegment) rep.merged_points += weld(rep);
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
    if (rep.merge_relocalized > 0) ++totals_.merges_by_relocalization;
    if (totals_.merges.size() < kMaxLoopEvents) {
      totals_.merges.push_back(SegmentMergeEvent{
          map_.keyframe_seq(kf), map_.keyframe_t_ns(kf), rep.loop_seq, rep.merged_from,
          rep.merged_into, rep.merge_keyframes, rep.inliers, rep.merge_similarity});
    }
  }
  totals_.merged_points += static_cast<std::uint64_t>(rep.merged_points);
  totals_.last_loop = rep;
  if (totals_.closures.size() < kMaxLoopEvents) {
    totals_.closures.push_back(LoopClosureEvent{
        map_.keyframe_seq(kf), map_.keyframe_t_ns(kf), rep.loop_seq, rep.loop_t_ns,
        map_.keyframe_segment(kf), rep.inliers, rep.found_new, rep.found_old, rep.found_usual,
        rep.rival_inliers, rep.drift, rep.connected, rep.similarity});
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
                                 const geometry::Pinhole& K, double& found_new, double& found_old,
                                 int& in_new_view, int& in_old_view) const {
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
  in_new_view = n_new_view;
  in_old_view = n_old_view;
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

}  // namespace mer::loop
