#pragma once
/// @file loop_closer.h
/// Loop closure: when the camera comes back to a place it mapped long ago, the drift
/// accumulated in between (position, heading and, in monocular mode, scale) shows as a
/// similarity between the new keyframe and the old one. The loop closer finds it and spreads
/// it over the keyframes of the loop.
///
///  1. Retrieval (KeyframeDatabase, keyframe_database.h): every keyframe's descriptors give
///     sorted keys (kKeyTables subsets of kKeyBits bits, as in locality-sensitive hashing),
///     indexed key -> keyframes. Candidates for a new keyframe are the
///     keyframes at least `min_keyframe_gap` keyframes older: those it already shares points
///     with (tracking found their points again) first, then those whose score (shared keys,
///     each weighted by log(keyframes / keyframes with the key)) is at least
///     `min_key_score_ratio` times the median, best first; `max_candidates` are checked.
///  2. Geometric check: the new keyframe's map-points are matched by descriptor (nearest
///     neighbour, ratio test, one-to-one) to the points of the candidate and its old
///     covisible neighbours; RANSAC over 3-point Umeyama fits finds the similarity S_cand_new
///     (scale fixed to 1 when the map is metric, RGB-D) whose transfer reprojects each match
///     onto its keypoint in both keyframes (chi-square gate at the keypoint's pyramid sigma).
///     A similarity with `min_inliers` is refined on the reprojection errors of its inliers
///     in both keyframes (`refine_iterations`; the points' depth, which the 3D fit weighs,
///     is their least certain part). `min_inliers` must agree; a loop implying more than
///     `max_drift_fraction` of the path since the candidate is refused (a similar place
///     elsewhere); one that passes every check but that bound is a look-alike of the view, and
///     a loop weaker than 1 / `ambiguity_ratio` times the strongest look-alike of its view
///     (found by the new keyframe or a keyframe seeing the same, of another place than the
///     loop's) is refused as ambiguous; and
///     `consistent_checks` keyframes in a row must find the same place. A
///     candidate of another map segment whose map-points are too few for this (a segment that
///     was being lost) is measured from its keyframes instead (`merge_by_relocalization`,
///     loop_merge_relocalized.cpp): they are relocalized against the new keyframe's local map
///     and the similarity between the two worlds is fitted to their poses.
///  3. Correction: the new keyframe and its recent covisible neighbours are moved rigidly
///     onto the loop; then a Sim(3) pose graph over every keyframe (Ceres; edges: consecutive
///     keyframes and covisibility pairs with their relative similarity before the correction,
///     loop edges between the corrected neighbourhood and the candidate's, and the edges of
///     earlier loops; the candidate held fixed) spreads the correction. Every map-point moves
///     with its reference keyframe, keyframe depths scale with their keyframe, the matched
///     points are merged, the old side's points are fused into the corrected keyframes
///     (observations of free keypoints, merges of duplicates), and the map records the
///     correction of the newest keyframe (Map::publish_correction) for the tracker. A bounded
///     full-graph bundle adjustment (`full_ba_iterations`) follows.
///
/// Threading: runs on its own thread, the loop thread (lowest priority), on each keyframe
/// after the back end's local BA and culling (lockstep: inline, after them). Holds the map's
/// writer lock from retrieval to publication; the full BA (its own adjuster in threaded
/// mode) takes it itself to read the map and to write back, not while it solves, and a new
/// keyframe pre-empts it. A local BA that ran meanwhile leaves the keyframes and points the
/// loop moved as the loop left them (local_ba.h).

#include <array>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "core/chi2.h"
#include "core/options.h"
#include "geometry/camera_model.h"
#include "geometry/sim3.h"
#include "loop/keyframe_database.h"
#include "loop/relocalizer.h"
#include "map/map.h"

namespace mer::backend {
class LocalBundleAdjuster;
}  // namespace mer::backend

