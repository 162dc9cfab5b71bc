#pragma once
/// @file map_culling.h
/// Map culling, `spin_once(new keyframe) -> CullingReport`, run after each keyframe's local
/// optimization (threaded mode: on the back-end thread, around the newest keyframe inserted;
/// lockstep: after the local BA on the same thread), so that a long run keeps a bounded map
/// (freed slots are reused by the map: map.h, slot reclamation). spin_once holds the map's
/// writer lock for the whole pass.
///
/// Map points (ORB-SLAM's recent-point culling): a point created in one of the last
/// `point_recent_keyframes` keyframes is freed when the tracker found it in fewer than
/// `point_min_found_ratio` of the frames it projected into (Map::note_visible /
/// note_found), or when it is `point_check_after_keyframes` keyframes old and has fewer than
/// `point_min_observations` observations. Points with a large reprojection error are culled
/// by the local bundle adjustment (local_ba.h).
///
/// Keyframes (ORB-SLAM's keyframe culling): a covisible keyframe of the new one is redundant
/// when more than `keyframe_redundancy` of its map points are each observed by at least
/// `redundant_observers` other keyframes at the same or a finer scale (pyramid level at most
/// `redundant_level_slack` above its own). A redundant keyframe is removed (Map::
/// remove_keyframe): its observations leave its points and points left with fewer than
/// `point_min_observations` observations are freed. The first keyframe (the anchor of the
/// map's gauge) and the newest `keep_newest_keyframes` keyframes are never removed.
///
/// At capacity: these rules alone do not bound the map (a keyframe whose points are seen by
/// few others is never redundant), so when the live keyframes exceed `capacity_fraction` of
/// map.max_keyframes, the live keyframe with the largest redundant-point fraction is removed
/// (at most `max_capacity_removals` per pass, ranked in one scan), and when the live points
/// exceed that fraction of map.max_points, the points with the fewest observations (older
/// than `point_recent_keyframes`) are freed down to it. A run shorter than the capacity is not
/// affected; a long one keeps its newest keyframes and the best-covered structure.
///
/// Keyframes of a discarded segment (a failed start, Map::discard_segment) are removed on
/// every pass, whatever the rules above, culling enabled or not; the newest keyframe of the
/// map waits for the next pass (Map::remove_keyframe keeps it).
///
/// Bounded work per call: one pass over the point slots in use (a few array reads per slot)
/// and, per covisible keyframe (at most map.max_covisible_per_keyframe), one pass over its
/// keypoints and their points' observations; at capacity, one such pass over every live
/// keyframe and two passes over the point slots. No allocation after construction.

#include <atomic>
#include <cstdint>
#include <span>
#include <vector>

#include "core/options.h"
#include "map/map.h"

namespace mer::backend {

/// Options of map culling (config section `culling`).
struct CullingOptions {
  bool enabled = true;
  double keyframe_redundancy = 0.9;
  int redundant_observers = 3;
  int redundant_level_slack = 1;
  int keep_newest_keyframes = 5;
  int point_recent_keyframes = 3;
  double point_min_found_ratio = 0.0;
  int point_check_after_keyframes = 2;
  int point_min_observations = 0;
  double capacity_fraction = 0.9;
  int max_capacity_removals = 2;
  int lineage_capacity = 16384;

