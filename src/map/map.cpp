#include "map/map.h"

#include <algorithm>
#include <climits>
#include <cmath>
#include <string>

#include "map/map_internal.h"

namespace mer::map {

using map_detail::as_u32;
using map_detail::kFateLive;
using map_detail::kLow32Mask;

Map::Map(const MapOptions& opts)
    : opts_(effective_options(opts)),
      max_kf_(as_u32(opts_.max_keyframes)),
      max_pts_(as_u32(opts_.max_points)),
      max_kp_(as_u32(opts_.max_keypoints_per_keyframe)),
      max_obs_(as_u32(opts_.max_observations_per_point)),
      max_cov_(as_u32(opts_.max_covisible_per_keyframe)),
      kfs_(std::make_unique<KeyframeSlot[]>(max_kf_)),
      kf_keypoints_(std::make_unique<features::Keypoint[]>(std::size_t{max_kf_} * max_kp_)),
      kf_descriptors_(std::make_unique<features::Descriptor[]>(std::size_t{max_kf_} * max_kp_)),
      kf_points_(std::make_unique<std::atomic<PointId>[]>(std::size_t{max_kf_} * max_kp_)),
      kf_depth_(std::make_unique<std::atomic<float>[]>(std::size_t{max_kf_} * max_kp_)),
      kf_depth_conf_(std::make_unique<std::atomic<float>[]>(std::size_t{max_kf_} * max_kp_)),
      covis_(std::make_unique<std::atomic<std::uint64_t>[]>(std::size_t{max_kf_} * max_cov_)),
      points_(std::make_unique<PointSlot[]>(max_pts_)),
      pt_visible_(std::make_unique<std::atomic<std::uint32_t>[]>(max_pts_)),
      pt_found_(std::make_unique<std::atomic<std::uint32_t>[]>(max_pts_)),
      grid_(opts_.cell_size, as_u32(opts_.cell_table_size), as_u32(opts_.points_per_cell)),
      obs_(std::make_unique<Observation[]>(std::size_t{max_pts_} * max_obs_)),
      obs_count_(std::make_unique<std::uint8_t[]>(max_pts_)),
      point_cell_(std::make_unique<CellKey[]>(max_pts_)),
      kf_serial_(std::make_unique<std::uint64_t[]>(max_kf_)),
      pt_serial_(std::make_unique<std::uint64_t[]>(max_pts_)),
      pt_segment_(std::make_unique<std::uint16_t[]>(max_pts_)),
      kf_retired_(max_kf_),
      pt_retired_(max_pts_),
      covis_weight_(std::make_unique<std::uint32_t[]>(max_kf_)),
      covis_touched_(std::make_unique<KeyframeId[]>(max_kf_)),
      covis_sorted_(std::make_unique<CovisibleKeyframe[]>(max_kf_)),
      list_scratch_(std::make_unique<CovisibleKeyframe[]>(max_cov_ + 1U)),
      medoid_dist_(std::make_unique<int[]>(std::size_t{max_obs_} * max_obs_)),
      medoid_row_(std::make_unique<int[]>(max_obs_)),
      merge_scratch_(std::make_unique<Observation[]>(max_obs_)) {
  const std::size_t n_kp = std::size_t{max_kf_} * max_kp_;
  for (std::size_t i = 0; i < n_kp; ++i) kf_points_[i].store(kNoId, std::memory_order_relaxed);
  std::fill_n(point_cell_.get(), max_pts_, kNoCell);
  for (std::uint32_t i = 0; i < kMaxSegments; ++i) {
    merged_into_[i].store(kNoSegment, std::memory_order_relaxed);
    start_state_[i].store(SegmentStartState::kPending, std::memory_order_relaxed);
    fate_[i].store(kFateLive, std::memory_order_relaxed);
  }
}

// ---- writer ------------------------------------------------------------------------------

bool Map::live_keyframe(KeyframeId kf) const noexcept {
  return kf < max_kf_ && is_live(kfs_[kf].state.load(std::memory_order_acquire));
}

bool Map::valid_keypoint(KeyframeId kf, std::uint32_t kp) const noexcept {
  return live_keyframe(kf) && kp < kfs_[kf].num_keypoints;
}

bool Map::own_keyframe(KeyframeId kf) const noexcept {
  return kf < max_kf_ && is_live(load_own(kfs_[kf].state));
}

bool Map::own_point(PointId p) const noexcept {
  return p < max_pts_ && is_live(load_own(points_[p].state));
}

KeyframeId Map::own_ref_keyframe(PointId p) const noexcept {
  return static_cast<KeyframeId>(load_own(points_[p].words[kPointRef]) & kLow32Mask);
}

std::uint32_t Map::own_ref_keypoint(PointId p) const noexcept {
  return static_cast<std::uint32_t>(load_own(points_[p].words[kPointRef]) >> 32U);
}

std::uint64_t Map::retire_epoch() noexcept {
  epoch_own_ += 1U;
  epoch_.store(epoch_own_, std::memory_order_release);
  return epoch_own_;
}

bool Map::readers_passed(std::uint64_t epoch) const noexcept {
  for (const ReaderSlot& r : readers_) {
    const std::uint64_t a = r.announced.load(std::memory_order_acquire);
    if (a != kReaderUnused && a < epoch) return false;
  }
  return true;
}

std::uint32_t Map::take_slot(std::atomic<std::uint32_t>& high_water, std::uint32_t capacity,
                             RetireQueue& retired, std::uint64_t& reused) noexcept {
  const std::uint32_t used = high_water.load(std::memory_order_relaxed);
  if (used < capacity) return used;  // never-used slots first (published by the caller)
  if (retired.size == 0U || !readers_passed(retired.front().epoch)) return kNoId;
  const std::uint32_t id = retired.front().id;
  retired.pop();
  ++reused;
  return id;
}

SE3d Map::decode_pose(const std::uint64_t (&w)[kPoseWords]) noexcept {
  SE3d T = SE3d::Identity();
  for (int i = 0; i < 9; ++i) T.linear()(i % 3, i / 3) = unpack_double(w[kPoseRotation + i]);
  for (int i = 0; i < 3; ++i) T.translation()[i] = unpack_double(w[kPoseTranslation + i]);
  return T;
}

void Map::decode_point(const std::uint64_t (&w)[kPointWords], PointView& out) noexcept {
  for (int i = 0; i < 3; ++i) out.p_w[i] = unpack_double(w[kPointPosition + i]);
  for (std::size_t i = 0; i < out.descriptor.size(); ++i) {
    out.descriptor[i] = w[kPointDescriptor + static_cast<int>(i)];
  }
  out.normal = {low_float(w[kPointNormalXY]), high_float(w[kPointNormalXY]),
                low_float(w[kPointNormalZMin])};
  out.min_distance = high_float(w[kPointNormalZMin]);
  out.max_distance = low_float(w[kPointMax]);
  out.ref_keyframe = static_cast<KeyframeId>(w[kPointRef] & kLow32Mask);
  out.ref_keypoint = static_cast<std::uint32_t>(w[kPointRef] >> 32U);
}

SE3d Map::own_pose(KeyframeId kf) const noexcept {
  std::uint64_t w[kPoseWords];
  for (int i = 0; i < kPoseWords; ++i) w[i] = load_own(kfs_[kf].pose[i]);
  return decode_pose(w);
}

Eigen::Vector3d Map::own_position(PointId p) const noexcept {
  const auto& w = points_[p].words;
  Eigen::Vector3d p_w;
  for (int i = 0; i < 3; ++i) p_w[i] = unpack_double(load_own(w[kPointPosition + i]));
  return p_w;
}

void Map::write_pose(KeyframeId kf, const SE3d& T_w_c, double scale) noexcept {
  KeyframeSlot& s = kfs_[kf];
  s.pose_lock.write_begin();
  for (int i = 0; i < 9; ++i) {
    store_payload(s.pose[kPoseRotation + i], pack_double(T_w_c.linear()(i % 3, i / 3)));
  }
  for (int i = 0; i < 3; ++i) {
    store_payload(s.pose[kPoseTranslation + i], pack_double(T_w_c.translation()[i]));
  }
  store_payload(s.pose[kPoseScale], pack_double(scale));
  s.pose_lock.write_end();
}

void Map::write_position(PointId p, const Eigen::Vector3d& p_w) noexcept {
  PointSlot& s = points_[p];
  s.lock.write_begin();
  for (int i = 0; i < 3; ++i) store_payload(s.words[kPointPosition + i], pack_double(p_w[i]));
  s.lock.write_end();
}

void Map::write_shape(PointId p, const features::Descriptor& d, const Eigen::Vector3d& normal,
                      float min_d, float max_d) noexcept {
  PointSlot& s = points_[p];
  s.lock.write_begin();
  for (std::size_t i = 0; i < d.size(); ++i) {
    store_payload(s.words[kPointDescriptor + static_cast<int>(i)], d[i]);
  }
  const Eigen::Vector3f n = normal.cast<float>();
  store_payload(s.words[kPointNormalXY], pack_floats(n.x(), n.y()));
  store_payload(s.words[kPointNormalZMin], pack_floats(n.z(), min_d));
  store_payload(s.words[kPointMax], pack_floats(max_d, 0.0F));
  s.lock.write_end();
}

void Map::write_ref(PointId p, KeyframeId kf, std::uint32_t kp) noexcept {
  PointSlot& s = points_[p];
  s.lock.write_begin();
  store_payload(s.words[kPointRef], (static_cast<std::uint64_t>(kp) << 32U) | kf);
  s.lock.write_end();
}

void Map::write_point_state(PointId p, std::uint32_t state) noexcept {
  PointSlot& s = points_[p];
  s.lock.write_begin();
  store_payload(s.state, state);
  s.lock.write_end();
}

void Map::shape_from_ref(PointId p, const Eigen::Vector3d& p_w, Eigen::Vector3d& normal,
                         float& min_d, float& max_d) const noexcept {
  const KeyframeId ref_kf = own_ref_keyframe(p);
  const Eigen::Vector3d ray = p_w - own_pose(ref_kf).translation();
  const double dist = ray.norm();
  const float level_scale = kf_keypoints_[kp_index(ref_kf, own_ref_keypoint(p))].scale;
  max_d = static_cast<float>(dist * static_cast<double>(level_scale));
  min_d = static_cast<float>(static_cast<double>(max_d) / opts_.distance_scale_range);
  if (normal.squaredNorm() == 0.0 && dist > 0.0) normal = ray / dist;
}

Result<KeyframeId> Map::add_keyframe(const KeyframeInput& in) {
  const std::size_t n = in.keypoints.size();
  if (n > max_kp_) {
    return invalid_argument(
        "keyframe has " + std::to_string(n) +
        " keypoints, more than map.max_keypoints_per_keyframe = " + std::to_string(max_kp_));
  }
  if (in.descriptors.size() != n || (!in.depth.empty() && in.depth.size() != n) ||
      (!in.depth_confidence.empty() && in.depth_confidence.size() != n)) {
    return invalid_argument("keyframe: " + std::to_string(n) + " keypoints but " +
                            std::to_string(in.descriptors.size()) + " descriptors, " +
                            std::to_string(in.depth.size()) + " depths, " +
                            std::to_string(in.depth_confidence.size()) + " confidences");
  }
  if (!in.T_w_c.matrix().allFinite()) return invalid_argument("keyframe: non-finite pose");
  const std::uint32_t id = take_slot(num_keyframes_, max_kf_, kf_retired_, reused_kf_slots_);
  if (id == kNoId) {
    return runtime_error("map full: " + std::to_string(max_kf_) + " keyframes (" +
                         std::to_string(kf_retired_.size) +
                         " freed slots wait for a reader; raise map.max_keyframes)");
  }

  // The slot is not live: readers do not touch its plain memory until the state publishes it.
  KeyframeSlot& s = kfs_[id];
  s.seq = in.seq;
  s.t_ns = in.t_ns;
  s.segment.store(in.segment, std::memory_order_relaxed);
  s.num_keypoints = static_cast<std::uint32_t>(n);
  const std::size_t base = kp_index(id, 0);
  std::copy(in.keypoints.begin(), in.keypoints.end(), &kf_keypoints_[base]);
  std::copy(in.descriptors.begin(), in.descriptors.end(), &kf_descriptors_[base]);
  for (std::size_t i = 0; i < n; ++i) {
    kf_points_[base + i].store(kNoId, std::memory_order_relaxed);
    kf_depth_[base + i].store(in.depth.empty() ? 0.0F : in.depth[i], std::memory_order_relaxed);
    kf_depth_conf_[base + i].store(in.depth_confidence.empty() ? 0.0F : in.depth_confidence[i],
                                   std::memory_order_relaxed);
  }
  write_pose(id, in.T_w_c, 1.0);
  write_covis(id, nullptr, 0);
  kf_serial_[id] = kf_serial_next_++;
  s.state.store(load_own(s.state) | kLiveBit, std::memory_order_release);
  if (id >= num_keyframes_.load(std::memory_order_relaxed)) {
    num_keyframes_.store(id + 1U, std::memory_order_release);
  }
  newest_kf_.store(id, std::memory_order_release);
  live_kfs_.store(load_own(live_kfs_) + 1U, std::memory_order_relaxed);
  return id;
}

Result<PointId> Map::add_point(const Eigen::Vector3d& p_w, KeyframeId ref_kf,
                               std::uint32_t ref_kp) {
  if (!valid_keypoint(ref_kf, ref_kp)) {
    return invalid_argument("add_point: unknown keyframe " + std::to_string(ref_kf) +
                            " / keypoint " + std::to_string(ref_kp));
  }
  std::atomic<PointId>& assoc = kf_points_[kp_index(ref_kf, ref_kp)];
  if (load_own(assoc) != kNoId) {
    return invalid_argument("add_point: keypoint " + std::to_string(ref_kp) + " of keyframe " +
                            std::to_string(ref_kf) + " already has a point");
  }
  if (!p_w.allFinite()) return invalid_argument("add_point: non-finite position");
  const std::uint32_t id = take_slot(num_points_, max_pts_, pt_retired_, reused_pt_slots_);
  if (id == kNoId) {
    return runtime_error("map full: " + std::to_string(max_pts_) + " points (" +
                         std::to_string(pt_retired_.size) +
                         " freed slots wait for a reader; raise map.max_points)");
  }

  // Written while not live (a reader's snapshot of it fails), then published by the state.
  write_ref(id, ref_kf, ref_kp);
  write_position(id, p_w);
  Eigen::Vector3d normal = Eigen::Vector3d::Zero();
  float min_d = 0.0F;
  float max_d = 0.0F;
  shape_from_ref(id, p_w, normal, min_d, max_d);
  write_shape(id, kf_descriptors_[kp_index(ref_kf, ref_kp)], normal, min_d, max_d);
  pt_visible_[id].store(1, std::memory_order_relaxed);  // the creating keyframe saw it
  pt_found_[id].store(1, std::memory_order_relaxed);
  pt_serial_[id] = kf_serial_next_;
  pt_segment_[id] = kfs_[ref_kf].segment.load(std::memory_order_relaxed);
  obs_[std::size_t{id} * max_obs_] = Observation::make(ref_kf, ref_kp);
  obs_count_[id] = 1;
  write_point_state(id, load_own(points_[id].state) | kLiveBit);
  if (id >= num_points_.load(std::memory_order_relaxed)) {
    num_points_.store(id + 1U, std::memory_order_release);
  }
  live_pts_.store(load_own(live_pts_) + 1U, std::memory_order_relaxed);

  assoc.store(id, std::memory_order_release);
  const CellKey key = grid_.key_of(p_w, pt_segment_[id]);
  point_cell_[id] = grid_.insert(id, key) ? key : kNoCell;
  return id;
}

bool Map::add_observation(PointId p, KeyframeId kf, std::uint32_t kp) {
  if (!own_point(p) || !valid_keypoint(kf, kp)) return false;
  std::atomic<PointId>& assoc = kf_points_[kp_index(kf, kp)];
  if (load_own(assoc) != kNoId) return false;
  const std::uint32_t n = obs_count_[p];
  if (n >= max_obs_) return false;
  Observation* o = &obs_[std::size_t{p} * max_obs_];
  for (std::uint32_t i = 0; i < n; ++i) {
    if (o[i].kf() == kf) return false;
  }
  o[n] = Observation::make(kf, kp);
  obs_count_[p] = static_cast<std::uint8_t>(n + 1U);
  assoc.store(p, std::memory_order_release);
  return true;
}

void Map::update_point(PointId p) {
  if (!own_point(p)) return;
  const std::uint32_t n = obs_count_[p];
  if (n == 0) return;
  const Observation* o = &obs_[std::size_t{p} * max_obs_];

  // Medoid under Hamming: least median distance to all observation descriptors (the
  // median taken over the row including the zero self-distance, as ORB-SLAM does).
  int* dist = medoid_dist_.get();
  for (std::uint32_t i = 0; i < n; ++i) {
    dist[i * n + i] = 0;
    const features::Descriptor& di = kf_descriptors_[kp_index(o[i].kf(), o[i].kp())];
    for (std::uint32_t j = i + 1; j < n; ++j) {
      const int d = features::hamming(di, kf_descriptors_[kp_index(o[j].kf(), o[j].kp())]);
      dist[i * n + j] = d;
      dist[j * n + i] = d;
    }
  }
  std::uint32_t best = 0;
  int best_median = INT_MAX;
  int* row = medoid_row_.get();
  const std::uint32_t mid = (n - 1U) / 2U;
  for (std::uint32_t i = 0; i < n; ++i) {
    std::copy_n(&dist[i * n], n, row);
    std::nth_element(row, row + mid, row + n);
    if (row[mid] < best_median) {
      best_median = row[mid];
      best = i;
    }
  }

  const Eigen::Vector3d p_w = own_position(p);
  Eigen::Vector3d normal = Eigen::Vector3d::Zero();
  for (std::uint32_t i = 0; i < n; ++i) {
    const Eigen::Vector3d ray = p_w - own_pose(o[i].kf()).translation();
    const double len = ray.norm();
    if (len > 0.0) normal += ray / len;
  }
  const double len = normal.norm();
  normal = len > 0.0 ? Eigen::Vector3d(normal / len) : Eigen::Vector3d::Zero();
  float min_d = 0.0F;
  float max_d = 0.0F;
  shape_from_ref(p, p_w, normal, min_d, max_d);
  write_shape(p, kf_descriptors_[kp_index(o[best].kf(), o[best].kp())], normal, min_d, max_d);
}

void Map::set_point_position(PointId p, const Eigen::Vector3d& p_w) {
  if (!own_point(p) || !p_w.allFinite()) return;
  write_position(p, p_w);
  const CellKey key = grid_.key_of(p_w, pt_segment_[p]);
  if (key == point_cell_[p]) return;
  point_cell_[p] = grid_.move(p, point_cell_[p], key) ? key : kNoCell;
}

void Map::set_keyframe_pose(KeyframeId kf, const SE3d& T_w_c, double scale) {
  if (!own_keyframe(kf)) return;
  if (!T_w_c.matrix().allFinite() || !std::isfinite(scale)) return;
  write_pose(kf, T_w_c, scale);
}

bool Map::set_keypoint_position(KeyframeId kf, std::uint32_t kp, float x, float y) {
  if (!valid_keypoint(kf, kp) || !std::isfinite(x) || !std::isfinite(y)) return false;
  features::Keypoint& k = kf_keypoints_[kp_index(kf, kp)];
  k.x = x;
  k.y = y;
  return true;
}

bool Map::set_keypoint_anchored(KeyframeId kf, std::uint32_t kp, bool anchored) {
  if (!valid_keypoint(kf, kp)) return false;
  kf_keypoints_[kp_index(kf, kp)].anchored = anchored ? 1 : 0;
  return true;
}

void Map::set_keyframe_depth(KeyframeId kf, std::uint32_t kp, float depth, float confidence) {
  if (!valid_keypoint(kf, kp)) return;
  kf_depth_[kp_index(kf, kp)].store(depth, std::memory_order_relaxed);
  kf_depth_conf_[kp_index(kf, kp)].store(confidence, std::memory_order_relaxed);
}

void Map::set_point_bad(PointId p) {
  if (!own_point(p)) return;
  write_point_state(p, freed(load_own(points_[p].state)));
  grid_.remove(p, point_cell_[p]);
  point_cell_[p] = kNoCell;
  const Observation* o = &obs_[std::size_t{p} * max_obs_];
  for (std::uint32_t i = 0; i < obs_count_[p]; ++i) {
    const std::size_t at = kp_index(o[i].kf(), o[i].kp());
    std::atomic<PointId>& assoc = kf_points_[at];
    if (load_own(assoc) == p) {
      assoc.store(kNoId, std::memory_order_release);
      kf_keypoints_[at].anchored = 0;
    }
  }
  obs_count_[p] = 0;
  live_pts_.store(load_own(live_pts_) - 1U, std::memory_order_relaxed);
  ++bad_points_;
  pt_retired_.push(p, retire_epoch());  // unlinked: the epoch orders it before reuse
}

int Map::merge_points(PointId keep, PointId drop) {
  if (keep == drop || !own_point(keep) || !own_point(drop)) return -1;
  const std::uint32_t n = obs_count_[drop];
  // set_point_bad clears drop's list: copy it first (at most max_obs_ entries).
  Observation* moved = merge_scratch_.get();
  std::copy_n(&obs_[std::size_t{drop} * max_obs_], n, moved);
  set_point_bad(drop);
  int count = 0;
  for (std::uint32_t i = 0; i < n; ++i) {
    if (add_observation(keep, moved[i].kf(), moved[i].kp())) ++count;
  }
  if (count > 0) update_point(keep);
  ++merged_points_;
  return count;
}

bool Map::remove_keyframe(KeyframeId kf, std::uint32_t min_point_observations,
                          std::uint32_t* bad_points) {
  if (bad_points != nullptr) *bad_points = 0;
  if (!own_keyframe(kf) || kf == newest_kf_.load(std::memory_order_relaxed)) return false;
  KeyframeSlot& s = kfs_[kf];
  s.state.store(freed(load_own(s.state)), std::memory_order_release);

  // Every edge to kf (lists are capped, so a neighbour may hold an edge kf does not).
  const std::uint32_t used = num_keyframes_.load(std::memory_order_relaxed);
  for (KeyframeId other = 0; other < used; ++other) {
    if (other != kf && own_keyframe(other)) remove_edge(other, kf);
  }
  write_covis(kf, nullptr, 0);

  // Its observations leave its points; points left with too few observations are freed.
  const std::uint32_t min_obs = std::max(1U, min_point_observations);
  const std::uint32_t nkp = s.num_keypoints;
  for (std::uint32_t kp = 0; kp < nkp; ++kp) {
    std::atomic<PointId>& assoc = kf_points_[kp_index(kf, kp)];
    const PointId p = load_own(assoc);
    if (p == kNoId) continue;
    assoc.store(kNoId, std::memory_order_release);
    if (!own_point(p)) continue;
    Observation* o = &obs_[std::size_t{p} * max_obs_];
    const std::uint32_t n = obs_count_[p];
    Observation* end = std::remove_if(o, o + n, [&](Observation x) { return x.kf() == kf; });
    const auto m = static_cast<std::uint32_t>(end - o);
    obs_count_[p] = static_cast<std::uint8_t>(m);
    if (m < min_obs) {
      set_point_bad(p);
      if (bad_points != nullptr) ++*bad_points;
      continue;
    }
    if (own_ref_keyframe(p) == kf) {  // the oldest remaining observation becomes the reference
      write_ref(p, o[0].kf(), o[0].kp());
      update_point(p);
    }
  }
  live_kfs_.store(load_own(live_kfs_) - 1U, std::memory_order_relaxed);
  ++removed_keyframes_;
  kf_retired_.push(kf, retire_epoch());
  return true;
}

}  // namespace mer::map