namespace mer::loop {

/// Options of loop closure (config section `loop`).
struct LoopOptions {
  bool enabled = true;
  int min_keyframe_gap = 20;
  double min_key_score_ratio = 1.2;
  int max_candidates = 3;
  int max_descriptor_distance = 50;
  double ratio = 0.8;
  int min_matches = 20;
  int min_inliers = 20;
  int guided_min_inliers = 10;
  int ransac_iterations = 300;
  int refine_iterations = 10;
  double inlier_chi2 = kChi2TwoDof95;
  int min_edge_weight = 15;
  int pose_graph_iterations = 20;
  double fuse_radius_px = 6.0;
  int full_ba_iterations = 30;
  int cooldown_keyframes = 5;
  int consistent_checks = 1;
  int merge_consistent_checks = 1;
  double max_drift_fraction = 0.2;
  bool exclude_connected = false;
  double min_time_gap_s = 3.0;
  double min_found_fraction = 0.3;
  double ambiguity_ratio = 0.5;
  bool merge_segments = true;
  bool merge_by_relocalization = true;
  int merge_relocalize_keyframes = 8;
  int merge_min_keyframes = 3;
  double merge_max_scale_uncertainty = 0.1;
  double merge_max_pose_residual_deg = 3.0;
  int seed = 1;

