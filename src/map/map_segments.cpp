// Map: segments, their Sim(3) corrections, merges and discards.
#include <algorithm>

#include "map/map.h"
#include "map/map_internal.h"

namespace mer::map {

using map_detail::kFateDiscarded;
using map_detail::kFateLive;
using map_detail::kFateMerged;

void Map::publish_correction(std::uint16_t segment, const geometry::Sim3d& S_new_old) noexcept {
  if (segment >= kMaxSegments) return;
  geometry::Sim3d& own = correction_own_[segment];
  own = S_new_old * own;
  std::atomic<std::uint64_t>* w = &correction_[std::size_t{segment} * kCorrectionWords];
  const std::uint64_t seg_count = load_payload(w[kPoseWords]) + 1U;
  const std::uint32_t count = correction_count_.load(std::memory_order_relaxed) + 1U;
  correction_lock_.write_begin();
  for (int i = 0; i < 9; ++i) store_payload(w[kPoseRotation + i], pack_double(own.R(i % 3, i / 3)));
  for (int i = 0; i < 3; ++i) store_payload(w[kPoseTranslation + i], pack_double(own.t[i]));
  store_payload(w[kPoseScale], pack_double(own.s));
  store_payload(w[kPoseWords], seg_count);
  correction_lock_.write_end();
  correction_count_.store(count, std::memory_order_release);
}

std::uint32_t Map::merge_segment(std::uint16_t from, std::uint16_t into,
                                 const geometry::Sim3d& S_into_from) {
  if (from >= kMaxSegments || into >= kMaxSegments || from == into ||
      merged_into_[from].load(std::memory_order_relaxed) != kNoSegment ||
      merged_into_[into].load(std::memory_order_relaxed) != kNoSegment ||
      !S_into_from.R.allFinite() || !S_into_from.t.allFinite() || !std::isfinite(S_into_from.s) ||
      S_into_from.s <= 0.0) {
    return 0;
  }
  // Claimed against a concurrent discard (the tracker's, lock-free): the first one wins.
  std::uint8_t live = kFateLive;
  if (!fate_[from].compare_exchange_strong(live, kFateMerged, std::memory_order_acq_rel) ||
      fate_[into].load(std::memory_order_acquire) == kFateDiscarded) {
    if (live == kFateLive) fate_[from].store(kFateLive, std::memory_order_release);
    return 0;
  }
  const geometry::Sim3d& S = S_into_from;
  const std::uint32_t nk = num_keyframes_.load(std::memory_order_relaxed);
  std::uint32_t moved = 0;
  for (KeyframeId kf = 0; kf < nk; ++kf) {
    if (!own_keyframe(kf) || kfs_[kf].segment.load(std::memory_order_relaxed) != from) continue;
    double scale = 1.0;
    SE3d T_w_c;
    if (!keyframe_pose(kf, T_w_c, &scale)) T_w_c = own_pose(kf);
    write_pose(kf, (S * geometry::Sim3d::from_se3(T_w_c)).rigid(), scale);
    if (S.s != 1.0) {
      const std::size_t base = kp_index(kf, 0);
      for (std::uint32_t k = 0; k < kfs_[kf].num_keypoints; ++k) {
        std::atomic<float>& d = kf_depth_[base + k];
        d.store(static_cast<float>(d.load(std::memory_order_relaxed) * S.s),
                std::memory_order_relaxed);
      }
    }
    kfs_[kf].segment.store(into, std::memory_order_relaxed);
    ++moved;
  }
  const std::uint32_t np = num_points_.load(std::memory_order_relaxed);
  for (PointId p = 0; p < np; ++p) {
    if (!own_point(p) || pt_segment_[p] != from) continue;
    pt_segment_[p] = into;
    const Eigen::Vector3d p_w = S * own_position(p);
    write_position(p, p_w);
    const CellKey key = grid_.key_of(p_w, into);
    point_cell_[p] = grid_.move(p, point_cell_[p], key) ? key : kNoCell;
    update_point(p);  // the distance range, in the units of `into`
  }
  SegmentMerge& m = merges_[from];
  m.into = into;
  m.sim_into_from = S;
  m.into_correction = correction_own_[into];
  m.into_count = static_cast<std::uint32_t>(
      load_payload(correction_[std::size_t{into} * kCorrectionWords + kPoseWords]));
  m.from_count = static_cast<std::uint32_t>(
                     load_payload(correction_[std::size_t{from} * kCorrectionWords + kPoseWords])) +
                 1U;
  merged_into_[from].store(into, std::memory_order_release);
  publish_correction(from, S);
  return moved;
}

void Map::publish_segment_start(std::uint16_t segment, SegmentStartState state, KeyframeId first,
                                KeyframeId last) noexcept {
  if (segment >= kMaxSegments ||
      start_state_[segment].load(std::memory_order_relaxed) != SegmentStartState::kPending) {
    return;
  }
  starts_[segment] = SegmentStartRecord{state, first, last};
  start_state_[segment].store(state, std::memory_order_release);
}

SegmentStartRecord Map::segment_start(std::uint16_t segment) const noexcept {
  if (segment >= kMaxSegments ||
      start_state_[segment].load(std::memory_order_acquire) == SegmentStartState::kPending) {
    return SegmentStartRecord{};
  }
  return starts_[segment];
}

bool Map::discard_segment(std::uint16_t segment) noexcept {
  if (segment >= kMaxSegments) return false;
  std::uint8_t live = kFateLive;
  if (!fate_[segment].compare_exchange_strong(live, kFateDiscarded, std::memory_order_acq_rel)) {
    return false;
  }
  discarded_count_.fetch_add(1, std::memory_order_acq_rel);
  return true;
}

bool Map::segment_discarded(std::uint16_t segment) const noexcept {
  return segment < kMaxSegments && fate_[segment].load(std::memory_order_acquire) == kFateDiscarded;
}

bool Map::segment_merge(std::uint16_t segment, SegmentMerge& out) const noexcept {
  if (segment >= kMaxSegments ||
      merged_into_[segment].load(std::memory_order_acquire) == kNoSegment)
    return false;
  out = merges_[segment];
  return true;
}

std::uint16_t Map::merged_segment(std::uint16_t segment,
                                  geometry::Sim3d& S_final_segment) const noexcept {
  S_final_segment = geometry::Sim3d{};
  SegmentMerge m;
  // Each merge joins a segment into one not merged yet, so the chain ends within kMaxSegments.
  for (std::uint32_t hops = 0; hops < kMaxSegments && segment_merge(segment, m); ++hops) {
    S_final_segment = m.sim_into_from * S_final_segment;
    segment = m.into;
  }
  return segment;
}

std::uint32_t Map::correction_count() const noexcept {
  return correction_count_.load(std::memory_order_acquire);
}

bool Map::read_correction(std::uint16_t segment, geometry::Sim3d& S,
                          std::uint32_t& count) const noexcept {
  S = geometry::Sim3d{};
  count = 0;
  if (segment >= kMaxSegments) return true;
  const std::atomic<std::uint64_t>* src = &correction_[std::size_t{segment} * kCorrectionWords];
  std::uint64_t w[kCorrectionWords];
  if (!correction_lock_.read([&] {
        for (int i = 0; i < kCorrectionWords; ++i) w[i] = load_payload(src[i]);
      })) {
    return false;
  }
  count = static_cast<std::uint32_t>(w[kPoseWords]);
  if (count == 0U) return true;
  for (int i = 0; i < 9; ++i) S.R(i % 3, i / 3) = unpack_double(w[kPoseRotation + i]);
  for (int i = 0; i < 3; ++i) S.t[i] = unpack_double(w[kPoseTranslation + i]);
  S.s = unpack_double(w[kPoseScale]);
  return true;
}

}  // namespace mer::map
