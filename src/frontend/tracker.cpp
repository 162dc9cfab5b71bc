#include "frontend/tracker.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <mutex>

#include "core/chi2.h"
#include "core/median.h"
#include "geometry/depth_sampling.h"
#include "platform/clock.h"
#include "platform/log_ring.h"

namespace mer::frontend {
namespace {

constexpr std::uint64_t kFnvOffset = 1469598103934665603ULL;
constexpr std::uint64_t kFnvPrime = 1099511628211ULL;
constexpr int kNoMatch = -1;
constexpr int kMaxRecentKeyframes = 64;    // distinct keyframes Q_T may draw from
constexpr double kReferenceWidth = 640.0;  // extractor.num_features is meant for this size
constexpr double kReferenceHeight = 480.0;
constexpr double kQueryNearFraction = 0.05;  // Q_S near plane, fraction of the median depth

// Re-projects the rotation onto SO(3): products of poses must not accumulate scale/shear.
SE3d orthonormalized(const SE3d& T) {
  SE3d out = T;
  out.linear() = Eigen::Quaterniond(T.linear()).normalized().toRotationMatrix();
  return out;
}

// A share f of the motion T: rotation angle and translation scaled by f (a frame's share of
// a motion over several frames; exact for constant motion to first order in the rotation).
SE3d fraction_of_motion(const SE3d& T, double f) {
  const Eigen::AngleAxisd aa(T.linear());
  SE3d out = SE3d::Identity();
  out.linear() = Eigen::AngleAxisd(aa.angle() * f, aa.axis()).toRotationMatrix();
  out.translation() = T.translation() * f;
  return out;
}

std::int32_t elapsed_ns(std::int64_t t0) {
  return static_cast<std::int32_t>(std::min<std::int64_t>(
      platform::monotonic_now_ns() - t0, std::numeric_limits<std::int32_t>::max()));
}

/// Sensor depth at sub-pixel (x, y), refused across depth edges (geometry::sample_depth).
float sample_depth(const cv::Mat& depth, float x, float y, double max_step) {
  if (depth.empty()) return 0.0F;
  return geometry::sample_depth({depth.ptr<float>(), depth.cols, depth.rows, depth.step1()}, x, y,
                                max_step);
}

}  // namespace

Tracker::Tracker(const TrackingOptions& opts, map::Map& map, const geometry::Pinhole& K, int width,
                 int height, SensorMode mode, bool focal_auto)
    : opts_(opts),
      map_(map),
      K_(K),
      width_(width),
      height_(height),
      focal_(opts.focal, K.fx, focal_auto),
      policy_(opts.keyframe.for_mode(mode), width, height),
      initializer_(opts, mode) {
  spatial_max_age_ns_ = static_cast<std::int64_t>(opts.spatial_max_age_s * 1e9);
}

Tracker::~Tracker() {
  map_.release_reader(map_reader_);
}

Status Tracker::init() {
  if (opts_.scale_features_with_area) {
    const double area_ratio =
        static_cast<double>(width_) * height_ / (kReferenceWidth * kReferenceHeight);
    if (area_ratio > 1.0) {
      const int cap = map_.options().max_keypoints_per_keyframe - opts_.extractor.num_levels;
      opts_.extractor.num_features =
          std::min(cap, static_cast<int>(std::lround(opts_.extractor.num_features * area_ratio)));
      MER_LOG_INFO("%dx%d images: %d features per frame", width_, height_,
                   opts_.extractor.num_features);
    }
  }
  Result<std::unique_ptr<features::Extractor>> ex =
      features::make_extractor(opts_.extractor, width_, height_);
  if (!ex.is_ok()) return ex.status();
  extractor_ = std::move(ex.value());
  if (map_reader_ < 0) {
    Result<int> reader = map_.register_reader();
    if (!reader.is_ok()) return reader.status();
    map_reader_ = reader.value();
  }
  const int max_kp = max_keypoints();
  if (max_kp > map_.options().max_keypoints_per_keyframe) {
    return invalid_argument("key 'tracking.extractor.num_features': " + std::to_string(max_kp) +
                            " keypoints per frame exceed map.max_keypoints_per_keyframe (" +
                            std::to_string(map_.options().max_keypoints_per_keyframe) + ")");
  }
  const auto nk = static_cast<std::size_t>(max_kp);
  const auto nq = static_cast<std::size_t>(opts_.max_query_points);
  pnp_ = std::make_unique<geometry::PnpRansac>(opts_.pnp, nq);
  grid_.reserve(width_, height_, opts_.match.grid_cell_px, max_kp);
  stamp_.assign(static_cast<std::size_t>(map_.options().max_points), 0);
  query_buf_.assign(nq, 0);
  cand_id_.assign(nq, 0);
  cand_p_w_.assign(nq, Eigen::Vector3d::Zero());
  cand_desc_.assign(nq, features::Descriptor{});
  cand_normal_.assign(nq, Eigen::Vector3f::Zero());
  cand_max_dist_.assign(nq, 0.0F);
  cand_kf_.assign(nq, 0);
  cand_gen_.assign(nq, map::kNoGeneration);
  cand_in_view_.assign(nq, 0);
  cand_match_.assign(nq, kNoMatch);
  kp_cand_.assign(nk, kNoMatch);
  kp_dist_.assign(nk, 0);
  corr_X_.assign(nk, Eigen::Vector3d::Zero());
  corr_uv_.assign(nk, Eigen::Vector2d::Zero());
  corr_sigma_.assign(nk, 1.0F);
  corr_kp_.assign(nk, 0);
  corr_mask_.assign(nk, 0);
  inlier_x_.assign(nk, 0.0F);
  inlier_y_.assign(nk, 0.0F);
  kp_point_.assign(nk, map::kNoId);
  kp_point_gen_.assign(nk, map::kNoGeneration);
  recent_.assign(static_cast<std::size_t>(opts_.temporal_frames), KeyframeHistogram{});
  qt_keyframes_.reserve(kMaxRecentKeyframes);
  depth_scratch_.reserve(std::max(nk, static_cast<std::size_t>(opts_.focal.max_frames) + 1024));
  focal_.reserve();
  initializer_.reserve(max_kp, width_, height_);
  return Status::ok();
}

int Tracker::max_keypoints() const {
  // The ORB backends keep at most num_features plus a few ties per level.
  return opts_.extractor.num_features + opts_.extractor.num_levels;
}

std::vector<float> Tracker::level_sigma2() const {
  std::vector<float> s;
  for (int l = 0; l < extractor_->num_levels(); ++l) s.push_back(extractor_->level_sigma2(l));
  return s;
}

// ---- Per-frame building blocks --------------------------------------------------------

void Tracker::gather_queries(const SE3d& T_c_w, TrackingResult& r) {
  if (++frame_stamp_ == 0) {  // wrapped: forget every stamp
    std::fill(stamp_.begin(), stamp_.end(), 0);
    frame_stamp_ = 1;
  }
  num_cand_ = 0;
  const auto cap = static_cast<int>(cand_id_.size());
  const std::uint32_t num_points = map_.num_points();
  auto add = [&](std::uint32_t p, std::int64_t min_ref_t_ns) {
    if (p >= num_points || num_cand_ >= cap) return false;
    if (stamp_[p] == frame_stamp_) return false;
    stamp_[p] = frame_stamp_;
    map::PointView pv;
    if (!map_.read_point(p, pv)) return false;
    // Another segment's points live in an unrelated world frame.
    if (map_.keyframe_segment(pv.ref_keyframe) != segment_) return false;
    if (min_ref_t_ns > 0 && map_.keyframe_t_ns(pv.ref_keyframe) < min_ref_t_ns) return false;
    const auto c = static_cast<std::size_t>(num_cand_++);
    cand_id_[c] = p;
    cand_p_w_[c] = pv.p_w;
    cand_desc_[c] = pv.descriptor;
    cand_normal_[c] = pv.normal;
    cand_max_dist_[c] = pv.max_distance;
    cand_kf_[c] = pv.ref_keyframe;
    cand_gen_[c] = pv.generation;
    cand_in_view_[c] = 0;
    cand_match_[c] = kNoMatch;
    return true;
  };

  // Q_T: points of the keyframes tracked in the last B frames (and the newest keyframe).
  // Keyframe ids kept from earlier frames may have been removed (skipped) or their slot
  // reused by a newer keyframe (whose points are as good a query).
  qt_keyframes_.clear();
  const map::KeyframeId newest = map_.newest_keyframe();
  if (newest != map::kNoId && map_.keyframe_segment(newest) == segment_) {
    qt_keyframes_.push_back(newest);
  }
  // Searched from a relocalizer's pose: the keyframe it was found against (the recent ones
  // saw another place).
  if (reloc_keyframe_ != map::kNoId && reloc_keyframe_ != newest &&
      map_.keyframe_is_live(reloc_keyframe_) &&
      map_.keyframe_generation(reloc_keyframe_) == reloc_generation_) {
    qt_keyframes_.push_back(reloc_keyframe_);
  }
  for (const KeyframeHistogram& h : recent_) {
    for (int i = 0; i < h.size(); ++i) {
      const std::uint32_t kf = h.keyframe(i);
      if (static_cast<int>(qt_keyframes_.size()) >= kMaxRecentKeyframes ||
          !map_.keyframe_is_live(kf)) {
        continue;
      }
      if (std::find(qt_keyframes_.begin(), qt_keyframes_.end(), kf) == qt_keyframes_.end()) {
        qt_keyframes_.push_back(kf);
      }
    }
  }
  int qt = 0;
  for (const std::uint32_t kf : qt_keyframes_) {
    const auto n = static_cast<std::uint32_t>(map_.keyframe_keypoints(kf).size());
    for (std::uint32_t k = 0; k < n; ++k) {
      const std::uint32_t p = map_.keyframe_point(kf, k);
      if (p != map::kNoId && add(p, 0)) ++qt;
    }
  }
  // Q_S: points in the cells visible from the predicted pose.
  const double far = opts_.query_far * median_depth_;
  const double near = kQueryNearFraction * median_depth_;
  const std::size_t ns =
      map_.query_visible(T_c_w.inverse(), K_, width_, height_, near, far, segment_, query_buf_);
  // Points made long ago are left to Q_T: in monocular mode they carry the drift since, and
  // tracking them would close the loop without correcting it (loop closure does that).
  const std::int64_t min_ref_t_ns =
      spatial_max_age_ns_ > 0 ? frame_t_ns_ - spatial_max_age_ns_ : std::int64_t{0};
  for (std::size_t i = 0; i < ns; ++i) (void)add(query_buf_[i], min_ref_t_ns);
  r.query_temporal = qt;
  r.query_spatial = static_cast<std::int32_t>(ns);
  r.query_total = num_cand_;
}

int Tracker::project_and_match(const SE3d& T_c_w, double radius_px, bool tight) {
  std::fill_n(kp_cand_.begin(), kps_.size(), kNoMatch);
  const Eigen::Vector3d centre = T_c_w.inverse().translation();
  const int levels = extractor_->num_levels();
  // Scale between pyramid levels (a one-level pyramid has no level 1 to read it from).
  const double log_scale =
      std::log(std::max(1.0001, levels > 1 ? static_cast<double>(extractor_->level_scale(1))
                                           : opts_.extractor.scale_factor));
  const int window = tight ? std::max(0, opts_.match.level_window - 1) : opts_.match.level_window;
  int matches = 0;
  for (int c = 0; c < num_cand_; ++c) {
    const auto ci = static_cast<std::size_t>(c);
    cand_match_[ci] = kNoMatch;
    cand_in_view_[ci] = 0;
    const Eigen::Vector3d p_c = T_c_w * cand_p_w_[ci];
    if (p_c.z() <= 0.0) continue;
    const Eigen::Vector2d uv = K_.project(p_c);
    if (uv.x() < 0.0 || uv.y() < 0.0 || uv.x() >= width_ || uv.y() >= height_) continue;
    const Eigen::Vector3d ray = cand_p_w_[ci] - centre;
    const double dist = ray.norm();
    const Eigen::Vector3f& nrm = cand_normal_[ci];
    if (nrm.squaredNorm() > 0.0F &&
        ray.dot(nrm.cast<double>()) < opts_.match.min_view_cos * dist * nrm.norm()) {
      continue;
    }
    cand_in_view_[ci] = 1;
    int pred_level = -1;
    if (cand_max_dist_[ci] > 0.0F && dist > 0.0) {
      pred_level =
          std::clamp(static_cast<int>(std::ceil(std::log(cand_max_dist_[ci] / dist) / log_scale)),
                     0, levels - 1);
    }
    const double r = radius_px * (pred_level >= 0 ? extractor_->level_scale(pred_level) : 1.0F);
    const int lo = pred_level >= 0 ? pred_level - window : 0;
    const int hi = pred_level >= 0 ? pred_level + window : levels;
    const auto [best, second, best_k] = grid_.search(uv, r, lo, hi, cand_desc_[ci]);
    if (best_k == kNoMatch || best > opts_.match.max_hamming) continue;
    if (second != std::numeric_limits<int>::max() && best > opts_.match.ratio * second) continue;
    const auto bk = static_cast<std::size_t>(best_k);
    if (kp_cand_[bk] != kNoMatch) {
      if (kp_dist_[bk] <= best) continue;
      cand_match_[static_cast<std::size_t>(kp_cand_[bk])] = kNoMatch;
      --matches;
    }
    kp_cand_[bk] = c;
    kp_dist_[bk] = best;
    cand_match_[ci] = best_k;
    ++matches;
  }
  return matches;
}

int Tracker::collect_correspondences() {
  int m = 0;
  const auto cap = static_cast<int>(corr_X_.size());
  for (int c = 0; c < num_cand_ && m < cap; ++c) {
    const int k = cand_match_[static_cast<std::size_t>(c)];
    if (k == kNoMatch) continue;
    const features::Keypoint& kp = kps_[static_cast<std::size_t>(k)];
    const auto mi = static_cast<std::size_t>(m++);
    corr_X_[mi] = cand_p_w_[static_cast<std::size_t>(c)];
    corr_uv_[mi] = Eigen::Vector2d(kp.x, kp.y);
    corr_sigma_[mi] = extractor_->level_scale(kp.level);
    corr_kp_[mi] = c;  // candidate index
  }
  return m;
}

bool Tracker::estimate_pose(const SE3d& T_c_w_pred, bool wide, TrackingResult& r) {
  const std::int64_t t_match = platform::monotonic_now_ns();
  int matches = project_and_match(T_c_w_pred,
                                  wide ? opts_.match.wide_radius_px : opts_.match.radius_px, false);
  if (matches < opts_.match.min_matches && !wide) {
    wide = true;
    ++counters_.wide_searches;
    matches = project_and_match(T_c_w_pred, opts_.match.wide_radius_px, false);
  }
  int m = collect_correspondences();
  r.step_ns[static_cast<std::size_t>(TrackStep::kMatch)] = elapsed_ns(t_match);
  const std::int64_t t_pose = platform::monotonic_now_ns();
  r.num_matches = m;
  if (m < opts_.min_inliers) {
    r.step_ns[static_cast<std::size_t>(TrackStep::kPose)] = elapsed_ns(t_pose);
    return false;
  }
  const auto um = static_cast<std::size_t>(m);
  geometry::PnpInput in;
  in.X_w = std::span<const Eigen::Vector3d>(corr_X_.data(), um);
  in.uv = std::span<const Eigen::Vector2d>(corr_uv_.data(), um);
  in.sigma = std::span<const float>(corr_sigma_.data(), um);
  in.K = K_;
  const bool est_focal = focal_.refining();
  const geometry::PnpResult pr =
      est_focal
          ? pnp_->solve_with_focal(in, std::span<std::uint8_t>(corr_mask_.data(), um), &T_c_w_pred)
          : pnp_->solve(in, std::span<std::uint8_t>(corr_mask_.data(), um), &T_c_w_pred);
  if (!pr.ok || pr.num_inliers < opts_.min_inliers) {
    r.step_ns[static_cast<std::size_t>(TrackStep::kPose)] = elapsed_ns(t_pose);
    return false;
  }
  SE3d T = pr.T_c_w;
  if (est_focal) update_focal(pr.focal, r.seq);

  // Second pass: tight search with the estimated pose, then refine on the gated matches.
  matches = project_and_match(T, opts_.match.refine_radius_px, true);
  m = collect_correspondences();
  const auto um2 = static_cast<std::size_t>(m);
  in.X_w = std::span<const Eigen::Vector3d>(corr_X_.data(), um2);
  in.uv = std::span<const Eigen::Vector2d>(corr_uv_.data(), um2);
  in.sigma = std::span<const float>(corr_sigma_.data(), um2);
  in.K = K_;
  geometry::RefineOptions ro;
  ro.iterations = opts_.pnp.refine_iterations;
  ro.huber_px = opts_.pnp.huber_px;
  int inliers = 0;
  SE3d T2 = T;
  for (int pass = 0; pass < 2; ++pass) {
    (void)geometry::refine_pose(in,
                                pass == 0 ? std::span<const std::uint8_t>{}
                                          : std::span<const std::uint8_t>(corr_mask_.data(), um2),
                                T2, nullptr, ro);
    inliers = 0;
    for (std::size_t i = 0; i < um2; ++i) {
      const Eigen::Vector3d p_c = T2 * corr_X_[i];
      const double s2 = static_cast<double>(corr_sigma_[i]) * corr_sigma_[i];
      const bool ok =
          p_c.z() > 0.0 && (K_.project(p_c) - corr_uv_[i]).squaredNorm() < kChi2TwoDof95 * s2;
      corr_mask_[i] = ok ? 1 : 0;
      inliers += ok ? 1 : 0;
    }
  }
  r.step_ns[static_cast<std::size_t>(TrackStep::kPose)] = elapsed_ns(t_pose);
  if (inliers < opts_.min_inliers) return false;
  T2 = orthonormalized(T2);
  T_c_w_ = T2;
  r.num_matches = m;
  r.num_inliers = inliers;

  // Culling statistics: every candidate the last search projected into the image was
  // visible; the inliers below were found.
  last_in_view_ = 0;
  for (int c = 0; c < num_cand_; ++c) {
    if (cand_in_view_[static_cast<std::size_t>(c)] != 0) {
      map_.note_visible(cand_id_[static_cast<std::size_t>(c)]);
      ++last_in_view_;
    }
  }
  // Tracked points: per-keypoint association, inlier positions, histogram, median depth.
  std::fill_n(kp_point_.begin(), kps_.size(), map::kNoId);
  histogram_.clear();
  depth_scratch_.clear();
  int ni = 0;
  for (std::size_t i = 0; i < um2; ++i) {
    if (corr_mask_[i] == 0) continue;
    const auto c = static_cast<std::size_t>(corr_kp_[i]);
    const auto k = static_cast<std::size_t>(cand_match_[c]);
    kp_point_[k] = cand_id_[c];
    kp_point_gen_[k] = cand_gen_[c];
    map_.note_found(cand_id_[c]);
    inlier_x_[static_cast<std::size_t>(ni)] = static_cast<float>(corr_uv_[i].x());
    inlier_y_[static_cast<std::size_t>(ni)] = static_cast<float>(corr_uv_[i].y());
    ++ni;
    histogram_.add(cand_kf_[c]);
    depth_scratch_.push_back((T2 * corr_X_[i]).z());
  }
  median_depth_ = std::max(upper_median(depth_scratch_), 1e-6);
  MER_LOG_DEBUG("frame %llu: %d inliers of %d map-points in view",
                static_cast<unsigned long long>(r.seq), inliers, last_in_view_);
  return true;
}

void Tracker::update_focal(double f, std::uint64_t seq) {
  if (focal_.add_tracked(f, seq, frames_since_init_)) K_ = K_.with_focal(focal_.value());
}

// ---- Tracking -------------------------------------------------------------------------

bool Tracker::track(const hal::Frame& frame, TrackingResult& r) {
  ++frames_since_init_;
  const bool from_hint = take_hint(frame);
  const SE3d T_c_w_pred = have_pose_ ? SE3d(velocity_ * T_c_w_) : T_c_w_;
  const SE3d T_c_w_prev = T_c_w_;
  const std::int64_t t_query = platform::monotonic_now_ns();
  gather_queries(T_c_w_pred, r);
  r.step_ns[static_cast<std::size_t>(TrackStep::kQuery)] = elapsed_ns(t_query);
  bool ok = estimate_pose(T_c_w_pred, poor_prediction_, r);
  if (!ok && !poor_prediction_) {
    ++counters_.wide_searches;
    ok = estimate_pose(T_c_w_pred, true, r);
  }
  r.focal = K_.fx;
  if (!ok) {
    r.state = TrackState::kLost;
    ++counters_.lost;
    poor_prediction_ = true;
    velocity_ = SE3d::Identity();
    T_c_w_ = T_c_w_prev;
    if (candidate_) {
      ++counters_.relocalization_rejected_lost;
      MER_LOG_INFO("frame %llu: relocalization refused (lost while confirming it)",
                   static_cast<unsigned long long>(frame.seq));
      reject_candidate();
    }
    return false;
  }
  velocity_ = orthonormalized(T_c_w_ * T_c_w_prev.inverse());
  if (from_hint && hint_frames_ > 1) {
    // The motion since a relocalizer's pose of an earlier frame spans several frames: the
    // next prediction takes one frame's share of it.
    velocity_ = fraction_of_motion(velocity_, 1.0 / static_cast<double>(hint_frames_));
  }
  have_pose_ = true;
  poor_prediction_ = false;
  bool confirmed = false;
  const double found = last_in_view_ > 0 ? static_cast<double>(r.num_inliers) / last_in_view_ : 0.0;
  // A pose trusted at once: its frame's share against the usual one (reported with the
  // relocalization, as a confirmed one reports its lowest; not a check).
  double at_once_ratio = 0.0;
  if (from_hint && !candidate_) {
    const double usual = recent_found_share();
    at_once_ratio = usual > 0.0 ? found / usual : 0.0;
  }
  if (candidate_ && !confirm_candidate(frame, found, r, confirmed)) return false;
  r.state = TrackState::kTracked;
  r.steady = true;
  found_share_[found_next_] = static_cast<float>(found);
  found_next_ = (found_next_ + 1) % kFoundHistory;
  found_valid_ = std::min(found_valid_ + 1, kFoundHistory);
  r.T_w_c = T_c_w_.inverse();
  last_T_w_c_ = r.T_w_c;
  ++counters_.tracked;
  counters_.sum_inliers += static_cast<std::uint64_t>(r.num_inliers);
  counters_.sum_query_temporal += static_cast<std::uint64_t>(r.query_temporal);
  counters_.sum_query_spatial += static_cast<std::uint64_t>(r.query_spatial);
  counters_.sum_query_total += static_cast<std::uint64_t>(r.query_total);

  r.reloc_found_ratio = static_cast<float>(at_once_ratio);  // (a confirmed one: decide_keyframe)
  decide_keyframe(frame, from_hint, confirmed, r);
  return true;
}

void Tracker::decide_keyframe(const hal::Frame& frame, bool from_hint, bool confirmed,
                              TrackingResult& r) {
  const std::int64_t t_decide = platform::monotonic_now_ns();
  KeyframeEvidence e;
  e.t_ns = frame.t_ns;
  e.inliers = r.num_inliers;
  e.inlier_x = std::span<const float>(inlier_x_.data(), static_cast<std::size_t>(r.num_inliers));
  e.inlier_y = std::span<const float>(inlier_y_.data(), static_cast<std::size_t>(r.num_inliers));
  e.histogram = &histogram_;
  e.centre_w = r.T_w_c.translation();
  e.median_depth = median_depth_;
  KeyframeReason reason = policy_.decide(e);
  if (force_keyframe_ && reason == KeyframeReason::kNone)
    reason = static_cast<KeyframeReason>(last_reason_);
  if ((from_hint && !candidate_) || confirmed) {
    // Back in the map at a place it knew: a keyframe ties the frames that follow to it.
    reason = KeyframeReason::kRelocalization;
    r.relocalized = true;
    r.reloc_confirmed = confirmed;
    if (confirmed) r.reloc_found_ratio = static_cast<float>(candidate_min_ratio_);
    SE3d T_w_rkf;
    if (reloc_keyframe_ != map::kNoId &&
        map_.keyframe_generation(reloc_keyframe_) == reloc_generation_ &&
        map_.keyframe_pose(reloc_keyframe_, T_w_rkf)) {
      r.reloc_keyframe_t_ns = map_.keyframe_t_ns(reloc_keyframe_);
      r.T_rkf_c = T_w_rkf.inverse() * r.T_w_c;
    }
    ++counters_.relocalized;
    MER_LOG_INFO("frame %llu: relocalized (%d inliers) after %llu lost frames",
                 static_cast<unsigned long long>(frame.seq), r.num_inliers,
                 static_cast<unsigned long long>(lost_frames_));
  }
  force_keyframe_ = false;
  r.kl = static_cast<float>(policy_.last_kl());
  const bool is_kf = reason != KeyframeReason::kNone;
  policy_.on_frame(e, is_kf);
  if (is_kf) {
    r.is_keyframe = true;
    r.keyframe_job = true;
    r.keyframe_reason = static_cast<std::uint8_t>(reason);
    last_reason_ = r.keyframe_reason;
    ++counters_.keyframes_decided;
    if (segment_ == start_segment_) ++start_keyframes_;
    ++counters_.keyframe_reasons[static_cast<std::size_t>(reason)];
    MER_LOG_DEBUG("frame %llu: keyframe (%s, inliers %d, kl %.3f)",
                  static_cast<unsigned long long>(frame.seq), to_string(reason), r.num_inliers,
                  policy_.last_kl());
  }
  recent_[recent_next_] = histogram_;
  recent_next_ = (recent_next_ + 1) % recent_.size();
  r.step_ns[static_cast<std::size_t>(TrackStep::kDecide)] = elapsed_ns(t_decide);
}

void Tracker::stop_reading() {
  map_.release_reader(map_reader_);
  map_reader_ = -1;
}

void Tracker::fill_keyframe_job(const hal::Frame& frame, map::KeyframeJob& job) const {
  job.segment = segment_;
  job.seq = frame.seq;
  job.t_ns = frame.t_ns;
  job.T_w_c = last_T_w_c_;
  job.K = K_;
  job.reason = last_reason_;
  const int n = std::min(static_cast<int>(kps_.size()), job.capacity());
  job.num_keypoints = n;
  std::copy_n(kps_.begin(), n, job.keypoints.begin());
  std::copy_n(descs_.begin(), n, job.descriptors.begin());
  if (start_to_queue_) {
    // The segment's start: its keyframes and points, as initialization made them.
    job.kind = map::KeyframeJobKind::kSegmentStart;
    initializer_.fill_segment_start(
        job.start,
        std::span<features::Keypoint>(job.keypoints.data(), static_cast<std::size_t>(n)));
    job.has_sensor_depth = false;
    job.num_recent = 0;
    return;
  }
  job.kind = map::KeyframeJobKind::kTracked;
  std::copy_n(kp_point_.begin(), n, job.point_ids.begin());
  std::copy_n(kp_point_gen_.begin(), n, job.point_gens.begin());
  job.has_sensor_depth = !frame.depth.empty();
  for (int i = 0; i < n && job.has_sensor_depth; ++i) {
    const auto ui = static_cast<std::size_t>(i);
    job.sensor_depth[ui] =
        sample_depth(frame.depth, kps_[ui].x, kps_[ui].y, opts_.rgbd_max_depth_step);
  }
  if (job.gray.size() == frame.gray.size()) frame.gray.copyTo(job.gray);
  // Recent frames, newest first, without this frame itself.
  job.num_recent = 0;
  const std::size_t cap = recent_gray_.size();
  for (std::size_t k = 0; k < recent_valid_; ++k) {
    if (job.num_recent >= static_cast<int>(job.recent_gray.size())) break;
    const std::size_t slot = (recent_head_ + cap - 1 - k) % cap;
    if (recent_t_ns_[slot] == frame.t_ns) continue;
    const auto out = static_cast<std::size_t>(job.num_recent);
    if (job.recent_gray[out].size() != recent_gray_[slot].size()) break;
    recent_gray_[slot].copyTo(job.recent_gray[out]);
    job.recent_T_w_c[out] = recent_T_w_c_[slot];
    ++job.num_recent;
  }
}

void Tracker::keep_recent_frames(int count, double spacing_s) {
  recent_gray_.resize(static_cast<std::size_t>(std::max(0, count)));
  for (auto& g : recent_gray_) g.create(height_, width_, CV_8UC1);
  recent_T_w_c_.assign(recent_gray_.size(), SE3d::Identity());
  recent_t_ns_.assign(recent_gray_.size(), 0);
  recent_head_ = 0;
  recent_valid_ = 0;
  recent_spacing_ns_ = static_cast<std::int64_t>(spacing_s * 1e9);
}

// ---- Initialization --------------------------------------------------------------------

void Tracker::initialize(const hal::Frame& frame, TrackingResult& r) {
  const InitDecision d = initializer_.spin_once(frame, grid_, K_, focal_);
  K_ = d.K;
  if (d.two_view_tried) ++counters_.init_attempts;
  counters_.init_gt_matches += static_cast<std::uint64_t>(d.gt_checked);
  counters_.init_gt_wrong += static_cast<std::uint64_t>(d.gt_wrong);
  if (d.started) {
    counters_.start_gt_matches += static_cast<std::uint64_t>(d.gt_checked);
    counters_.start_gt_wrong += static_cast<std::uint64_t>(d.gt_wrong);
  }
  if (!d.started) ++counters_.init_frame_refusals[static_cast<std::size_t>(d.refusal)];
  if (d.refusal == InitRefusal::kTwoView) {
    ++counters_.init_refusals;
    ++counters_.init_two_view_refusals[static_cast<std::size_t>(d.two_view)];
    counters_.last_init_refusal = refusal_name(d);  // a static name: no allocation
  }
  if (d.has_orientation) {
    r.has_orientation = true;
    r.orientation_chain = d.orientation_chain;
    r.q_chain_c = Eigen::Quaterniond(d.R_c_w.transpose());
    ++counters_.frames_oriented;
  }
  if (!d.started) return;
  // The segment's first keyframes and points go to keyframe creation (the tracking thread
  // never takes the map's writer lock); tracking resumes once they are in
  // (poll_segment_start).
  begin_segment_start(r);
  median_depth_ = d.median_depth;
  T_c_w_ = d.T_c_w;
  velocity_ = SE3d::Identity();
  have_pose_ = true;
  poor_prediction_ = d.num_views == 2;  // after a two-view start: the wide radius
  initialized_ = true;
  if (!counters_.initialized) {
    counters_.initialized_seq = frame.seq;
    counters_.reference_seq = d.ref_seq;
  }
  if (d.num_views == 2) counters_.segment_reference_seq = d.ref_seq;
  counters_.initialized = true;
  start_t_ns_ = frame.t_ns;
  start_segment_ = segment_;
  start_keyframes_ = static_cast<std::uint32_t>(d.num_views);
  policy_.reset(d.num_points, frame.t_ns, T_c_w_.inverse().translation());
  r.state = TrackState::kTracked;
  r.T_w_c = d.T_w_c;
  r.num_inliers = d.num_points;
  r.num_matches = d.num_matches;
  r.focal = K_.fx;
  last_T_w_c_ = r.T_w_c;
  r.has_anchor = true;  // anchored to its own keyframe (made by the job)
  r.anchor_t_ns = frame.t_ns;
  r.T_kf_c = r.T_w_c.inverse() * r.T_w_c;
  ++counters_.tracked;
}

// ---- Entry point -------------------------------------------------------------------------

TrackingResult Tracker::spin_once(const hal::Frame& frame) {
  // Quiescent point: nothing read from the map in earlier frames is held past here except
  // ids that are re-checked (map.h, slot reclamation).
  map_.reader_quiescent(map_reader_);
  follow_map_correction();
  TrackingResult r;
  r.seq = frame.seq;
  r.t_ns = frame.t_ns;
  frame_t_ns_ = frame.t_ns;
  r.focal = K_.fx;
  r.has_ground_truth = frame.has_ground_truth;
  r.T_w_c_gt = frame.T_w_c_gt;
  const std::int64_t t_extract = platform::monotonic_now_ns();
  extractor_->extract(frame.gray);
  kps_ = extractor_->keypoints();
  descs_ = extractor_->descriptors();
  if (kps_.size() > grid_.capacity()) {
    kps_ = kps_.first(grid_.capacity());
    descs_ = descs_.first(grid_.capacity());
  }
  grid_.build(kps_, descs_);
  r.step_ns[static_cast<std::size_t>(TrackStep::kExtract)] = elapsed_ns(t_extract);
  r.num_features = static_cast<std::int32_t>(kps_.size());
  std::uint64_t h = kFnvOffset;
  for (const auto& k : kps_) {
    h = (h ^ static_cast<std::uint64_t>(static_cast<std::uint32_t>(k.x * 16.0F))) * kFnvPrime;
    h = (h ^ static_cast<std::uint64_t>(static_cast<std::uint32_t>(k.y * 16.0F))) * kFnvPrime;
  }
  r.feature_hash = h;
  if (opts_.busy_work_us > 0) {
    const std::int64_t until =
        platform::monotonic_now_ns() + std::int64_t{opts_.busy_work_us} * 1000;
    while (platform::monotonic_now_ns() < until) {
    }
  }
  start_to_queue_ = false;  // the last frame's start was queued (or keyframe_not_queued said not)
  if (start_pending_) {
    // The segment's first keyframes are not in the map yet (threaded: keyframe creation is
    // busy): no pose for this frame; the next one tries again.
    const StartPoll poll = poll_segment_start();
    if (poll != StartPoll::kInserted) {
      if (poll == StartPoll::kPending) ++counters_.segment_start_waits;
      r.state = TrackState::kNotInitialized;
      state_ = other_segment_kept() ? TrackerState::kNewSegment : TrackerState::kInitializing;
      r.tracker_state = state_;
      r.segment = segment_;
      return r;
    }
  }
  // A relocalizer's pose against another segment's keyframe (lost in a new segment, or
  // relocalizing in one) returns to the segment it was found in.
  const std::uint16_t segment_before = segment_;
  const bool initialized_before = initialized_;
  const bool returning =
      hint_.valid &&
      (state_ == TrackerState::kNewSegment || state_ == TrackerState::kRelocalizing) &&
      map_.keyframe_segment(hint_.keyframe) != segment_;
  if (returning && !return_to_segment_of_hint()) hint_.valid = false;
  if (!initialized_) {
    r.state = TrackState::kNotInitialized;
    initialize(frame, r);
    advance_state(r);  // (a start anchors its frame to its own keyframe)
    if (r.has_orientation && state_ == TrackerState::kInitializing) {
      r.tracker_state = TrackerState::kInitializingRotation;
    }
    return r;
  }
  const bool tracked = track(frame, r);
  if (returning && candidate_) {
    candidate_returning_ = true;  // decided when the candidate is confirmed or refused
    candidate_segment_before_ = segment_before;
    candidate_initialized_before_ = initialized_before;
  } else if (returning && !tracked) {
    // Not found after all: back to the segment it came from (initializing it, or
    // relocalizing from its last tracked pose).
    segment_ = segment_before;
    initialized_ = initialized_before;
    T_c_w_ = last_tracked_T_c_w_;
    median_depth_ = last_tracked_median_depth_;
  } else if (returning && segment_ != segment_before) {
    ++counters_.segment_returns;
  }
  if (r.state == TrackState::kTracked) set_anchor(r);
  advance_state(r);
  // Ring of recent tracked frames (dense depth of later keyframes).
  if (!recent_gray_.empty() && r.state == TrackState::kTracked &&
      frame.gray.size() == recent_gray_[0].size()) {
    const std::size_t cap = recent_gray_.size();
    const std::size_t newest = (recent_head_ + cap - 1) % cap;
    if (recent_valid_ == 0 || frame.t_ns - recent_t_ns_[newest] >= recent_spacing_ns_) {
      frame.gray.copyTo(recent_gray_[recent_head_]);
      recent_T_w_c_[recent_head_] = r.T_w_c;
      recent_t_ns_[recent_head_] = frame.t_ns;
      recent_head_ = (recent_head_ + 1) % cap;
      recent_valid_ = std::min(recent_valid_ + 1, cap);
    }
  }
  return r;
}

}  // namespace mer::frontend