  template <class V>
  void visit(V& v) {
    v.field("enabled", enabled, "look for loops at every new keyframe");
    v.field("min_keyframe_gap", min_keyframe_gap,
            "loop candidates are at least this many keyframes older than the new one",
            options::Range<int>{2, 100000});
    v.field("min_key_score_ratio", min_key_score_ratio,
            "retrieval score a candidate needs, as a multiple of the median over the old "
            "keyframes; the score is the number of distinct descriptor keys (4 tables of 16 "
            "bits) shared with the new keyframe, each weighted by log(keyframes / keyframes "
            "with that key)",
            options::Range<double>{0.0, 1e9});
    v.field("max_candidates", max_candidates,
            "candidates checked geometrically per keyframe, most shared keys first",
            options::Range<int>{1, 100});
    v.field("max_descriptor_distance", max_descriptor_distance,
            "Hamming distance of a point match, at most", options::Range<int>{0, 256});
    v.field("ratio", ratio, "best / second-best descriptor distance of a match, at most",
            options::Range<double>{0.1, 1.0});
    v.field("min_matches", min_matches, "point matches needed before RANSAC",
            options::Range<int>{3, 100000});
    v.field("min_inliers", min_inliers, "matches the loop similarity must explain",
            options::Range<int>{3, 100000});
    v.field("guided_min_inliers", guided_min_inliers,
            "a RANSAC similarity with at least this many inliers projects the old keyframes' "
            "points into the new keyframe (fuse_radius_px, max_descriptor_distance) to find the "
            "matches the descriptor-only search missed, and is refit on all of them before "
            "min_inliers is checked (0: off)",
            options::Range<int>{0, 100000});
    v.field("ransac_iterations", ransac_iterations, "3-point RANSAC samples",
            options::Range<int>{1, 1000000});
    v.field("refine_iterations", refine_iterations,
            "Levenberg-Marquardt iterations refining a supported similarity on its inliers' "
            "reprojection errors in both keyframes (robust, keypoint sigmas) instead of their "
            "3D positions, whose depth errors the 3D fit weighs most; the inliers are counted "
            "again and the refinement kept when at least as many agree (0: off)",
            options::Range<int>{0, 1000});
    v.field("inlier_chi2", inlier_chi2,
            "squared transfer error / keypoint sigma^2 of an inlier, in both keyframes",
            options::Range<double>{0.1, 1000.0});
    v.field("min_edge_weight", min_edge_weight,
            "shared points a covisibility edge of the pose graph needs",
            options::Range<int>{1, 100000});
    v.field("fuse_radius_px", fuse_radius_px,
            "loop fusion: an old point projected into a corrected keyframe is matched to the "
            "keypoints within this radius, in sigmas of the keypoint's level (1 px at level 0)",
            options::Range<double>{0.1, 1000.0});
    v.field("pose_graph_iterations", pose_graph_iterations,
            "Levenberg-Marquardt iterations of the Sim(3) pose graph",
            options::Range<int>{1, 10000});
    v.field("full_ba_iterations", full_ba_iterations,
            "full-graph bundle adjustment iterations after a loop (0: none; a new keyframe "
            "pre-empts it)",
            options::Range<int>{0, 10000});
    v.field("max_drift_fraction", max_drift_fraction,
            "a loop whose correction would move what the new keyframe sees by more than this "
            "fraction of the path travelled since the old keyframe is refused (a similar place "
            "elsewhere); the move is the camera centre's shift plus the correction's rotation "
            "angle times the keyframe's median scene depth",
            options::Range<double>{0.0, 1e6});
    v.field("exclude_connected", exclude_connected,
            "keyframes that share map-points with the new one (joined to it through the "
            "covisibility graph already) are never loop candidates");
    v.field("min_time_gap_s", min_time_gap_s,
            "loop candidates were made at least this long before the new keyframe",
            options::Range<double>{0.0, 1e6});
    v.field("min_found_fraction", min_found_fraction,
            "a loop's similarity must be confirmed both ways: of the old window's map-points "
            "that it projects into the new keyframe's image, and of the new keyframe's that it "
            "projects into the old one's, the share that finds a keypoint with a matching "
            "descriptor (fuse_radius_px, max_descriptor_distance) must be at least this "
            "fraction of the usual share, that of the new keyframe's points in its own most "
            "covisible older keyframe; a look-alike place matches its copy but not the "
            "surroundings (0: not checked)",
            options::Range<double>{0.0, 1.0});
    v.field("ambiguity_ratio", ambiguity_ratio,
            "a loop is refused as ambiguous when the new keyframe, or a keyframe sharing at "
            "least min_edge_weight points with it, found a similarity to another place (not the "
            "loop's old keyframe nor one sharing points with it) that passed every check but "
            "the drift bound with at least this fraction of the loop's inliers: the view looks "
            "the same elsewhere (panels repeating along a hall), so the place it matched within "
            "the bound may be a copy too (0: off)",
            options::Range<double>{0.0, 1e6});
    v.field("merge_segments", merge_segments,
            "keyframes of other map segments (started after a lost spell) are candidates too, "
            "without the time and keyframe gaps: a loop onto one moves the newer segment into "
            "the older one's frame by the loop's similarity and joins the two (the drift bound "
            "does not apply between frames; the other checks do)");
    v.field("consistent_checks", consistent_checks,
            "keyframes in a row (at most 3 apart) whose geometric check must find the same old "
            "place (the candidate or a keyframe covisible with it) before the loop is corrected",
            options::Range<int>{1, 100});
    v.field("merge_by_relocalization", merge_by_relocalization,
            "a candidate of another segment with too few map-points for the 3D similarity (a "
            "segment that was being lost keeps few) is measured from its keyframes instead: "
            "the merge_relocalize_keyframes of its segment made nearest to it are relocalized "
            "against the "
            "new keyframe's local map (the relocalizer's matching, PnP and refinement, "
            "section relocalization), and the similarity fitted to those placed (rotation "
            "from their orientations, scale and translation from their positions) is checked "
            "both ways as any loop's");
    v.field("merge_relocalize_keyframes", merge_relocalize_keyframes,
            "merge_by_relocalization: keyframes of the candidate's segment tried, the candidate "
            "and those made nearest to it",
            options::Range<int>{1, 64});
    v.field("merge_min_keyframes", merge_min_keyframes,
            "merge_by_relocalization: keyframes placed that the similarity needs, at least",
            options::Range<int>{3, 64});
    v.field("merge_max_scale_uncertainty", merge_max_scale_uncertainty,
            "merge_by_relocalization: the similarity's scale uncertainty (standard deviation of "
            "its logarithm), at most; the scale is measured twice, by the spread of the placed "
            "keyframes' centres in both frames and by the depth ratios of the map-points both "
            "segments hold for the same keypoints, and the two are combined by their "
            "uncertainties; keyframes that disagree most are dropped while more than "
            "merge_min_keyframes remain",
            options::Range<double>{0.0, 10.0});
    v.field("merge_max_pose_residual_deg", merge_max_pose_residual_deg,
            "merge_by_relocalization: each placed keyframe's pose after the similarity within "
            "this of its relocalized one: its orientation, and its position as the angle the "
            "error subtends at its median scene depth, degrees",
            options::Range<double>{0.0, 180.0});
    v.field("merge_consistent_checks", merge_consistent_checks,
            "consistent_checks for a match onto another segment's keyframe: no drift bound "
            "holds between two world frames, and a merge joins them for good",
            options::Range<int>{1, 100});
    v.field("cooldown_keyframes", cooldown_keyframes,
            "keyframes after a closed loop before the next loop in its segment is looked for "
            "(merges with other segments are looked for meanwhile)",
            options::Range<int>{0, 100000});
    v.field("seed", seed, "RANSAC sampling seed", options::Range<int>{0, 1 << 30});
  }
};

/// What one spin did.
struct LoopReport {
  int candidates = 0;         ///< candidates checked geometrically
  int pending = 0;            ///< a check passed, waiting for the next keyframes to agree
  int refused_drift = 0;      ///< checks passed but refused by max_drift_fraction
  int refused_found = 0;      ///< checks passed but refused by min_found_fraction
  int refused_ambiguous = 0;  ///< the best one refused by ambiguity_ratio
  int lookalike_inliers = 0;  ///< the strongest look-alike (drift-refused) this keyframe found
  bool closed = false;        ///< a loop was found and corrected
  map::KeyframeId loop_keyframe = map::kNoId;  ///< the old keyframe it closed on
  std::uint64_t loop_seq = 0;                  ///< its frame
  std::int64_t loop_t_ns = 0;                  ///< its timestamp
  int matches = 0;             ///< point matches with the loop keyframe (best candidate)
  int inliers = 0;             ///< of those, explained by the similarity
  double found_new = 0.0;      ///< share of the old window's points in the new view found
  double found_old = 0.0;      ///< share of the new keyframe's points in the old view found
  bool connected = false;      ///< the old keyframe shared points with the new one
  double drift = 0.0;          ///< the correction over the path (max_drift_fraction)
  double found_usual = 0.0;    ///< the new keyframe's share with its own older neighbour
  int rival_inliers = 0;       ///< the strongest look-alike of its view (ambiguity_ratio)
  geometry::Sim3d similarity;  ///< the loop's similarity: new keyframe's camera -> old one's
  double scale = 1.0;          ///< scale of the correction at the new keyframe
  double shift = 0.0;          ///< translation of the new keyframe by the correction, map units
  int keyframes = 0;           ///< keyframes in the pose graph
  int merged_points = 0;       ///< duplicate points merged
  int fused_observations = 0;  ///< old points observed by window keyframes through fusion
  double ms = 0.0;             ///< wall time, full BA excluded
  double full_ba_ms = 0.0;
  std::uint16_t merged_from = map::kNoSegment;  ///< the loop joined this segment ...
  std::uint16_t merged_into = map::kNoSegment;  ///< ... to this one (merge_segments)
  int merge_keyframes = 0;                      ///< keyframes the merge moved
  int merge_relocalized = 0;  ///< keyframes the merge's similarity was fitted to (0: 3D matches)
  geometry::Sim3d merge_similarity;  ///< world of merged_from -> world of merged_into
};

/// Two map segments joined by a loop between them (merge_segments).
struct SegmentMergeEvent {
  std::uint64_t seq = 0;          ///< frame of the keyframe that found the other segment
  std::int64_t t_ns = 0;          ///< its timestamp
  std::uint64_t loop_seq = 0;     ///< frame of the keyframe it matched
  std::uint16_t from = 0;         ///< the segment that moved (the newer one) ...
  std::uint16_t into = 0;         ///< ... into this one's frame
  int keyframes = 0;              ///< keyframes moved
  int inliers = 0;                ///< matches the similarity explains
  geometry::Sim3d sim_into_from;  ///< world of `from` -> world of `into`
};

/// A closed loop, for ground-truth audits: the two keyframes and the similarity the loop
/// found between them (before the correction spread it).
struct LoopClosureEvent {
  std::uint64_t seq = 0;        ///< frame of the new keyframe
  std::int64_t t_ns = 0;        ///< its timestamp
  std::uint64_t loop_seq = 0;   ///< frame of the old keyframe
  std::int64_t loop_t_ns = 0;   ///< its timestamp
  std::uint16_t segment = 0;    ///< the segment both belong to
  int inliers = 0;              ///< matches the similarity explains
  double found_new = 0.0;       ///< LoopReport::found_new
  double found_old = 0.0;       ///< LoopReport::found_old
  double found_usual = 0.0;     ///< LoopReport::found_usual
  int rival_inliers = 0;        ///< LoopReport::rival_inliers
  double drift = 0.0;           ///< the correction over the path (max_drift_fraction)
  bool connected = false;       ///< LoopReport::connected
  geometry::Sim3d sim_old_new;  ///< new keyframe's camera -> old one's, old map units
};

/// Loop hypotheses refused, by reason (summary.json `loop.rejected`).
struct LoopRejections {
  std::uint64_t few_matches = 0;      ///< a candidate with fewer than min_matches point matches
  std::uint64_t few_inliers = 0;      ///< no similarity explained min_inliers of them
  std::uint64_t drift = 0;            ///< the correction was implausible (max_drift_fraction)
  std::uint64_t not_found = 0;        ///< not confirmed both ways (min_found_fraction)
  std::uint64_t ambiguous = 0;        ///< a look-alike elsewhere as strong (ambiguity_ratio)
  std::uint64_t inconsistent = 0;     ///< seen once, not again by the next keyframes
  std::uint64_t merge_refused = 0;    ///< the map refused the merge (a segment discarded meanwhile)
  std::uint64_t relocalized_fit = 0;  ///< merge_by_relocalization, both ways: too few keyframes
                                      ///< placed, or their similarity did not hold
};

/// Closed loops kept per run, at most (later ones are only counted).
inline constexpr std::size_t kMaxLoopEvents = 1024;

/// Totals over a run (summary.json `loop`).
struct LoopTotals {
  std::uint64_t keyframes_checked = 0;   ///< spins that looked for a loop
  std::uint64_t candidates_checked = 0;  ///< geometric checks
  std::uint64_t loops_closed = 0;
  std::uint64_t merged_points = 0;
  double max_ms = 0.0;  ///< longest spin, full BA excluded
  double max_full_ba_ms = 0.0;
  LoopReport last_loop;                        ///< the last loop closed
  std::vector<LoopClosureEvent> closures;      ///< every loop closed (at most kMaxLoopEvents)
  LoopRejections rejected;                     ///< refusals by reason
  std::uint64_t excluded_connected = 0;        ///< candidates skipped: they share points (counted
                                               ///< per keyframe checked)
  std::uint64_t segments_merged = 0;           ///< loops that joined two segments (of loops_closed)
  std::uint64_t merges_by_relocalization = 0;  ///< of segments_merged: measured from keyframes
                                               ///< relocalized (merge_by_relocalization)
  std::vector<SegmentMergeEvent> merges;       ///< every merge (at most kMaxLoopEvents)
};

/// Loop-closure stage: `spin_once(new keyframe) -> LoopReport`.
class LoopCloser {
 public:
  /// `metric`: the map has a known scale (RGB-D): loops are rigid. `ba` runs the full-graph
  /// optimization after a loop (may be null: none).
  /// `reloc`: the relocalizer's options, for placing another segment's keyframes
  /// (merge_by_relocalization).
  LoopCloser(const LoopOptions& opts, map::Map& map, std::vector<float> level_sigma2, bool metric,
             backend::LocalBundleAdjuster* ba, const RelocalizerOptions& reloc = {});
  ~LoopCloser();
  LoopCloser(const LoopCloser&) = delete;
  LoopCloser& operator=(const LoopCloser&) = delete;

