// Map: lock-free reads of keyframes, points and the cell grid; counters.
#include <algorithm>

#include "map/map.h"

namespace mer::map {

std::size_t Map::point_observations(PointId p,
                                    std::span<std::pair<KeyframeId, std::uint32_t>> out) const {
  if (!own_point(p)) return 0;
  const std::size_t n = std::min<std::size_t>(obs_count_[p], out.size());
  const Observation* o = &obs_[std::size_t{p} * max_obs_];
  for (std::size_t i = 0; i < n; ++i) out[i] = {o[i].kf(), o[i].kp()};
  return n;
}

std::size_t Map::point_num_observations(PointId p) const {
  return own_point(p) ? obs_count_[p] : 0U;
}

PointStats Map::point_stats(PointId p) const {
  if (!own_point(p)) return {};
  return {obs_count_[p], pt_visible_[p].load(std::memory_order_relaxed),
          pt_found_[p].load(std::memory_order_relaxed), pt_serial_[p]};
}

std::uint64_t Map::keyframe_serial(KeyframeId kf) const noexcept {
  return own_keyframe(kf) ? kf_serial_[kf] : kNoSerial;
}

SE3d Map::relative_pose(KeyframeId a, KeyframeId b) const {
  if (!own_keyframe(a) || !own_keyframe(b)) return SE3d::Identity();
  return own_pose(a).inverse() * own_pose(b);
}

MapCounters Map::counters() const noexcept {
  MapCounters c;
  c.live_keyframes = load_own(live_kfs_);
  c.live_points = load_own(live_pts_);
  c.keyframe_slots_used = num_keyframes_.load(std::memory_order_relaxed);
  c.point_slots_used = num_points_.load(std::memory_order_relaxed);
  c.removed_keyframes = removed_keyframes_;
  c.bad_points = bad_points_;
  c.merged_points = merged_points_;
  c.reused_keyframe_slots = reused_kf_slots_;
  c.reused_point_slots = reused_pt_slots_;
  c.keyframe_slots_waiting = kf_retired_.size;
  c.point_slots_waiting = pt_retired_.size;
  return c;
}

Result<int> Map::register_reader() {
  for (int r = 0; r < kMaxMapReaders; ++r) {
    ReaderSlot& slot = readers_[r];
    if (slot.announced.load(std::memory_order_relaxed) != kReaderUnused) continue;
    slot.announced.store(epoch_.load(std::memory_order_acquire), std::memory_order_release);
    return r;
  }
  return runtime_error("map: more than " + std::to_string(kMaxMapReaders) +
                       " registered reader threads");
}

void Map::release_reader(int reader) noexcept {
  if (reader < 0 || reader >= kMaxMapReaders) return;
  readers_[reader].announced.store(kReaderUnused, std::memory_order_release);
}

// ---- readers -----------------------------------------------------------------------------

std::uint32_t Map::num_keyframes() const noexcept {
  return num_keyframes_.load(std::memory_order_acquire);
}

std::uint32_t Map::num_points() const noexcept {
  return num_points_.load(std::memory_order_acquire);
}

void Map::reader_quiescent(int reader) noexcept {
  if (reader < 0 || reader >= kMaxMapReaders) return;
  readers_[reader].announced.store(epoch_.load(std::memory_order_acquire),
                                   std::memory_order_release);
}

KeyframeId Map::newest_keyframe() const noexcept {
  return newest_kf_.load(std::memory_order_acquire);
}

std::vector<StampedPose> Map::live_keyframe_poses(std::uint16_t segment) const {
  std::vector<StampedPose> poses;
  const KeyframeId n = num_keyframes();
  for (KeyframeId id = 0; id < n; ++id) {
    if (segment != kNoSegment && keyframe_segment(id) != segment) continue;
    SE3d T;
    if (keyframe_is_live(id) && keyframe_pose(id, T)) poses.push_back({keyframe_t_ns(id), T});
  }
  std::sort(poses.begin(), poses.end(),
            [](const StampedPose& a, const StampedPose& b) { return a.t_ns < b.t_ns; });
  return poses;
}

std::uint32_t Map::live_keyframes() const noexcept {
  return live_kfs_.load(std::memory_order_relaxed);
}

std::uint32_t Map::live_points() const noexcept {
  return live_pts_.load(std::memory_order_relaxed);
}

bool Map::keyframe_is_live(KeyframeId kf) const noexcept {
  return live_keyframe(kf);
}

Generation Map::keyframe_generation(KeyframeId kf) const noexcept {
  if (kf >= max_kf_) return kNoGeneration;
  const std::uint32_t st = kfs_[kf].state.load(std::memory_order_acquire);
  return is_live(st) ? generation_of(st) : kNoGeneration;
}

Generation Map::point_generation(PointId p) const noexcept {
  if (p >= max_pts_) return kNoGeneration;
  const std::uint32_t st = points_[p].state.load(std::memory_order_acquire);
  return is_live(st) ? generation_of(st) : kNoGeneration;
}

bool Map::keyframe_pose(KeyframeId kf, SE3d& T_w_c, double* scale) const noexcept {
  if (!live_keyframe(kf)) return false;
  const KeyframeSlot& s = kfs_[kf];
  std::uint64_t w[kPoseWords];
  if (!s.pose_lock.read([&] {
        for (int i = 0; i < kPoseWords; ++i) w[i] = load_payload(s.pose[i]);
      })) {
    return false;
  }
  T_w_c = decode_pose(w);
  if (scale != nullptr) *scale = unpack_double(w[kPoseScale]);
  return true;
}

std::span<const features::Keypoint> Map::keyframe_keypoints(KeyframeId kf) const noexcept {
  if (!live_keyframe(kf)) return {};
  return {&kf_keypoints_[kp_index(kf, 0)], kfs_[kf].num_keypoints};
}

std::span<const features::Descriptor> Map::keyframe_descriptors(KeyframeId kf) const noexcept {
  if (!live_keyframe(kf)) return {};
  return {&kf_descriptors_[kp_index(kf, 0)], kfs_[kf].num_keypoints};
}

std::uint32_t Map::keyframe_num_keypoints(KeyframeId kf) const noexcept {
  return live_keyframe(kf) ? kfs_[kf].num_keypoints : 0U;
}

std::int64_t Map::keyframe_t_ns(KeyframeId kf) const noexcept {
  return live_keyframe(kf) ? kfs_[kf].t_ns : 0;
}

std::uint64_t Map::keyframe_seq(KeyframeId kf) const noexcept {
  return live_keyframe(kf) ? kfs_[kf].seq : 0U;
}

std::uint16_t Map::keyframe_segment(KeyframeId kf) const noexcept {
  return live_keyframe(kf) ? kfs_[kf].segment.load(std::memory_order_relaxed) : kNoSegment;
}

PointId Map::keyframe_point(KeyframeId kf, std::uint32_t kp) const noexcept {
  if (!valid_keypoint(kf, kp)) return kNoId;
  return kf_points_[kp_index(kf, kp)].load(std::memory_order_acquire);
}

float Map::keyframe_depth(KeyframeId kf, std::uint32_t kp) const noexcept {
  if (!valid_keypoint(kf, kp)) return 0.0F;
  return kf_depth_[kp_index(kf, kp)].load(std::memory_order_relaxed);
}

float Map::keyframe_depth_confidence(KeyframeId kf, std::uint32_t kp) const noexcept {
  if (!valid_keypoint(kf, kp)) return 0.0F;
  return kf_depth_conf_[kp_index(kf, kp)].load(std::memory_order_relaxed);
}

bool Map::keyframe_point_3d(KeyframeId kf, std::uint32_t kp, const geometry::Pinhole& K,
                            Eigen::Vector3d& p_c) const noexcept {
  const float depth = keyframe_depth(kf, kp);
  if (!(depth > 0.0F)) return false;
  const features::Keypoint& k = kf_keypoints_[kp_index(kf, kp)];
  p_c = static_cast<double>(depth) *
        K.unproject({static_cast<double>(k.x), static_cast<double>(k.y)});
  return true;
}

bool Map::read_point(PointId p, PointView& out) const noexcept {
  if (p >= max_pts_) return false;
  const PointSlot& s = points_[p];
  if (!is_live(s.state.load(std::memory_order_acquire))) return false;
  std::uint64_t w[kPointWords];
  std::uint32_t state = 0;
  if (!s.lock.read([&] {
        state = load_payload(s.state);
        for (int i = 0; i < kPointWords; ++i) w[i] = load_payload(s.words[i]);
      })) {
    return false;
  }
  if (!is_live(state)) return false;
  decode_point(w, out);
  out.generation = generation_of(state);
  return true;
}

bool Map::point_is_bad(PointId p) const noexcept {
  return p >= max_pts_ || !is_live(points_[p].state.load(std::memory_order_acquire));
}

void Map::note_visible(PointId p) noexcept {
  if (p < max_pts_) pt_visible_[p].fetch_add(1U, std::memory_order_relaxed);
}

void Map::note_found(PointId p) noexcept {
  if (p < max_pts_) pt_found_[p].fetch_add(1U, std::memory_order_relaxed);
}

std::size_t Map::query_visible(const SE3d& T_w_c, const geometry::Pinhole& K, int width, int height,
                               double near, double far, std::uint16_t segment,
                               std::span<PointId> out) const noexcept {
  Frustum f;
  if (!Frustum::make(T_w_c, K, width, height, near, far, f)) return 0;
  return grid_.query_frustum(f, segment, out);
}

std::size_t Map::query_radius(const Eigen::Vector3d& c_w, double radius, std::uint16_t segment,
                              std::span<PointId> out) const noexcept {
  return grid_.query_radius(c_w, radius, segment, out);
}

std::size_t Map::memory_bytes() const noexcept {
  const std::size_t n_kp = std::size_t{max_kf_} * max_kp_;
  std::size_t b = sizeof(Map);
  b += max_kf_ * sizeof(KeyframeSlot);
  b += n_kp * (sizeof(features::Keypoint) + sizeof(features::Descriptor) +
               sizeof(std::atomic<PointId>) + 2 * sizeof(std::atomic<float>));
  b += std::size_t{max_kf_} * max_cov_ * sizeof(std::atomic<std::uint64_t>);
  b += max_pts_ * (sizeof(PointSlot) + sizeof(std::uint8_t) + sizeof(CellKey) +
                   2 * sizeof(std::atomic<std::uint32_t>) + sizeof(std::uint64_t) +
                   sizeof(std::uint16_t) + sizeof(Retired));
  b += max_kf_ * (sizeof(std::uint64_t) + sizeof(Retired));
  b += std::size_t{max_pts_} * max_obs_ * sizeof(Observation);
  b += max_kf_ * (sizeof(std::uint32_t) + sizeof(KeyframeId) + sizeof(CovisibleKeyframe));
  b += (max_cov_ + 1U) * sizeof(CovisibleKeyframe);
  b += (std::size_t{max_obs_} * max_obs_ + max_obs_) * sizeof(int);
  b += std::size_t{kMaxSegments} * kCorrectionWords * sizeof(std::atomic<std::uint64_t>);
  b += std::size_t{kMaxSegments} * sizeof(geometry::Sim3d);
  b += grid_.memory_bytes();
  return b;
}

}  // namespace mer::map
