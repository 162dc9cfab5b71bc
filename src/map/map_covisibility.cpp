// Map: the covisibility graph (writer-side edge upkeep, lock-free reads).
#include <algorithm>

#include "map/map.h"
#include "map/map_internal.h"

namespace mer::map {

using map_detail::pack_edge;
using map_detail::stronger;
using map_detail::unpack_edge;

std::uint32_t Map::own_covis(KeyframeId kf, CovisibleKeyframe* out) const noexcept {
  const std::uint32_t n = load_own(kfs_[kf].covis_count);
  const std::size_t base = std::size_t{kf} * max_cov_;
  for (std::uint32_t i = 0; i < n; ++i) out[i] = unpack_edge(load_own(covis_[base + i]));
  return n;
}

void Map::write_covis(KeyframeId kf, const CovisibleKeyframe* list, std::uint32_t n) noexcept {
  KeyframeSlot& s = kfs_[kf];
  const std::size_t base = std::size_t{kf} * max_cov_;
  s.covis_lock.write_begin();
  for (std::uint32_t i = 0; i < n; ++i) store_payload(covis_[base + i], pack_edge(list[i]));
  store_payload(s.covis_count, n);
  s.covis_lock.write_end();
}

void Map::upsert_edge(KeyframeId owner, KeyframeId other, std::uint32_t weight) noexcept {
  CovisibleKeyframe* list = list_scratch_.get();
  std::uint32_t n = own_covis(owner, list);
  const CovisibleKeyframe edge{other, weight};
  CovisibleKeyframe* it =
      std::find_if(list, list + n, [&](const CovisibleKeyframe& e) { return e.id == other; });
  if (it != list + n) {
    if (it->weight == weight) return;
    it->weight = weight;
  } else if (n < max_cov_) {
    list[n++] = edge;
  } else if (stronger(edge, list[n - 1U])) {
    list[n - 1U] = edge;
  } else {
    return;
  }
  std::sort(list, list + n, stronger);
  write_covis(owner, list, n);
}

void Map::remove_edge(KeyframeId owner, KeyframeId other) noexcept {
  CovisibleKeyframe* list = list_scratch_.get();
  const std::uint32_t n = own_covis(owner, list);
  CovisibleKeyframe* end =
      std::remove_if(list, list + n, [&](const CovisibleKeyframe& e) { return e.id == other; });
  const auto m = static_cast<std::uint32_t>(end - list);
  if (m != n) write_covis(owner, list, m);
}

void Map::update_covisibility(KeyframeId kf) {
  if (!own_keyframe(kf)) return;
  // Shared points with every other keyframe (each point observes a keyframe at most once).
  std::uint32_t* weight = covis_weight_.get();
  std::uint32_t touched = 0;
  const std::uint32_t nkp = kfs_[kf].num_keypoints;
  for (std::uint32_t kp = 0; kp < nkp; ++kp) {
    const PointId p = load_own(kf_points_[kp_index(kf, kp)]);
    if (p == kNoId || !own_point(p)) continue;
    const Observation* o = &obs_[std::size_t{p} * max_obs_];
    for (std::uint32_t i = 0; i < obs_count_[p]; ++i) {
      if (o[i].kf() == kf) continue;
      if (weight[o[i].kf()]++ == 0U) covis_touched_[touched++] = o[i].kf();
    }
  }
  // Former neighbours that share nothing now lose their edge to kf.
  const std::uint32_t n_old = load_own(kfs_[kf].covis_count);
  for (std::uint32_t i = 0; i < n_old; ++i) {
    const CovisibleKeyframe e = unpack_edge(load_own(covis_[std::size_t{kf} * max_cov_ + i]));
    if (weight[e.id] == 0U) remove_edge(e.id, kf);
  }
  CovisibleKeyframe* sorted = covis_sorted_.get();
  for (std::uint32_t i = 0; i < touched; ++i) {
    const KeyframeId other = covis_touched_[i];
    sorted[i] = {other, weight[other]};
    weight[other] = 0;
  }
  std::sort(sorted, sorted + touched, stronger);
  write_covis(kf, sorted, std::min(touched, max_cov_));
  for (std::uint32_t i = 0; i < touched; ++i) upsert_edge(sorted[i].id, kf, sorted[i].weight);
}

std::size_t Map::covisible_keyframes(KeyframeId kf,
                                     std::span<CovisibleKeyframe> out) const noexcept {
  if (!live_keyframe(kf) || out.empty()) return 0;
  const KeyframeSlot& s = kfs_[kf];
  const std::size_t base = std::size_t{kf} * max_cov_;
  std::size_t got = 0;
  if (!s.covis_lock.read([&] {
        got = std::min<std::size_t>(load_payload(s.covis_count), out.size());
        for (std::size_t i = 0; i < got; ++i) out[i] = unpack_edge(load_payload(covis_[base + i]));
      })) {
    return 0;
  }
  return got;
}

std::uint32_t Map::covisibility_weight(KeyframeId a, KeyframeId b) const noexcept {
  if (!live_keyframe(a)) return 0;
  const KeyframeSlot& s = kfs_[a];
  const std::size_t base = std::size_t{a} * max_cov_;
  std::uint32_t weight = 0;
  if (!s.covis_lock.read([&] {
        weight = 0;
        const std::uint32_t n = load_payload(s.covis_count);
        for (std::uint32_t i = 0; i < n; ++i) {
          const CovisibleKeyframe e = unpack_edge(load_payload(covis_[base + i]));
          if (e.id == b) weight = e.weight;
        }
      })) {
    return 0;
  }
  return weight;
}

}  // namespace mer::map