  /// Looks for a loop closing at keyframe kf and corrects the map when one is found. Takes the
  /// map's writer lock itself.
  LoopReport spin_once(map::KeyframeId kf, const geometry::Pinhole& K);

  const LoopTotals& totals() const { return totals_; }

  /// The keyframe database retrieval uses (refreshed by spin_once under the writer lock).
  /// Lockstep callers may share it with a Relocalizer; threaded ones give that its own.
  KeyframeDatabase& database() { return db_; }

 private:
  /// A retrieved loop candidate (retrieve_candidates).
  struct Candidate {
    bool covisible = false;  ///< it shares points with the new keyframe
    double score = 0.0;      ///< shared points, or the key score
    map::KeyframeId id = map::kNoId;
  };
  /// The best-supported loop of one check (check_candidates).
  struct Hypothesis {
    map::KeyframeId cand = map::kNoId;
    int matches = 0;
    int inliers = 0;
    geometry::Sim3d sim;  ///< S_cand_new
    double drift = 0.0;
    double found_new = 0.0;
    double found_old = 0.0;
    bool connected = false;  ///< it shared points with the new keyframe
    double usual = 0.0;      ///< usual_found_share of the new keyframe
    int relocalized = 0;     ///< keyframes its similarity was fitted to (0: 3D matches)
    int rival = 0;           ///< the strongest look-alike of the view (ambiguity_ratio)
  };
  // The steps of spin_once, in order.
  /// Retrieval into ranked_: old keyframes the new one shares points with (by shared points),
  /// then those whose key score passes the bar (by score), at most max_candidates.
  /// `merges_only` (a loop's cooldown): other segments' keyframes only.
  void retrieve_candidates(map::KeyframeId kf, std::uint64_t serial, std::uint16_t segment,
                           bool merges_only);
  /// Geometric check of every candidate; the one whose similarity explains the most matches
  /// and passes the drift and both-ways checks wins (cand kNoId: none).
  Hypothesis check_candidates(map::KeyframeId kf, std::uint16_t segment, const geometry::Pinhole& K,
                              LoopReport& rep);
  /// Consistency over consecutive keyframes, then the merge and correction of a loop seen
  /// often enough (a merge re-expresses best.sim in the joined map's units).
  void decide(map::KeyframeId kf, std::uint64_t serial, std::uint16_t segment, Hypothesis& best,
              const geometry::Pinhole& K, LoopReport& rep);
  /// After a closure, without the writer lock: the full BA and the totals.
  void finish_closure(map::KeyframeId kf, std::uint64_t serial, const geometry::Pinhole& K,
                      LoopReport& rep);
  std::vector<Candidate> ranked_;  // retrieve_candidates' result
  /// Keyframes of the candidate's neighbourhood tied to the corrected one by loop edges.
  static constexpr std::size_t kLoopNeighbours = 6;
  /// Covisible keyframes read per keyframe (map.max_covisible_per_keyframe bounds it anyway).
  static constexpr std::size_t kMaxCovisible = 64;
  struct Match {
    std::uint32_t kp_new = 0;
    std::uint32_t kp_old = 0;
    map::PointId p_new = map::kNoId;
    map::PointId p_old = map::kNoId;
    std::uint32_t old_view = 0;  ///< index in old_views_ of the keyframe kp_old belongs to
  };
  /// An old keyframe whose points are matched (the candidate and its old neighbours).
  struct OldView {
    map::KeyframeId kf = map::kNoId;
    SE3d T_view_cand = SE3d::Identity();  ///< candidate camera -> this keyframe's camera
  };
  std::vector<OldView> old_views_;
  // The best-supported candidate's matches, inlier mask and old views, while the others are
  // checked.
  std::vector<Match> best_matches_;
  std::vector<std::uint8_t> best_inlier_;
  std::vector<OldView> best_old_views_;
  int match_points(map::KeyframeId kf, map::KeyframeId cand);
  /// How far the loop's correction moves what the new keyframe sees (the centre's shift plus
  /// the rotation angle times the median scene depth), over the path travelled since the
  /// candidate.
  double implied_drift(map::KeyframeId kf, map::KeyframeId cand,
                       const geometry::Sim3d& S_cand_new) const;
  /// Guided check of S_cand_new both ways: the old views' points projected into the new
  /// keyframe (found_new) and the new keyframe's points projected into the candidate
  /// (found_old); each is the share of the points in view that find a keypoint within
  /// fuse_radius_px sigmas with a descriptor within max_descriptor_distance. `in_new_view`:
  /// the old views' points in the new keyframe's view; `in_old_view`: the new keyframe's in the
  /// candidate's.
  void found_both_ways(map::KeyframeId kf, map::KeyframeId cand, const geometry::Sim3d& S_cand_new,
                       const geometry::Pinhole& K, double& found_new, double& found_old,
                       int& in_new_view, int& in_old_view) const;
  /// Appends kf's live, not-bad map points (one per associated keypoint) to `out`.
  void append_points(map::KeyframeId kf, std::vector<map::PointId>& out) const;
  /// Median depth of kf's map points in the camera T_c_w (0 without any).
  double keyframe_median_depth(map::KeyframeId kf, const SE3d& T_c_w) const;
  /// The share (as found_share) of the new keyframe's points found in its most covisible
  /// older keyframe of the same segment, placed by the map's poses: what the same place looks
  /// like in this scene. 0 without such a keyframe.
  double usual_found_share(map::KeyframeId kf, const geometry::Pinhole& K) const;
  /// Of the map points `pts` (world, camera frame T_c_w), the share in view of keyframe `view`
  /// that find a keypoint there (as found_both_ways); `in_view` gets how many were in view.
  double found_share(map::KeyframeId view, const geometry::Sim3d& S_view_w,
                     const std::vector<map::PointId>& pts, const geometry::Pinhole& K,
                     int& in_view) const;
  int ransac_sim3(map::KeyframeId kf, map::KeyframeId cand, const geometry::Pinhole& K,
                  geometry::Sim3d& S_cand_new);
  /// merge_by_relocalization: the keyframes of cand's segment made nearest to it, relocalized
  /// against kf's local map; the similarity fitted to those placed, as S_cand_new (cand's
  /// camera from kf's). (The caller also swaps the two, to place kf's side in cand's map.) Returns
  /// how many keyframes it rests on (0: refused); `inliers` gets the candidate's refined
  /// relocalization inliers (or the best placed keyframe's).
  int sim3_from_relocalized_keyframes(map::KeyframeId kf, map::KeyframeId cand,
                                      const geometry::Pinhole& K, geometry::Sim3d& S_cand_new,
                                      int& inliers);
  /// Camera-frame positions of the matches' points (x_new_, x_old_); drops the matches whose
  /// points are gone or behind a camera. False when a pose is missing.
  bool match_positions(map::KeyframeId kf, map::KeyframeId cand);
  /// Matches of matches_ that S_cand_new explains (reprojection in both keyframes); their mask
  /// in `mask` when given.
  int count_sim3_inliers(map::KeyframeId kf, const geometry::Sim3d& S_cand_new,
                         const geometry::Pinhole& K, std::vector<std::uint8_t>* mask) const;
  /// Refits S_cand_new on its inliers until the set settles; inlier_ holds them. Returns
  /// their count.
  int refit_sim3(map::KeyframeId kf, const geometry::Pinhole& K, geometry::Sim3d& S_cand_new);
  /// Refines S_cand_new on the inliers' reprojection errors in both keyframes
  /// (refine_iterations); keeps it when at least as many matches agree, inlier_ then holding
  /// them. Returns the inlier count (`inliers`, the current count, when not kept).
  int refine_sim3(map::KeyframeId kf, const geometry::Pinhole& K, int inliers,
                  geometry::Sim3d& S_cand_new);
  /// Guided search: the old views' points not matched yet, moved into the new keyframe by
  /// S_cand_new, matched to the new keyframe's unmatched map-point keypoints within
  /// fuse_radius_px sigmas; appended to matches_. Returns how many.
  int guided_matches(map::KeyframeId kf, map::KeyframeId cand, const geometry::Sim3d& S_cand_new,
                     const geometry::Pinhole& K);
  /// kf and cand are of different segments: moves the newer segment into the older one's
  /// frame (Map::merge_segment) by the similarity between the two cameras; rep says which.
  /// After a merge S_cand_new is re-expressed in the joined map's units (its scale was the
  /// ratio of the two segments' scales, now applied by the merge: it becomes 1), so that the
  /// loop correction that follows does not apply it a second time.
  void merge_segments(map::KeyframeId kf, map::KeyframeId cand, geometry::Sim3d& S_cand_new,
                      LoopReport& rep);
  /// Corrects the loop's segment (loop_correction.cpp): the pose graph of its keyframes with
  /// the loop's edges, solved with the candidate fixed, applied to keyframes and points; the
  /// matched points merged and the loop's points fused. Returns the points merged.
  int correct(map::KeyframeId kf, map::KeyframeId cand, const geometry::Sim3d& S_cand_new,
              const geometry::Pinhole& K, LoopReport& rep);
  struct PoseGraph;  // loop_correction.cpp
  /// The nodes (the segment's live keyframes), the window moved with the new keyframe by the
  /// loop's correction and the solve's start; false when either keyframe is not a node.
  bool load_pose_graph(map::KeyframeId kf, map::KeyframeId cand, const geometry::Sim3d& S_cand_new,
                       PoseGraph& g) const;
  /// Sequential, covisibility and earlier loops' edges, the loop edges (remembered for the
  /// next loops) and the solve.
  void solve_pose_graph(PoseGraph& g);
  /// The solved poses into the map (depths scaled), points moved with their reference
  /// keyframe, matched points merged, loop fusion, the correction published. Returns the
  /// points merged.
  int apply_correction(PoseGraph& g, map::KeyframeId cand, const geometry::Pinhole& K,
                       LoopReport& rep);
  float sigma2(const features::Keypoint& k) const;
  /// Projects the points of `old_kfs` into each of `window` (corrected poses) and matches them
  /// to keypoints by descriptor (chi-square gate at the keypoint's sigma): a free keypoint
  /// gets an observation of the old point, a keypoint tracking another point has its point
  /// merged into the old one. Returns the points merged.
  int fuse_loop(const std::vector<map::KeyframeId>& window,
                const std::vector<map::KeyframeId>& old_kfs, const geometry::Pinhole& K,
                LoopReport& rep);

