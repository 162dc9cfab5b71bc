// The tracker's state machine (tracker.h): tracking, lost, relocalizing and map segments;
// relocalization hints and their checks against the motion since the loss; a segment's start
// and failed starts; loop corrections and segment merges followed.
#include <algorithm>
#include <cmath>
#include <numbers>

#include "core/median.h"
#include "frontend/tracker.h"
#include "platform/log_ring.h"

namespace mer::frontend {
namespace {

constexpr double kRadToDeg = 180.0 / std::numbers::pi;

}  // namespace

void Tracker::advance_state(TrackingResult& r) {
  if (r.state == TrackState::kTracked) {
    state_ = TrackerState::kTracking;
    // The velocity the motion bound carries the last pose on with: from two consecutive
    // tracked frames of one segment, at rest otherwise.
    const double dt = static_cast<double>(r.t_ns - last_tracked_t_ns_) * 1e-9;
    last_tracked_omega_.setZero();
    last_tracked_velocity_.setZero();
    if (lost_frames_ == 0 && last_tracked_segment_ == segment_ && last_tracked_t_ns_ > 0 &&
        dt > 0.0) {
      const Eigen::AngleAxisd turn(T_c_w_.linear() * last_tracked_T_c_w_.linear().transpose());
      last_tracked_omega_ = turn.axis() * (turn.angle() / dt);
      last_tracked_velocity_ =
          (T_c_w_.inverse().translation() - last_tracked_T_c_w_.inverse().translation()) / dt;
    }
    lost_frames_ = 0;
    spell_places_used_ = 0;  // a new spell weighs its own offers
    last_tracked_t_ns_ = r.t_ns;
    last_tracked_T_c_w_ = T_c_w_;
    last_tracked_segment_ = segment_;
    last_tracked_median_depth_ = median_depth_;
  } else if (!initialized_ && !other_segment_kept()) {
    state_ = TrackerState::kInitializing;  // the first map: nothing to relocalize against
  } else {
    if (lost_frames_ == 0) {
      ++counters_.lost_spells;
      if (count_failed_start(r) && opts_.init.discard_failed_starts) discard_failed_start(r);
    }
    ++lost_frames_;
    counters_.max_lost_frames = std::max(counters_.max_lost_frames, lost_frames_);
    if (initialized_) {
      state_ = relocalization_available_ &&
                       lost_frames_ > static_cast<std::uint64_t>(opts_.relocalize_after_lost_frames)
                   ? TrackerState::kRelocalizing
                   : TrackerState::kLost;
      const double lost_s = static_cast<double>(r.t_ns - last_tracked_t_ns_) * 1e-9;
      // (Not while a relocalization is being confirmed: it may yet bring the map back.)
      if (opts_.new_segments && !candidate_ && lost_s >= opts_.new_segment_after_s &&
          segments_started_ < opts_.max_segments) {
        start_new_segment(r.seq);
      }
    }
    if (!initialized_) {
      state_ = other_segment_kept() ? TrackerState::kNewSegment : TrackerState::kInitializing;
    }
  }
  r.tracker_state = state_;
  r.segment = segment_;
  r.relocalization_request = !candidate_ &&
                             (state_ == TrackerState::kRelocalizing ||
                              (state_ == TrackerState::kNewSegment && relocalization_available_)) &&
                             !long_loss_merges(r.t_ns);
  if (r.relocalization_request) ++counters_.relocalization_requests;
}

bool Tracker::long_loss_merges(std::int64_t t_ns) const {
  const RelocalizationCheckOptions& o = opts_.relocalization_check;
  if (!o.enabled || o.after_long_loss != LongLossReturn::kMerge) return false;
  // Only where a new segment can hold the frames; otherwise the relocalizer is the only way
  // back and keeps looking.
  if (!opts_.new_segments || segments_started_ >= opts_.max_segments) return false;
  if (state_ == TrackerState::kNewSegment) return true;  // lost for long: a new segment's turn
  return static_cast<double>(t_ns - last_tracked_t_ns_) * 1e-9 > o.short_loss_s;
}

bool Tracker::count_failed_start(const TrackingResult& r) {
  if (!initialized_ || segment_ != start_segment_ || start_t_ns_ == 0) return false;
  const double since_start_s = static_cast<double>(r.t_ns - start_t_ns_) * 1e-9;
  if (since_start_s >= opts_.init.failed_start_window_s ||
      start_keyframes_ > static_cast<std::uint32_t>(opts_.init.failed_start_max_keyframes)) {
    return false;
  }
  ++counters_.failed_starts;
  start_t_ns_ = 0;  // once per start
  MER_LOG_INFO(
      "frame %llu: lost %.2f s after the start of segment %u with %u keyframes: a "
      "failed start",
      static_cast<unsigned long long>(r.seq), since_start_s, unsigned{segment_}, start_keyframes_);
  return true;
}

void Tracker::discard_failed_start(TrackingResult& r) {
  // Its segment id is spent: without one left for the next start, the segment is kept.
  if (segments_started_ >= opts_.max_segments || !map_.discard_segment(segment_)) return;
  MER_LOG_INFO("frame %llu: segment %u discarded; initializing segment %u",
               static_cast<unsigned long long>(r.seq), unsigned{segment_},
               unsigned{segments_started_});
  r.discarded_start = true;
  r.discarded_segment = segment_;
  ++counters_.discarded_starts;
  ++segments_discarded_;
  begin_next_segment();
  if (!other_segment_kept()) {
    // No start is kept: the next one is the map's first (initialized_seq, reference_seq).
    counters_.initialized = false;
    counters_.initialized_seq = 0;
    counters_.reference_seq = 0;
  }
}

void Tracker::start_new_segment(std::uint64_t seq) {
  MER_LOG_INFO("frame %llu: lost for %llu frames without relocalizing; starting map segment %u",
               static_cast<unsigned long long>(seq), static_cast<unsigned long long>(lost_frames_),
               unsigned{segments_started_});
  ++counters_.new_segments;
  begin_next_segment();
}

void Tracker::begin_next_segment() {
  segment_ = segments_started_++;
  initialized_ = false;
  initializer_.drop_reference();
  have_pose_ = false;
  poor_prediction_ = true;
  velocity_ = SE3d::Identity();
  histogram_.clear();
  for (KeyframeHistogram& h : recent_) h.clear();
  recent_valid_ = 0;  // the dense backends' recent frames are in the old world frame
  reloc_keyframe_ = map::kNoId;
  force_keyframe_ = false;
}

Tracker::MotionBound Tracker::motion_bound(const SE3d& T_c_w, std::int64_t t_ns,
                                           std::uint16_t segment) const {
  const RelocalizationCheckOptions& o = opts_.relocalization_check;
  const double lost_s = static_cast<double>(t_ns - last_tracked_t_ns_) * 1e-9;
  if (segment != last_tracked_segment_ || lost_s > o.short_loss_s) return MotionBound::kNone;
  // Where the last tracked velocity was taking the camera.
  const double w = last_tracked_omega_.norm();
  const Eigen::Matrix3d R_pred =
      (w > 0.0 ? Eigen::AngleAxisd(w * lost_s, last_tracked_omega_ / w).toRotationMatrix()
               : Eigen::Matrix3d::Identity()) *
      last_tracked_T_c_w_.linear();
  const Eigen::Vector3d c_pred =
      last_tracked_T_c_w_.inverse().translation() + last_tracked_velocity_ * lost_s;
  const double moved = (T_c_w.inverse().translation() - c_pred).norm();
  const double turned_deg =
      Eigen::AngleAxisd(T_c_w.linear() * R_pred.transpose()).angle() * kRadToDeg;
  const double half_t2 = 0.5 * lost_s * lost_s;
  const double max_moved =
      (o.max_accel_depths_per_s2 * half_t2 + o.margin_depths) * last_tracked_median_depth_;
  const double max_turned_deg = o.max_angular_accel_deg_per_s2 * half_t2 + o.margin_deg;
  MER_LOG_DEBUG(
      "relocalization after %.2f s: %.3f from the predicted position (bound %.3f), %.1f deg "
      "from the predicted orientation (bound %.1f)",
      lost_s, moved, max_moved, turned_deg, max_turned_deg);
  return moved <= max_moved && turned_deg <= max_turned_deg ? MotionBound::kWithin
                                                            : MotionBound::kOutside;
}

int Tracker::place_refusals(map::KeyframeId kf) const {
  int n = 0;
  for (std::size_t i = 0; i < spell_places_used_; ++i) {
    const SpellPlace& p = spell_places_[i];
    if (map_.keyframe_generation(p.kf) != p.generation) continue;  // gone since
    if (p.kf == kf || map_.covisibility_weight(p.kf, kf) > 0) n += p.refusals;
  }
  return n;
}

void Tracker::count_place_refusal(map::KeyframeId kf, map::Generation gen) {
  if (kf == map::kNoId) return;
  std::size_t least = 0;
  for (std::size_t i = 0; i < spell_places_used_; ++i) {
    SpellPlace& p = spell_places_[i];
    if (p.kf == kf && p.generation == gen) {
      ++p.refusals;
      return;
    }
    if (p.refusals < spell_places_[least].refusals) least = i;
  }
  const std::size_t slot = spell_places_used_ < kSpellPlaces ? spell_places_used_++ : least;
  spell_places_[slot] = SpellPlace{kf, gen, 1};
}

double Tracker::recent_found_share() const {
  if (found_valid_ == 0) return 0.0;
  std::array<float, kFoundHistory> v = found_share_;  // a copy: the ring keeps its order
  return upper_median(v.begin(), v.begin() + static_cast<std::ptrdiff_t>(found_valid_));
}

void Tracker::reject_candidate() {
  count_place_refusal(candidate_kf_, candidate_generation_);
  candidate_ = false;
  candidate_frames_ = 0;
  reloc_keyframe_ = map::kNoId;
  T_c_w_ = last_tracked_T_c_w_;
  median_depth_ = last_tracked_median_depth_;
  have_pose_ = false;
  poor_prediction_ = true;
  velocity_ = SE3d::Identity();
  if (candidate_returning_) {  // back to the segment it returned from
    segment_ = candidate_segment_before_;
    initialized_ = candidate_initialized_before_;
    candidate_returning_ = false;
  }
}

bool Tracker::return_to_segment_of_hint() {
  const std::uint16_t seg = map_.keyframe_segment(hint_.keyframe);
  if (seg == map::kNoSegment || map_.segment_discarded(seg) ||
      map_.keyframe_generation(hint_.keyframe) != hint_.generation) {
    return false;
  }
  // The query's depth range: that keyframe's median keypoint depth (its segment's scale).
  depth_scratch_.clear();
  const std::uint32_t n = map_.keyframe_num_keypoints(hint_.keyframe);
  for (std::uint32_t k = 0; k < n && depth_scratch_.size() < depth_scratch_.capacity(); ++k) {
    const float d = map_.keyframe_depth(hint_.keyframe, k);
    if (d > 0.0F) depth_scratch_.push_back(d);
  }
  if (!depth_scratch_.empty()) median_depth_ = std::max(upper_median(depth_scratch_), 1e-6);
  segment_ = seg;
  initialized_ = true;  // (a new segment's two-view reference is kept: the return may fail)
  anchor_kf_ = hint_.keyframe;
  anchor_generation_ = hint_.generation;
  return true;
}

void Tracker::reserve_relocalization_request(RelocalizationRequest& req) const {
  const auto n = static_cast<std::size_t>(max_keypoints());
  req.keypoints.resize(n);
  req.descriptors.resize(n);
  req.count = 0;
}

void Tracker::fill_relocalization_request(const hal::Frame& frame,
                                          RelocalizationRequest& req) const {
  const std::size_t n = std::min({kps_.size(), req.keypoints.size(), req.descriptors.size()});
  std::copy_n(kps_.begin(), n, req.keypoints.begin());
  std::copy_n(descs_.begin(), n, req.descriptors.begin());
  req.count = n;
  req.seq = frame.seq;
  req.t_ns = frame.t_ns;
  req.K = K_;
}

void Tracker::set_relocalization_hint(const RelocalizationHint& hint) {
  if (!hint.valid || start_pending_ ||
      (state_ != TrackerState::kRelocalizing && state_ != TrackerState::kNewSegment)) {
    return;
  }
  hint_ = hint;
  ++counters_.relocalization_hints;
}

void Tracker::keyframe_not_queued() {
  if (start_to_queue_) {
    // The segment's start found no free job: initialize again from the next frames (the
    // reference is kept).
    start_to_queue_ = false;
    start_pending_ = false;
    initialized_ = false;
    have_pose_ = false;
    ++counters_.segment_starts_not_queued;
    return;
  }
  force_keyframe_ = true;
}

void Tracker::begin_segment_start(TrackingResult& r) {
  start_to_queue_ = true;
  start_pending_ = true;
  r.is_keyframe = true;
  r.keyframe_job = true;
  r.keyframe_reason = static_cast<std::uint8_t>(KeyframeReason::kInitialization);
  last_reason_ = r.keyframe_reason;
}

Tracker::StartPoll Tracker::poll_segment_start() {
  const map::SegmentStartRecord rec = map_.segment_start(segment_);
  if (rec.state == map::SegmentStartState::kPending) return StartPoll::kPending;
  start_pending_ = false;
  if (rec.state == map::SegmentStartState::kRefused) {
    // Never written (map full): this segment id holds nothing; initialize the next one.
    ++counters_.segment_starts_refused;
    initialized_ = false;
    initializer_.drop_reference();
    have_pose_ = false;
    poor_prediction_ = true;
    if (segments_started_ >= opts_.max_segments) {
      MER_LOG_WARN("map segment %u: its start was refused by the map (no segment id left)",
                   unsigned{segment_});
      return StartPoll::kRefused;
    }
    MER_LOG_WARN("map segment %u: its start was refused by the map; starting segment %u",
                 unsigned{segment_}, unsigned{segments_started_});
    segment_ = segments_started_++;
    return StartPoll::kRefused;
  }
  // In the map: the tracked-point histogram of the start frame (every point was made in the
  // first keyframe) and the anchor for the frames that follow.
  histogram_.clear();
  for (int i = 0; i < initializer_.start_points(); ++i) histogram_.add(rec.first);
  recent_[recent_next_] = histogram_;
  recent_next_ = (recent_next_ + 1) % recent_.size();
  anchor_kf_ = rec.last;
  anchor_generation_ = map_.keyframe_generation(rec.last);
  return StartPoll::kInserted;
}

void Tracker::follow_map_correction() {
  const std::uint32_t total = map_.correction_count();
  if (total == correction_count_seen_ && segment_ == correction_segment_) return;
  // A merge moves the tracked segment into another one's frame and publishes that as a
  // correction of it: follow the correction, then the segment it joined (bounded: each merge
  // joins a segment that has not merged itself).
  for (std::uint32_t hop = 0; hop < map::kMaxSegments; ++hop) {
    geometry::Sim3d S;
    std::uint32_t count = 0;
    if (!map_.read_correction(segment_, S, count)) return;  // retried at the next frame
    correction_count_seen_ = total;
    if (segment_ != correction_segment_) {
      // Tracking is in another segment since the last frame (a new one, or a return to an
      // earlier one): its pose came from that segment's map as it is now, corrections
      // included.
      correction_segment_ = segment_;
      correction_seen_ = S;
      correction_segment_count_ = count;
      return;
    }
    if (count != correction_segment_count_) {
      // The part published since the last frame: S * seen^-1.
      apply_correction(S * correction_seen_.inverse());
      correction_seen_ = S;
      correction_segment_count_ = count;
    }
    map::SegmentMerge m;
    if (!map_.segment_merge(segment_, m) || count < m.from_count) return;
    // Merged (and its move followed): the frame is now that of `into`, as it was at the merge.
    MER_LOG_INFO("tracking follows the merge of map segment %u into segment %u", unsigned{segment_},
                 unsigned{m.into});
    if (last_tracked_segment_ == segment_) {
      last_tracked_segment_ = m.into;
    }
    if (candidate_segment_before_ == segment_) candidate_segment_before_ = m.into;
    segment_ = m.into;
    correction_segment_ = m.into;
    correction_seen_ = m.into_correction;
    correction_segment_count_ = m.into_count;
    ++counters_.segment_merges_followed;
  }
}

void Tracker::apply_correction(const geometry::Sim3d& D) {
  if (have_pose_) T_c_w_ = geometry::apply_to_pose(D, T_c_w_.inverse()).inverse();
  last_T_w_c_ = geometry::apply_to_pose(D, last_T_w_c_);
  for (SE3d& T : recent_T_w_c_) T = geometry::apply_to_pose(D, T);
  velocity_.translation() *= D.s;
  median_depth_ *= D.s;
  if (last_tracked_segment_ == segment_) {
    // The motion bound's reference moves with the map (velocities in its units).
    last_tracked_T_c_w_ = geometry::apply_to_pose(D, last_tracked_T_c_w_.inverse()).inverse();
    last_tracked_velocity_ = D.s * (D.R * last_tracked_velocity_);
    last_tracked_omega_ = D.R * last_tracked_omega_;
    last_tracked_median_depth_ *= D.s;
  }
  MER_LOG_INFO("tracking follows a map correction of segment %u (scale %.4f, shift %.3f)",
               unsigned{segment_}, D.s, D.t.norm());
}

void Tracker::set_anchor(TrackingResult& r) {
  // The newest keyframe: the smallest offset. (The keyframe most tracked points come from,
  // ORB-SLAM's reference keyframe, gave 10-40 % larger errors on room_orbit seeds 1, 2, 5.)
  map::KeyframeId kf = map_.newest_keyframe();
  if (kf != map::kNoId && map_.keyframe_segment(kf) == segment_) {
    anchor_kf_ = kf;
    anchor_generation_ = map_.keyframe_generation(kf);
  } else if (anchor_kf_ != map::kNoId &&
             map_.keyframe_generation(anchor_kf_) == anchor_generation_ &&
             map_.keyframe_segment(anchor_kf_) == segment_) {
    kf = anchor_kf_;  // the newest is another segment's (a return, before its keyframe is made)
  } else {
    return;
  }
  SE3d T_w_kf;
  if (!map_.keyframe_pose(kf, T_w_kf)) return;
  r.has_anchor = true;
  r.anchor_t_ns = map_.keyframe_t_ns(kf);
  r.T_kf_c = T_w_kf.inverse() * r.T_w_c;
}

bool Tracker::take_hint(const hal::Frame& frame) {
  // A relocalizer's pose (a frame of this lost spell) replaces the last tracked pose. Within
  // the motion bound it is trusted at once; otherwise it is a candidate that the following
  // frames must confirm (tracking.relocalization_check).
  const RelocalizationCheckOptions& check = opts_.relocalization_check;
  bool from_hint = !candidate_ && hint_.valid &&
                   (state_ == TrackerState::kRelocalizing || state_ == TrackerState::kNewSegment);
  const MotionBound bound = from_hint && check.enabled
                                ? motion_bound(hint_.T_c_w, frame.t_ns, segment_)
                                : MotionBound::kWithin;
  if (from_hint && bound == MotionBound::kNone && long_loss_merges(frame.t_ns)) {
    // After a long loss the camera comes back only through a merge (after_long_loss: merge).
    ++counters_.relocalization_rejected_long_loss;
    from_hint = false;
  }
  if (from_hint && bound == MotionBound::kOutside) {
    // After a short loss the camera cannot be there: searched from the last pose instead.
    ++counters_.relocalization_rejected_bound;
    count_place_refusal(hint_.keyframe, hint_.generation);
    MER_LOG_INFO(
        "frame %llu: relocalization against the keyframe of frame %llu refused (outside the "
        "motion bound)",
        static_cast<unsigned long long>(frame.seq),
        static_cast<unsigned long long>(map_.keyframe_seq(hint_.keyframe)));
    from_hint = false;
  }
  if (!candidate_) reloc_keyframe_ = map::kNoId;
  if (from_hint) {
    T_c_w_ = hint_.T_c_w;
    have_pose_ = false;
    poor_prediction_ = true;
    reloc_keyframe_ = hint_.keyframe;
    reloc_generation_ = hint_.generation;
    // (Threaded: the relocalizer's pose may be of a frame some frames back.)
    hint_frames_ = frame.seq > hint_.seq ? frame.seq - hint_.seq : 1U;
    if (bound == MotionBound::kWithin) {
      ++counters_.relocalization_trusted;
    } else {
      candidate_ = true;
      candidate_frames_ = 0;
      candidate_min_ratio_ = std::numeric_limits<double>::infinity();
      candidate_kf_ = hint_.keyframe;
      candidate_generation_ = hint_.generation;
      // The place's refused offers of this spell: as many more frames must confirm it.
      const int refused = place_refusals(hint_.keyframe);
      candidate_required_ = std::max(
          check.confirm_frames, std::min(check.max_confirm_frames, check.confirm_frames + refused));
      if (refused > 0) ++counters_.relocalization_longer_checks;
      ++counters_.relocalization_candidates;
      MER_LOG_INFO(
          "frame %llu: relocalization candidate against the keyframe of frame %llu (its place "
          "refused %d times in this lost spell): %d frames to confirm it",
          static_cast<unsigned long long>(frame.seq),
          static_cast<unsigned long long>(map_.keyframe_seq(hint_.keyframe)), refused,
          candidate_required_);
    }
  }
  hint_.valid = false;
  return from_hint;
}

bool Tracker::confirm_candidate(const hal::Frame& frame, double found, TrackingResult& r,
                                bool& confirmed) {
  const RelocalizationCheckOptions& check = opts_.relocalization_check;
  // A confirming frame must see the place, not only a pattern it shares with another one.
  const double usual = recent_found_share();
  candidate_min_ratio_ = std::min(candidate_min_ratio_, usual > 0.0 ? found / usual : 0.0);
  if (found < check.min_found_fraction * usual) {
    ++counters_.relocalization_rejected_found;
    MER_LOG_INFO(
        "frame %llu: relocalization refused (found %d of %d map-points in view, a share of "
        "%.2f against %.2f usually)",
        static_cast<unsigned long long>(frame.seq), r.num_inliers, last_in_view_, found, usual);
    r.state = TrackState::kLost;
    ++counters_.lost;
    reject_candidate();
    return false;
  }
  if (++candidate_frames_ < candidate_required_) {
    // Tracked from the candidate: the next frame is predicted from here; nothing is
    // reported or written until it is confirmed.
    r.state = TrackState::kLost;
    ++counters_.lost;
    return false;
  }
  candidate_ = false;
  confirmed = true;
  ++counters_.relocalization_confirmed;
  if (candidate_returning_) ++counters_.segment_returns;
  candidate_returning_ = false;
  return true;
}

}  // namespace mer::frontend
