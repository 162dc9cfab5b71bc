#include "frontend/initializer.h"

#include <algorithm>
#include <cmath>

#include "core/median.h"
#include "geometry/depth_sampling.h"
#include "geometry/lie.h"
#include "geometry/self_calibration.h"
#include "geometry/triangulation.h"
#include "platform/log_ring.h"

namespace mer::frontend {
namespace {

constexpr double kRgbdMinDepthM = 0.1;  // RGB-D initialization: valid sensor depth range, m
constexpr double kRgbdMaxDepthM = 10.0;
// Re-projects the rotation onto SO(3).
SE3d orthonormalized(const SE3d& T) {
  SE3d out = T;
  out.linear() = Eigen::Quaterniond(T.linear()).normalized().toRotationMatrix();
  return out;
}

/// Sensor depth at sub-pixel (x, y), refused across depth edges (geometry::sample_depth).
float sample_depth(const cv::Mat& depth, float x, float y, double max_step) {
  if (depth.empty()) return 0.0F;
  return geometry::sample_depth({depth.ptr<float>(), depth.cols, depth.rows, depth.step1()}, x, y,
                                max_step);
}

}  // namespace

const char* to_string(InitRefusal r) {
  switch (r) {
    case InitRefusal::kNone:
      return "none";
    case InitRefusal::kNoDepth:
      return "no_depth";
    case InitRefusal::kTooFewFeatures:
      return "too_few_features";
    case InitRefusal::kNoReference:
      return "no_reference";
    case InitRefusal::kTooFewMatches:
      return "too_few_matches";
    case InitRefusal::kReferenceTooOld:
      return "reference_too_old";
    case InitRefusal::kFocalPending:
      return "focal_pending";
    case InitRefusal::kTwoView:
      return "two_view";
    case InitRefusal::kTooFewDepthPoints:
      return "too_few_depth_points";
    case InitRefusal::kWindowAmbiguous:
      return "window_ambiguous";
    case InitRefusal::kWindowUncertain:
      return "window_uncertain";
    case InitRefusal::kWindowTooFewPoints:
      return "window_too_few_points";
  }
  return "?";
}

const char* refusal_name(const InitDecision& d) {
  return d.refusal == InitRefusal::kTwoView ? geometry::to_string(d.two_view)
                                            : to_string(d.refusal);
}

Initializer::Initializer(const TrackingOptions& opts, SensorMode mode)
    : opts_(opts.init),
      min_disparity_px_(opts.focal.min_disparity_px),
      scale_factor_(opts.extractor.scale_factor),
      seed_(opts.pnp.seed),
      rgbd_max_depth_step_(opts.rgbd_max_depth_step),
      rgbd_(mode == SensorMode::kRgbd),
      num_levels_(std::max(1, opts.extractor.num_levels)) {}

void Initializer::reserve(int max_keypoints, int width, int height) {
  const auto n = static_cast<std::size_t>(max_keypoints);
  if (!rgbd_ && opts_.align.enabled && width > 0 && height > 0) {
    const cv::Mat blank(height, width, CV_8UC1, cv::Scalar(0));
    build_levels(blank, ref_levels_);
    build_levels(blank, cur_levels_);
    ref_patch_.resize(n);
    ref_patch_ok_.reserve(n);
  }
  ref_kps_.reserve(n);
  ref_descs_.reserve(n);
  ref_prev_.reserve(n);
  ref_match_.reserve(n);
  kp_ref_.assign(n, kNoMatch);
  kp_dist_.assign(n, 0);
  init_uv0_.reserve(n);
  init_uv1_.reserve(n);
  init_ref_idx_.reserve(n);
  init_cur_idx_.reserve(n);
  scratch_.reserve(n);
  start_.reserve(max_keypoints);
  start_uv_.resize(n);
  max_keypoints_ = max_keypoints;
  const auto nv = static_cast<std::size_t>(opts_.window.max_views);
  win_seq_.assign(nv, 0);
  win_uv_.assign(nv * n, Eigen::Vector2f::Zero());
  win_sel_.reserve(n);
  win_consistent_.reserve(n);
  for (geometry::WindowBundleAdjuster& ba : ba_) {
    ba.reserve(opts_.window.max_views + 1, opts_.window.max_points);
  }
  point_cost_.assign(kMaxWindowCandidates * static_cast<std::size_t>(opts_.window.max_points), 0.0);
  win_T_.assign(nv + 1, SE3d::Identity());
  win_points_c0_.reserve(n);
  win_good_.reserve(n);
  tri_T_.reserve(nv + 2);
  tri_x_.reserve(nv + 2);
  two_view_ws_.reserve(n, two_view_);
  plane_hints_.reserve(geometry::kMaxPlaneNormals);
}

void Initializer::drop_reference() {
  ref_valid_ = false;
  plane_hints_.clear();
}

InitDecision Initializer::spin_once(const hal::Frame& frame, const KeypointGrid& features,
                                    const geometry::Pinhole& K, FocalEstimator& focal) {
  InitDecision d;
  d.K = K;
  if (rgbd_) {
    initialize_rgbd(frame, features, focal, d);
  } else {
    initialize_mono(frame, features, focal, d);
  }
  return d;
}

void Initializer::set_reference(const hal::Frame& frame, const KeypointGrid& features,
                                const Eigen::Matrix3d* R_c_w) {
  if (R_c_w != nullptr) {
    ref_R_ref_w_ = *R_c_w;
  } else {
    ref_R_ref_w_.setIdentity();
    ++chain_;
  }
  const std::span<const features::Keypoint> kps = features.keypoints();
  const std::span<const features::Descriptor> descs = features.descriptors();
  ref_kps_.assign(kps.begin(), kps.end());
  ref_descs_.assign(descs.begin(), descs.end());
  ref_prev_.clear();
  for (const auto& k : kps) ref_prev_.emplace_back(k.x, k.y);
  ref_valid_ = true;
  plane_hints_.clear();
  ref_seq_ = frame.seq;
  ref_t_ns_ = frame.t_ns;
  if (!rgbd_ && opts_.align.enabled) {
    build_levels(frame.gray, ref_levels_);
    sample_reference_patches();
  }
  // The audit's copy reuses its buffer: frames of one source have one size (no allocation
  // after the first reference).
  ref_gt_ =
      !rgbd_ && frame.has_ground_truth && !frame.depth.empty() && frame.depth.type() == CV_32FC1;
  if (ref_gt_) {
    frame.depth.copyTo(ref_depth_gt_);
    ref_T_w_c_gt_ = frame.T_w_c_gt;
  }
  win_views_ = 0;
  win_stride_ = 1;
  frames_since_ref_ = 0;
  ref_first_matches_ = 0;
}

void Initializer::audit_matches(const hal::Frame& frame, const geometry::Pinhole& K,
                                InitDecision& d) const {
  if (!ref_gt_ || !frame.has_ground_truth) return;
  const SE3d T_cur_ref = frame.T_w_c_gt.inverse() * ref_T_w_c_gt_;
  for (std::size_t i = 0; i < init_uv0_.size(); ++i) {
    const int u = static_cast<int>(std::lround(init_uv0_[i].x()));
    const int v = static_cast<int>(std::lround(init_uv0_[i].y()));
    if (u < 0 || v < 0 || u >= ref_depth_gt_.cols || v >= ref_depth_gt_.rows) continue;
    const double z = ref_depth_gt_.at<float>(v, u);
    if (!(z > 0.0)) continue;
    const Eigen::Vector3d X_ref(z * (init_uv0_[i].x() - K.cx) / K.fx,
                                z * (init_uv0_[i].y() - K.cy) / K.fy, z);
    const Eigen::Vector3d X = T_cur_ref * X_ref;
    if (!(X.z() > 0.0)) continue;
    const Eigen::Vector2d uv(K.fx * X.x() / X.z() + K.cx, K.fy * X.y() / X.z() + K.cy);
    ++d.gt_checked;
    if ((uv - init_uv1_[i]).norm() > kGtWrongMatchPx) ++d.gt_wrong;
  }
}

int Initializer::match_reference(const KeypointGrid& features) {
  const std::span<const features::Keypoint> kps = features.keypoints();
  std::fill_n(kp_ref_.begin(), kps.size(), kNoMatch);
  ref_match_.assign(ref_kps_.size(), kNoMatch);
  const double r = opts_.search_radius_px;
  for (std::size_t i = 0; i < ref_kps_.size(); ++i) {
    const int level = ref_kps_[i].level;
    const auto [best, second, best_k] =
        features.search(ref_prev_[i], r, level - 1, level + 1, ref_descs_[i]);
    if (best_k == kNoMatch || best > opts_.max_hamming) continue;
    if (second != std::numeric_limits<int>::max() && best > opts_.ratio * second) continue;
    const auto bk = static_cast<std::size_t>(best_k);
    if (kp_ref_[bk] != kNoMatch) {
      if (kp_dist_[bk] <= best) continue;
      ref_match_[static_cast<std::size_t>(kp_ref_[bk])] = kNoMatch;
    }
    kp_ref_[bk] = static_cast<std::int32_t>(i);
    kp_dist_[bk] = best;
    ref_match_[i] = best_k;
  }
  init_uv0_.clear();
  init_uv1_.clear();
  init_ref_idx_.clear();
  init_cur_idx_.clear();
  for (std::size_t i = 0; i < ref_kps_.size(); ++i) {
    const int k = ref_match_[i];
    if (k == kNoMatch) continue;
    const features::Keypoint& kp = kps[static_cast<std::size_t>(k)];
    init_uv0_.emplace_back(ref_kps_[i].x, ref_kps_[i].y);
    init_uv1_.emplace_back(kp.x, kp.y);
    init_ref_idx_.push_back(static_cast<std::int32_t>(i));
    init_cur_idx_.push_back(k);
    ref_prev_[i] = Eigen::Vector2d(kp.x, kp.y);
  }
  return static_cast<int>(init_uv0_.size());
}

void Initializer::focal_from_reference(int matches, FocalEstimator& focal, InitDecision& d) {
  if (matches < opts_.two_view.min_matches) return;
  scratch_.clear();
  for (std::size_t i = 0; i < init_uv0_.size(); ++i) {
    scratch_.push_back((init_uv1_[i] - init_uv0_[i]).norm());
  }
  if (upper_median(scratch_) < min_disparity_px_) return;
  const geometry::FocalEstimate est = geometry::estimate_focal_two_view(
      init_uv0_, init_uv1_, d.K.cx, d.K.cy, focal.report().initial, seed_);
  if (!est.ok) {
    MER_LOG_DEBUG("focal estimate refused: %.2f px, relative sigma %.4f, %d inliers", est.focal,
                  est.relative_sigma, est.num_inliers);
    return;
  }
  const double med = focal.add_two_view(est.focal);
  d.K = d.K.with_focal(med);
  MER_LOG_INFO("focal estimate %.2f px (median %.2f over %d)", est.focal, med,
               focal.report().estimates);
}

bool Initializer::reference_too_old(std::int64_t t_ns) const {
  const double max_age_s =
      plane_hints_.empty() ? opts_.max_reference_age_s : opts_.max_plane_hint_reference_age_s;
  return static_cast<double>(t_ns - ref_t_ns_) * 1e-9 > max_age_s;
}

void Initializer::initialize_mono(const hal::Frame& frame, const KeypointGrid& features,
                                  FocalEstimator& focal, InitDecision& d) {
  const std::span<const features::Keypoint> kps = features.keypoints();
  if (static_cast<int>(kps.size()) < opts_.min_features) {
    ref_valid_ = false;
    d.refusal = InitRefusal::kTooFewFeatures;
    return;
  }
  if (!ref_valid_) {
    set_reference(frame, features);
    d.refusal = InitRefusal::kNoReference;
    return;
  }
  int m = match_reference(features);
  if (opts_.align.enabled) m = align_matches(frame);
  audit_matches(frame, d.K, d);
  if (ref_first_matches_ == 0) ref_first_matches_ = m;
  if (m < opts_.two_view.min_matches) {
    set_reference(frame, features);
    d.refusal = InitRefusal::kTooFewMatches;
    return;
  }
  if (focal.init_waits()) {
    focal_from_reference(m, focal, d);
    if (focal.init_waits()) {
      if (reference_too_old(frame.t_ns)) set_reference(frame, features);
      d.refusal = InitRefusal::kFocalPending;
      return;
    }
  }
  d.two_view_tried = true;
  geometry::reconstruct_two_view(init_uv0_, init_uv1_, d.K, opts_.two_view, plane_hints_,
                                 two_view_ws_, two_view_);
  const geometry::TwoViewResult& tv = two_view_;
  if (!tv.ok) {
    if (opts_.plane_hints && plane_hints_.empty())
      plane_hints_.assign(tv.plane_normals_c0.begin(), tv.plane_normals_c0.end());
    d.refusal = InitRefusal::kTwoView;
    d.two_view = tv.refusal;
    MER_LOG_DEBUG("frame %llu: initialization refused (%s)",
                  static_cast<unsigned long long>(frame.seq), geometry::to_string(tv.refusal));
    // A homography's motion (a plane fills the view) has a twin the window cannot tell apart
    // when the camera moves along a line: only an essential model's uncertain motion, or a tie
    // when asked for, goes to the window.
    const bool window_decides =
        (tv.refusal == geometry::TwoViewRefusal::kUncertainMotion &&
         tv.model == geometry::TwoViewModel::kEssential) ||
        (tv.refusal == geometry::TwoViewRefusal::kAmbiguous && opts_.window.decide_ties);
    if (opts_.window.enabled && window_decides && !tv.candidate_motions.empty() &&
        win_views_ >= opts_.window.min_views &&
        decide_on_window(frame, tv.candidate_motions, d.K, d)) {
      make_start(frame, features, win_points_c0_, win_good_, d.T_c_w, m, focal, d);
      return;
    }
    if (tv.refusal == geometry::TwoViewRefusal::kPureRotation) {
      d.has_orientation = true;
      d.R_c_w = tv.rotation_c1_c0 * ref_R_ref_w_;
      d.orientation_chain = chain_;
    }
    // A sweep leaves the reference's view: renew it while the orientation is still known.
    const bool renew = d.has_orientation &&
                       static_cast<double>(m) < opts_.rotation_renew_fraction * ref_first_matches_;
    if (tv.refusal == geometry::TwoViewRefusal::kTooFewMatches || reference_too_old(frame.t_ns) ||
        renew) {
      set_reference(frame, features, d.has_orientation ? &d.R_c_w : nullptr);
    } else {
      remember_frame(frame);
    }
    return;
  }
  make_start(frame, features, tv.points_c0, tv.triangulated, tv.T_c1_c0, m, focal, d);
  if (tv.model == geometry::TwoViewModel::kEssential) {
    MER_LOG_INFO(
        "initialized at frame %llu from frame %llu: essential model, %d points, parallax %.2f "
        "deg, translation direction sigma %.3f deg",
        static_cast<unsigned long long>(frame.seq), static_cast<unsigned long long>(ref_seq_),
        d.num_points, tv.median_parallax_deg, tv.translation_dir_sigma_deg);
  } else {
    MER_LOG_INFO(
        "initialized at frame %llu from frame %llu: homography model, %d points, parallax %.2f deg",
        static_cast<unsigned long long>(frame.seq), static_cast<unsigned long long>(ref_seq_),
        d.num_points, tv.median_parallax_deg);
  }
}

void Initializer::make_start(const hal::Frame& frame, const KeypointGrid& features,
                             std::span<const Eigen::Vector3d> points_c0,
                             std::span<const std::uint8_t> good, const SE3d& T_cur_ref, int matches,
                             FocalEstimator& focal, InitDecision& d) {
  const std::span<const features::Keypoint> kps = features.keypoints();
  // Two keyframes: the reference (world frame) and this frame, with the points triangulated
  // in the reference, scaled to unit median depth there.
  scratch_.clear();
  for (std::size_t i = 0; i < init_ref_idx_.size(); ++i) {
    if (good[i] != 0) scratch_.push_back(points_c0[i].z());
  }
  const double scale = scratch_.empty() ? 1.0 : 1.0 / std::max(upper_median(scratch_), 1e-12);
  SE3d T = T_cur_ref;
  T.translation() *= scale;
  std::fill_n(start_.ref_depth.begin(), ref_kps_.size(), 0.0F);
  std::fill_n(start_.ref_confidence.begin(), ref_kps_.size(), 0.0F);
  std::fill_n(start_.depth.begin(), kps.size(), 0.0F);
  std::fill_n(start_.confidence.begin(), kps.size(), 0.0F);
  scratch_.clear();
  int ni = 0;
  for (std::size_t i = 0; i < init_ref_idx_.size(); ++i) {
    if (good[i] == 0) continue;
    const Eigen::Vector3d X = points_c0[i] * scale;
    const auto k0 = static_cast<std::size_t>(init_ref_idx_[i]);
    const auto k = static_cast<std::size_t>(init_cur_idx_[i]);
    const double z1 = (T * X).z();
    start_.ref_depth[k0] = static_cast<float>(X.z());
    start_.depth[k] = static_cast<float>(z1);
    start_.ref_confidence[k0] = 1.0F;
    start_.confidence[k] = 1.0F;
    const auto ui = static_cast<std::size_t>(ni);
    start_.points_w[ui] = X;
    start_.first_keypoint[ui] = static_cast<std::uint32_t>(k0);
    start_.second_keypoint[ui] = static_cast<std::uint32_t>(k);
    start_uv_[ui] = init_uv1_[i].cast<float>();
    ++ni;
    scratch_.push_back(z1);
  }
  start_.num_points = ni;
  start_.num_views = 2;
  start_.ref_seq = ref_seq_;
  start_.ref_t_ns = ref_t_ns_;
  start_.ref_num_keypoints = static_cast<int>(ref_kps_.size());
  d.started = true;
  d.refusal = InitRefusal::kNone;
  d.two_view = geometry::TwoViewRefusal::kNone;
  d.num_views = 2;
  d.T_c_w = orthonormalized(T);
  d.T_w_c = d.T_c_w.inverse();
  d.num_points = ni;
  d.num_matches = matches;
  d.median_depth = std::max(upper_median(scratch_), 1e-6);
  d.ref_seq = ref_seq_;
  focal.fix_at_init(frame.seq);
}

void Initializer::remember_frame(const hal::Frame& frame) {
  if (!opts_.window.enabled) return;
  ++frames_since_ref_;
  if (frames_since_ref_ % win_stride_ != 0) return;
  const int max_views = opts_.window.max_views;
  const auto nk = static_cast<std::size_t>(max_keypoints_);
  if (win_views_ == max_views) {
    // Full: keep every other frame (slots 1, 3, ...), the stride doubles.
    for (int k = 1; k < max_views; k += 2) {
      const auto from = static_cast<std::size_t>(k);
      const auto to = static_cast<std::size_t>(k / 2);
      win_seq_[to] = win_seq_[from];
      std::copy_n(win_uv_.begin() + static_cast<std::ptrdiff_t>(from * nk), nk,
                  win_uv_.begin() + static_cast<std::ptrdiff_t>(to * nk));
    }
    win_views_ = max_views / 2;
    win_stride_ *= 2;
    if (frames_since_ref_ % win_stride_ != 0) return;
  }
  if (win_views_ >= max_views) return;  // max_views 1: no room after the halving
  const auto slot = static_cast<std::size_t>(win_views_);
  win_seq_[slot] = frame.seq;
  const float nan = std::numeric_limits<float>::quiet_NaN();
  const std::size_t nref = std::min(ref_kps_.size(), nk);  // the grid holds at most nk
  for (std::size_t i = 0; i < nref; ++i) {
    const int k = ref_match_[i];
    // (ref_prev_: where the match is in this frame, aligned with init.align)
    win_uv_[slot * nk + i] = k == kNoMatch ? Eigen::Vector2f(nan, nan) : ref_prev_[i].cast<float>();
  }
  ++win_views_;
}

void Initializer::initialize_rgbd(const hal::Frame& frame, const KeypointGrid& features,
                                  FocalEstimator& focal, InitDecision& d) {
  if (frame.depth.empty()) {
    d.refusal = InitRefusal::kNoDepth;
    return;
  }
  const std::span<const features::Keypoint> kps = features.keypoints();
  if (focal.init_waits()) {
    if (!ref_valid_ || static_cast<int>(kps.size()) < opts_.min_features) {
      d.refusal = ref_valid_ ? InitRefusal::kTooFewFeatures : InitRefusal::kNoReference;
      set_reference(frame, features);
      return;
    }
    const int m = match_reference(features);
    if (m < opts_.two_view.min_matches || reference_too_old(frame.t_ns)) {
      d.refusal = m < opts_.two_view.min_matches ? InitRefusal::kTooFewMatches
                                                 : InitRefusal::kReferenceTooOld;
      set_reference(frame, features);
      return;
    }
    focal_from_reference(m, focal, d);
    if (focal.init_waits()) {
      d.refusal = InitRefusal::kFocalPending;
      return;
    }
  }
  // One keyframe, this frame (the world frame), with a point per keypoint with depth.
  std::fill_n(start_.depth.begin(), kps.size(), 0.0F);
  std::fill_n(start_.confidence.begin(), kps.size(), 0.0F);
  int valid = 0;
  for (std::size_t i = 0; i < kps.size(); ++i) {
    const float z = sample_depth(frame.depth, kps[i].x, kps[i].y, rgbd_max_depth_step_);
    if (z < kRgbdMinDepthM || z > kRgbdMaxDepthM) continue;
    start_.depth[i] = z;
    start_.confidence[i] = 1.0F;
    ++valid;
  }
  if (valid < opts_.rgbd_min_points) {
    d.refusal = InitRefusal::kTooFewDepthPoints;
    return;
  }
  scratch_.clear();
  int ni = 0;
  for (std::size_t i = 0; i < kps.size(); ++i) {
    if (start_.depth[i] <= 0.0F) continue;
    const auto ui = static_cast<std::size_t>(ni);
    start_.points_w[ui] = d.K.unproject({kps[i].x, kps[i].y}) * start_.depth[i];
    start_.first_keypoint[ui] = static_cast<std::uint32_t>(i);
    scratch_.push_back(start_.depth[i]);
    ++ni;
  }
  start_.num_points = ni;
  start_.num_views = 1;
  d.started = true;
  d.num_views = 1;
  d.T_c_w = SE3d::Identity();
  d.T_w_c = SE3d::Identity();
  d.num_points = ni;
  d.median_depth = std::max(upper_median(scratch_), 1e-6);
  d.ref_seq = frame.seq;
  focal.fix_at_init(frame.seq);
  MER_LOG_INFO("initialized (RGB-D) at frame %llu with %d points",
               static_cast<unsigned long long>(frame.seq), ni);
}

void Initializer::fill_segment_start(map::SegmentStart& st,
                                     std::span<features::Keypoint> keypoints) const {
  const std::size_t un = keypoints.size();
  st.num_views = start_.num_views;
  st.ref_seq = start_.ref_seq;
  st.ref_t_ns = start_.ref_t_ns;
  st.ref_num_keypoints = 0;
  if (start_.num_views == 2) {
    const int m = std::min(start_.ref_num_keypoints, static_cast<int>(st.ref_keypoints.size()));
    st.ref_num_keypoints = m;
    std::copy_n(ref_kps_.begin(), m, st.ref_keypoints.begin());
    std::copy_n(ref_descs_.begin(), m, st.ref_descriptors.begin());
    std::copy_n(start_.ref_depth.begin(), m, st.ref_depth.begin());
    std::copy_n(start_.ref_confidence.begin(), m, st.ref_confidence.begin());
  }
  std::copy_n(start_.depth.begin(), un, st.depth.begin());
  std::copy_n(start_.confidence.begin(), un, st.confidence.begin());
  const int np = std::min(start_.num_points, static_cast<int>(st.points_w.size()));
  st.num_points = np;
  std::copy_n(start_.points_w.begin(), np, st.points_w.begin());
  std::copy_n(start_.first_keypoint.begin(), np, st.first_keypoint.begin());
  std::copy_n(start_.second_keypoint.begin(), np, st.second_keypoint.begin());
  if (opts_.align.enabled && start_.num_views == 2) {
    for (int p = 0; p < np; ++p) {
      const auto up = static_cast<std::size_t>(p);
      const std::uint32_t k = start_.second_keypoint[up];
      if (k >= un) continue;
      keypoints[k].x = start_uv_[up].x();
      keypoints[k].y = start_uv_[up].y();
    }
  }
}

}  // namespace mer::frontend