  /// A loop edge of an earlier loop (ids checked by generation).
  struct LoopEdge {
    map::KeyframeId a = map::kNoId;
    map::Generation gen_a = map::kNoGeneration;
    map::KeyframeId b = map::kNoId;
    map::Generation gen_b = map::kNoGeneration;
  };
  std::vector<LoopEdge> loop_edges_;
  /// A loop that passed the geometric check and waits to be seen again (consistent_checks).
  struct Pending {
    map::KeyframeId cand = map::kNoId;
    std::uint64_t serial = 0;  ///< of the keyframe that saw it last
    int count = 0;             ///< consecutive agreeing checks so far
  };
  Pending pending_;
  LoopOptions opts_;
  map::Map& map_;
  std::vector<float> level_sigma2_;
  bool metric_;
  double max_scale_ = 0.0;  // scale bound of the candidate being checked (set per candidate)
  backend::LocalBundleAdjuster* ba_;
  KeyframeDatabase db_;
  std::unique_ptr<Relocalizer> merge_reloc_;  ///< merge_by_relocalization (db_ unused by it)
  std::vector<std::uint16_t> reloc_tried_;    ///< segments measured so in this check
  /// Per keyframe slot, the strongest look-alike its checks found (a similarity that passed
  /// every check but the drift bound, ambiguity_ratio): its inliers and the old keyframe it
  /// matched; and the slot's occupant they are of (ids are reused; a keyframe the loop thread
  /// skipped is never reset).
  struct Lookalike {
    map::Generation generation = map::kNoGeneration;
    int inliers = 0;
    map::KeyframeId place = map::kNoId;  ///< the old keyframe the look-alike matched
    map::Generation place_generation = map::kNoGeneration;
  };
  std::vector<Lookalike> lookalike_;
  /// The strongest look-alike found by kf or a keyframe sharing min_edge_weight points with
  /// it, of another place than `loop_cand` (neither it nor a keyframe sharing points with it:
  /// a loop implying too much drift onto the loop's own place is no rival of it).
  int strongest_lookalike(map::KeyframeId kf, map::KeyframeId loop_cand) const;
  /// A placed keyframe's keypoint and the other segment's point it was matched to
  /// (merge_by_relocalization): observations added once the two segments are one.
  struct Weld {
    map::KeyframeId kf = map::kNoId;
    std::uint32_t kp = 0;
    map::PointId point = map::kNoId;
  };
  std::vector<Weld> weld_;       // the hypothesis being checked
  std::vector<Weld> best_weld_;  // the best one so far
  /// After a merge measured from keyframes: each placed keyframe observes the points its
  /// relocalization matched (a keypoint holding a point of its own merges it into that one),
  /// so that the joined map's optimizations hold the two sides together. Returns the points
  /// merged; rep.fused_observations counts the observations added.
  int weld(LoopReport& rep);
  std::uint64_t last_loop_serial_ = 0;
  bool any_loop_ = false;
  std::uint32_t rng_ = 1;
  // Scratch.
  std::vector<Match> matches_;
  std::vector<std::uint8_t> inlier_;
  std::vector<Eigen::Vector3d> x_new_;  // matched points in the new keyframe's camera
  std::vector<Eigen::Vector3d> x_old_;  // in the loop keyframe's camera
  LoopTotals totals_;
};

}  // namespace mer::loop