  template <class V>
  void visit(V& v) {
    v.field("enabled", enabled,
            "remove redundant keyframes and bad map points after each keyframe (their map "
            "slots are reused)");
    v.field("keyframe_redundancy", keyframe_redundancy,
            "a keyframe whose fraction of redundant map points exceeds this is removed",
            options::Range<double>{0.0, 1.0});
    v.field("redundant_observers", redundant_observers,
            "a map point is redundant in a keyframe when at least this many other keyframes "
            "observe it at the same or a finer scale",
            options::Range<int>{1, 64});
    v.field("redundant_level_slack", redundant_level_slack,
            "pyramid levels by which another keyframe's observation may be coarser and still "
            "count for redundancy",
            options::Range<int>{0, 32});
    v.field("keep_newest_keyframes", keep_newest_keyframes,
            "the newest keyframes (insertion order) are never removed; nor is the first one",
            options::Range<int>{1, 1000});
    v.field("point_recent_keyframes", point_recent_keyframes,
            "map points created within this many keyframes are checked by the found-ratio "
            "and observation rules",
            options::Range<int>{0, 1000});
    v.field("point_min_found_ratio", point_min_found_ratio,
            "a recent map point found (tracked inlier) in fewer than this fraction of the "
            "frames it projected into is removed (0: off; ORB-SLAM's 0.25 made the monocular "
            "synthetic runs drift more)",
            options::Range<double>{0.0, 1.0});
    v.field("point_check_after_keyframes", point_check_after_keyframes,
            "a recent map point this many keyframes old with fewer than point_min_observations "
            "observations is removed",
            options::Range<int>{1, 1000});
    v.field("point_min_observations", point_min_observations,
            "observations a map point needs to survive the observation rule and the removal "
            "of a keyframe observing it (0: auto, 3 with monocular depth, 1 with metric "
            "sensor depth; 1: only points left unobserved are removed)",
            options::Range<int>{0, 255});
    v.field("capacity_fraction", capacity_fraction,
            "above this fraction of map.max_keyframes live keyframes, the most redundant ones "
            "are removed; above this fraction of map.max_points live points, those with the "
            "fewest observations (1: off)",
            options::Range<double>{0.1, 1.0});
    v.field("max_capacity_removals", max_capacity_removals,
            "keyframes removed per pass when above capacity_fraction", options::Range<int>{1, 100});
    v.field("lineage_capacity", lineage_capacity,
            "removed keyframes whose pose relative to their strongest covisible keyframe is "
            "kept, so frames tracked against them can be re-anchored to the final map "
            "(trajectory_final.txt; 72 B each, the oldest forgotten first)",
            options::Range<int>{0, 10000000});
  }
};

/// What one culling pass did.
struct CullingReport {
  bool ran = false;
  int checked_keyframes = 0;    ///< covisible keyframes examined for redundancy
  int culled_keyframes = 0;     ///< keyframes removed
  int culled_points = 0;        ///< points freed by the point rules (at capacity included)
  int orphaned_points = 0;      ///< points freed because a removed keyframe left them too few views
  int capacity_keyframes = 0;   ///< of culled_keyframes, removed at capacity
  int capacity_points = 0;      ///< of culled_points, freed at capacity
  int discarded_keyframes = 0;  ///< keyframes of discarded segments removed (not in culled_*)
  double ms = 0.0;
};

/// Totals over a run (summary.json `map`).
struct CullingTotals {
  std::uint64_t runs = 0;
  std::uint64_t culled_keyframes = 0;
  std::uint64_t culled_points = 0;        ///< point rules + orphaned by keyframe removal
  std::uint64_t orphaned_points = 0;      ///< of these, orphaned by keyframe removal
  std::uint64_t capacity_keyframes = 0;   ///< keyframes removed at capacity
  std::uint64_t capacity_points = 0;      ///< points freed at capacity
  std::uint64_t discarded_keyframes = 0;  ///< keyframes of discarded segments removed
  double total_ms = 0.0;
  double max_ms = 0.0;
};

/// A removed keyframe's place relative to the live keyframe of its segment that shared most
/// points with it when it was removed: its final pose is the parent's final pose times
/// T_parent_kf, whose translation is in the units of `segment` at that time (a later merge
/// rescales it: final_trajectory.h).
struct CulledKeyframe {
  std::int64_t t_ns = 0;         ///< the removed keyframe's timestamp
  std::int64_t parent_t_ns = 0;  ///< the parent's timestamp
  SE3d T_parent_kf = SE3d::Identity();
  std::uint16_t segment = 0;  ///< the map segment both were in when it was removed
};

/// The culling stage (a map writer: see spin_once).
class MapCuller {
 public:
  /// `metric_depth`: keyframe depth is metric sensor depth (rgbd mode), so a point seen by
  /// one keyframe is already well placed; resolves `point_min_observations: 0`.
  MapCuller(const CullingOptions& opts, map::Map& map, bool metric_depth = false);

  /// One pass after keyframe `newest` was added (kNoId: culls points only). Takes the map's
  /// writer lock (the caller must not hold it).
  CullingReport spin_once(map::KeyframeId newest);
  /// Removes the keyframes of discarded segments only (as spin_once does first), e.g. when a
  /// segment's start was inserted or the run ends; returns how many. Takes the writer lock.
  int remove_discarded_segments();

  /// Fraction of kf's map points that are redundant (see the file comment; 0 without
  /// points); the caller holds the map's writer lock (or is the only thread using the map).
  double redundancy(map::KeyframeId kf);

  const CullingTotals& totals() const { return totals_; }
  /// The last options().lineage_capacity removed keyframes, in no particular order (read
  /// when the back end has stopped).
  std::span<const CulledKeyframe> lineage() const {
    return std::span<const CulledKeyframe>(lineage_.data(), lineage_count_);
  }
  /// Options in effect (`point_min_observations` resolved).
  const CullingOptions& options() const { return opts_; }

 private:
  int cull_points();
  bool removable(map::KeyframeId kf) const;
  bool remove(map::KeyframeId kf, CullingReport& rep);
  /// kf's lineage record (false: lineage off, or no live keyframe to carry it).
  bool parent_of(map::KeyframeId kf, CulledKeyframe& rec);
  void cull_at_capacity(CullingReport& rep);
  // Removes the keyframes of discarded segments (Map::discard_segment; not a culling rule:
  // done also when culling is disabled) into rep and the totals. No lineage: their frames
  // are not re-anchored. The caller holds the writer lock.
  void remove_discarded(CullingReport& rep);

  CullingOptions opts_;
  map::Map& map_;
  CullingTotals totals_;
  std::vector<map::CovisibleKeyframe> covis_;                   // max_covisible_per_keyframe
  std::vector<std::pair<map::KeyframeId, std::uint32_t>> obs_;  // max_observations_per_point
  std::vector<std::uint32_t> obs_histogram_;                    // max_observations_per_point + 1
  struct Ranked {
    double redundancy = 0.0;
    std::uint64_t serial = 0;
    map::KeyframeId kf = map::kNoId;
  };
  std::vector<Ranked> ranked_;  // max_capacity_removals best removal candidates
  std::vector<map::CovisibleKeyframe> parent_covis_;  // max_covisible_per_keyframe
  std::vector<CulledKeyframe> lineage_;               // ring of lineage_capacity
  std::size_t lineage_count_ = 0;
  // Map::discarded_segments() when a pass last left no keyframe of a discarded segment live
  // (the scan is skipped until the next discard). A keyframe job of a discarded segment
  // inserted after that stays, flagged: relocalization and loops skip it. Atomic: threaded,
  // the depth thread (a segment's start) and the back end read it before the writer lock.
  std::atomic<std::uint32_t> discards_cleared_{0};
  std::size_t lineage_next_ = 0;
};

}  // namespace mer::backend
