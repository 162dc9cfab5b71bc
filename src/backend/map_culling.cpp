#include "backend/map_culling.h"

#include <algorithm>
#include <mutex>

#include "platform/clock.h"
#include "platform/log_ring.h"

namespace mer::backend {
namespace {

constexpr std::uint64_t kLogEveryKeyframes = 100;  // map size logged this often (info level)
// point_min_observations: auto. Monocular points come from two views and need a third to be
// trusted (ORB-SLAM's rule); a point on metric sensor depth is placed by one keyframe.
constexpr int kMonoMinObservations = 3;
constexpr int kMetricMinObservations = 1;

CullingOptions resolved(CullingOptions o, bool metric_depth) {
  if (o.point_min_observations == 0) {
    o.point_min_observations = metric_depth ? kMetricMinObservations : kMonoMinObservations;
  }
  return o;
}

}  // namespace

MapCuller::MapCuller(const CullingOptions& opts, map::Map& map, bool metric_depth)
    : opts_(resolved(opts, metric_depth)),
      map_(map),
      covis_(static_cast<std::size_t>(map.options().max_covisible_per_keyframe)),
      obs_(static_cast<std::size_t>(map.options().max_observations_per_point)),
      obs_histogram_(static_cast<std::size_t>(map.options().max_observations_per_point) + 1U),
      ranked_(static_cast<std::size_t>(opts_.max_capacity_removals)),
      parent_covis_(static_cast<std::size_t>(map.options().max_covisible_per_keyframe)),
      lineage_(static_cast<std::size_t>(opts_.lineage_capacity)) {}

int MapCuller::cull_points() {
  const std::uint64_t now = map_.keyframes_added();
  const auto recent = static_cast<std::uint64_t>(opts_.point_recent_keyframes);
  const auto check_after = static_cast<std::uint64_t>(opts_.point_check_after_keyframes);
  const auto min_obs = static_cast<std::uint32_t>(opts_.point_min_observations);
  int culled = 0;
  const std::uint32_t used = map_.num_points();
  for (map::PointId p = 0; p < used; ++p) {
    const map::PointStats s = map_.point_stats(p);
    if (s.observations == 0) continue;  // not live
    // Age in keyframes added since its creation: 0 for a point of the newest keyframe, which
    // the tracker has not had a chance to find yet.
    const std::uint64_t age = now - s.created_serial;
    if (age == 0 || age > recent) continue;
    const bool low_ratio =
        static_cast<double>(s.found) < opts_.point_min_found_ratio * static_cast<double>(s.visible);
    const bool few_views = age >= check_after && s.observations < min_obs;
    if (low_ratio || few_views) {
      map_.set_point_bad(p);
      ++culled;
    }
  }
  return culled;
}

double MapCuller::redundancy(map::KeyframeId kf) {
  const std::span<const features::Keypoint> kps = map_.keyframe_keypoints(kf);
  const auto need = static_cast<std::uint32_t>(opts_.redundant_observers);
  int points = 0;
  int redundant = 0;
  for (std::uint32_t k = 0; k < kps.size(); ++k) {
    const map::PointId p = map_.keyframe_point(kf, k);
    if (p == map::kNoId) continue;
    ++points;
    if (map_.point_num_observations(p) <= need) continue;  // itself + fewer than `need` others
    const int max_level = kps[k].level + opts_.redundant_level_slack;
    const std::size_t no = map_.point_observations(p, obs_);
    std::uint32_t others = 0;
    for (std::size_t o = 0; o < no && others < need; ++o) {
      if (obs_[o].first == kf) continue;
      const std::span<const features::Keypoint> other = map_.keyframe_keypoints(obs_[o].first);
      if (obs_[o].second < other.size() && other[obs_[o].second].level <= max_level) ++others;
    }
    if (others >= need) ++redundant;
  }
  return points > 0 ? static_cast<double>(redundant) / static_cast<double>(points) : 0.0;
}

bool MapCuller::removable(map::KeyframeId kf) const {
  // Not live any more, the anchor (first keyframe) or one of the newest: kept.
  const std::uint64_t serial = map_.keyframe_serial(kf);
  return serial != map::Map::kNoSerial && serial != 0 &&
         serial + static_cast<std::uint64_t>(opts_.keep_newest_keyframes) < map_.keyframes_added();
}

bool MapCuller::parent_of(map::KeyframeId kf, CulledKeyframe& rec) {
  if (lineage_.empty()) return false;
  // The live keyframe sharing most points with kf (else the newest one) carries it on; it
  // must be of kf's segment (another segment's pose is in another world frame).
  const std::uint16_t segment = map_.keyframe_segment(kf);
  map::KeyframeId parent = map::kNoId;
  const std::size_t n = map_.covisible_keyframes(kf, parent_covis_);
  for (std::size_t i = 0; i < n && parent == map::kNoId; ++i) {
    if (parent_covis_[i].id != kf && map_.keyframe_is_live(parent_covis_[i].id)) {
      parent = parent_covis_[i].id;
    }
  }
  if (parent == map::kNoId) parent = map_.newest_keyframe();
  SE3d T_w_kf;
  SE3d T_w_parent;
  if (parent == map::kNoId || parent == kf || map_.keyframe_segment(parent) != segment ||
      !map_.keyframe_pose(kf, T_w_kf) || !map_.keyframe_pose(parent, T_w_parent)) {
    return false;
  }
  rec = CulledKeyframe{map_.keyframe_t_ns(kf), map_.keyframe_t_ns(parent),
                       T_w_parent.inverse() * T_w_kf, segment};
  return true;
}

bool MapCuller::remove(map::KeyframeId kf, CullingReport& rep) {
  CulledKeyframe rec;
  const bool has_parent = parent_of(kf, rec);
  std::uint32_t orphaned = 0;
  if (!map_.remove_keyframe(kf, static_cast<std::uint32_t>(opts_.point_min_observations),
                            &orphaned)) {
    return false;
  }
  if (has_parent) {
    lineage_[lineage_next_] = rec;
    lineage_next_ = (lineage_next_ + 1) % lineage_.size();
    lineage_count_ = std::min(lineage_count_ + 1, lineage_.size());
  }
  ++rep.culled_keyframes;
  rep.orphaned_points += static_cast<int>(orphaned);
  return true;
}

int MapCuller::remove_discarded_segments() {
  if (map_.discarded_segments() == discards_cleared_.load(std::memory_order_relaxed)) return 0;
  const std::lock_guard<platform::PiMutex> lock(map_.writer_lock());
  CullingReport rep;
  remove_discarded(rep);
  return rep.discarded_keyframes;
}

void MapCuller::remove_discarded(CullingReport& rep) {
  const std::uint32_t discards = map_.discarded_segments();
  if (discards == discards_cleared_.load(std::memory_order_relaxed)) return;
  const int orphaned_before = rep.orphaned_points;
  bool left = false;  // a keyframe of a discarded segment stays live (the map's newest)
  const map::KeyframeId n = map_.num_keyframes();
  for (map::KeyframeId kf = 0; kf < n; ++kf) {
    if (!map_.keyframe_is_live(kf) || !map_.segment_discarded(map_.keyframe_segment(kf))) {
      continue;
    }
    std::uint32_t orphaned = 0;
    if (map_.remove_keyframe(kf, static_cast<std::uint32_t>(opts_.point_min_observations),
                             &orphaned)) {
      ++rep.discarded_keyframes;
      rep.orphaned_points += static_cast<int>(orphaned);
    } else {
      left = true;
    }
  }
  if (!left)
    discards_cleared_.store(
        discards, std::memory_order_relaxed);  // later passes skip the scan until a new discard
  const auto orphaned = static_cast<std::uint64_t>(rep.orphaned_points - orphaned_before);
  totals_.discarded_keyframes += static_cast<std::uint64_t>(rep.discarded_keyframes);
  totals_.culled_points += orphaned;
  totals_.orphaned_points += orphaned;
}

void MapCuller::cull_at_capacity(CullingReport& rep) {
  const map::MapOptions& mo = map_.options();
  const auto kf_limit =
      static_cast<std::uint32_t>(opts_.capacity_fraction * static_cast<double>(mo.max_keyframes));
  if (map_.live_keyframes() > kf_limit) {
    // One scan ranks the removable keyframes; the most redundant go (the oldest on a tie).
    const std::size_t want =
        std::min<std::size_t>(ranked_.size(), std::size_t{map_.live_keyframes() - kf_limit});
    std::size_t n = 0;
    auto before = [&](const Ranked& a, const Ranked& b) {
      return a.redundancy != b.redundancy ? a.redundancy > b.redundancy : a.serial < b.serial;
    };
    const std::uint32_t used = map_.num_keyframes();
    for (map::KeyframeId kf = 0; kf < used; ++kf) {
      if (!removable(kf)) continue;
      const Ranked r{redundancy(kf), map_.keyframe_serial(kf), kf};
      if (n < want) {
        ranked_[n++] = r;
      } else if (before(r, ranked_[n - 1])) {
        ranked_[n - 1] = r;
      } else {
        continue;
      }
      std::sort(ranked_.begin(), ranked_.begin() + static_cast<std::ptrdiff_t>(n), before);
    }
    for (std::size_t i = 0; i < n; ++i) {
      if (remove(ranked_[i].kf, rep)) ++rep.capacity_keyframes;
    }
  }

  // Points: free the least observed (older than the recent ones) down to the limit.
  const auto pt_limit =
      static_cast<std::uint32_t>(opts_.capacity_fraction * static_cast<double>(mo.max_points));
  const std::uint32_t live = map_.live_points();
  if (live <= pt_limit) return;
  std::uint32_t need = live - pt_limit;
  const std::uint64_t now = map_.keyframes_added();
  const auto recent = static_cast<std::uint64_t>(opts_.point_recent_keyframes);
  const std::uint32_t used = map_.num_points();
  auto eligible = [&](const map::PointStats& s) {
    return s.observations > 0 && now - s.created_serial > recent;
  };
  std::fill(obs_histogram_.begin(), obs_histogram_.end(), 0U);
  for (map::PointId p = 0; p < used; ++p) {
    const map::PointStats s = map_.point_stats(p);
    if (eligible(s))
      ++obs_histogram_[std::min<std::size_t>(s.observations, obs_histogram_.size() - 1)];
  }
  // Free every eligible point with fewer than `cut` observations, and points with exactly
  // `cut` (lowest ids first) until `need` are freed.
  std::size_t cut = 1;
  std::uint32_t below = 0;
  while (cut + 1 < obs_histogram_.size() && below + obs_histogram_[cut] < need) {
    below += obs_histogram_[cut];
    ++cut;
  }
  std::uint32_t at_cut = need > below ? need - below : 0U;
  for (map::PointId p = 0; p < used && need > 0; ++p) {
    const map::PointStats s = map_.point_stats(p);
    if (!eligible(s) || s.observations > cut) continue;
    if (s.observations == cut) {
      if (at_cut == 0) continue;
      --at_cut;
    }
    map_.set_point_bad(p);
    ++rep.culled_points;
    ++rep.capacity_points;
    --need;
  }
}

CullingReport MapCuller::spin_once(map::KeyframeId newest) {
  CullingReport rep;
  if (!opts_.enabled &&
      map_.discarded_segments() == discards_cleared_.load(std::memory_order_relaxed)) {
    return rep;
  }
  const std::lock_guard<platform::PiMutex> lock(map_.writer_lock());
  const auto t0 = platform::monotonic_now_ns();  // after the wait: `ms` is the work
  remove_discarded(rep);
  if (!opts_.enabled) {
    rep.ms = platform::elapsed_ms(t0);
    return rep;
  }
  const int orphaned_by_discard = rep.orphaned_points;  // already in the totals

  rep.culled_points = cull_points();

  const std::size_t nc = newest == map::kNoId ? 0 : map_.covisible_keyframes(newest, covis_);
  for (std::size_t i = 0; i < nc; ++i) {
    const map::KeyframeId kf = covis_[i].id;
    if (!removable(kf)) continue;
    ++rep.checked_keyframes;
    if (redundancy(kf) > opts_.keyframe_redundancy) (void)remove(kf, rep);
  }
  cull_at_capacity(rep);
  rep.ran = true;
  rep.ms = platform::elapsed_ms(t0);

  const std::uint64_t now = map_.keyframes_added();
  ++totals_.runs;
  totals_.culled_keyframes += static_cast<std::uint64_t>(rep.culled_keyframes);
  const int orphaned = rep.orphaned_points - orphaned_by_discard;
  totals_.culled_points += static_cast<std::uint64_t>(rep.culled_points + orphaned);
  totals_.orphaned_points += static_cast<std::uint64_t>(orphaned);
  totals_.capacity_keyframes += static_cast<std::uint64_t>(rep.capacity_keyframes);
  totals_.capacity_points += static_cast<std::uint64_t>(rep.capacity_points);
  totals_.total_ms += rep.ms;
  totals_.max_ms = std::max(totals_.max_ms, rep.ms);
  if (now % kLogEveryKeyframes == 0) {
    const map::MapCounters c = map_.counters();
    MER_LOG_INFO(
        "map after %llu keyframes: %u keyframes, %u points live; culled %llu keyframes, "
        "%llu points; reused %llu keyframe, %llu point slots",
        static_cast<unsigned long long>(now), c.live_keyframes, c.live_points,
        static_cast<unsigned long long>(totals_.culled_keyframes),
        static_cast<unsigned long long>(totals_.culled_points),
        static_cast<unsigned long long>(c.reused_keyframe_slots),
        static_cast<unsigned long long>(c.reused_point_slots));
  }
  return rep;
}

}  // namespace mer::backend
