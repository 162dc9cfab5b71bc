// Photometric keypoint alignment of keyframe creation (depth.align_keypoints; the contract is
// in keyframe_builder.h): the ring of recent keyframe pyramids, the anchors of points, the
// alignment of a keyframe's keypoints to their points' anchors and of new points'
// observations in older keyframes.
#include <algorithm>
#include <cmath>
#include <limits>

#include <Eigen/SVD>
#include <opencv2/imgproc.hpp>

#include "depth/keyframe_builder.h"

namespace mer::depth {
namespace {

constexpr int kAlignIterations = 10;        // Gauss-Newton steps of a keypoint alignment
constexpr float kAlignTolerancePx = 0.01F;  // converged: last update shorter (level px)

}  // namespace

void KeyframeBuilder::build_pyramid(const cv::Mat& gray) {
  const std::size_t levels = std::max<std::size_t>(1, level_sigma2_.size());
  if (level_to_x0_.size() != levels) {
    level_to_x0_.assign(levels, 1.0);
    level_to_y0_.assign(levels, 1.0);
  }
  KeyframeImage& img = images_[image_next_];
  img.kf = map::kNoId;
  img.gen = map::kNoGeneration;
  img.levels.resize(levels);
  gray.copyTo(img.levels[0]);
  for (std::size_t l = 1; l < levels; ++l) {
    // The extractor's level sizes (orb_extractor.cpp), area-averaged from level 0. Bilinear
    // resampling from the level before is 10x cheaper (1.3 against 13.7 ms for a 1241x376
    // pyramid) but aliases, and aligned hall_drive maps were worse with it (seeds 1-6:
    // 0.168 against 0.139 % re-anchored ATE).
    const double s = std::sqrt(static_cast<double>(level_sigma2_[l]));
    const int w = std::max(1, static_cast<int>(std::lround(gray.cols / s)));
    const int h = std::max(1, static_cast<int>(std::lround(gray.rows / s)));
    cv::resize(gray, img.levels[l], cv::Size(w, h), 0.0, 0.0, cv::INTER_AREA);
    level_to_x0_[l] = static_cast<double>(gray.cols) / w;
    level_to_y0_[l] = static_cast<double>(gray.rows) / h;
  }
}

Eigen::Vector2f KeyframeBuilder::to_level(const features::Keypoint& kp, std::size_t l) const {
  // Pixel centres aligned, as the extractor places keypoints (orb_extractor.cpp).
  return {static_cast<float>((kp.x + 0.5) / level_to_x0_[l] - 0.5),
          static_cast<float>((kp.y + 0.5) / level_to_y0_[l] - 0.5)};
}

const std::vector<cv::Mat>* KeyframeBuilder::keyframe_levels(map::KeyframeId kf) const {
  for (const KeyframeImage& img : images_) {
    if (img.kf == kf && img.kf != map::kNoId && map_.keyframe_generation(kf) == img.gen) {
      return &img.levels;
    }
  }
  return nullptr;
}

bool KeyframeBuilder::sample_anchor(const std::vector<cv::Mat>& levels,
                                    const features::Keypoint& kp, const SE3d& T_w_a,
                                    const Eigen::Vector3d& p_w, double fx, Anchor& out) const {
  const double z = (T_w_a.inverse() * p_w).z();
  const auto l =
      static_cast<std::size_t>(std::clamp<int>(kp.level, 0, static_cast<int>(levels.size()) - 1));
  const Eigen::Vector2f at = to_level(kp, l);
  if (!(z > 0.0) ||
      !features::sample_anchor_patch(levels[l], at.x(), at.y(), out.pixels, out.centre))
    return false;
  out.q_w_a = Eigen::Quaternionf(T_w_a.rotation().cast<float>());
  out.level = static_cast<std::int8_t>(l);
  out.m_px = static_cast<float>(z * std::sqrt(level_sigma2(static_cast<int>(l))) / fx);
  return true;
}

KeyframeBuilder::AlignOutcome KeyframeBuilder::align_to_anchor(
    const Anchor& a, const std::vector<cv::Mat>& levels, const Eigen::Vector3d& p_w,
    const SE3d& T_c_w, const geometry::Pinhole& K, features::Keypoint& kp) const {
  // The anchor's camera now (it moved with the map since) or, once culled, as sampled.
  Eigen::Matrix3d R_w_a = a.q_w_a.toRotationMatrix().cast<double>();
  double m_px = a.m_px;
  SE3d T_w_a;
  if (a.kf != map::kNoId && map_.keyframe_generation(a.kf) == a.kf_gen &&
      map_.keyframe_pose(a.kf, T_w_a)) {
    const double z_a = (T_w_a.inverse() * p_w).z();
    if (z_a > 0.0) {
      R_w_a = T_w_a.rotation();
      m_px = z_a * std::sqrt(level_sigma2(a.level)) / K.fx;
    }
  }
  const Eigen::Vector3d X = T_c_w * p_w;
  if (!(X.z() > 0.0) || !(m_px > 0.0)) return AlignOutcome::kRefused;
  // Target level-0 px per anchor px: projection Jacobian x the anchor's pixel axes.
  Eigen::Matrix<double, 2, 3> J;
  J << K.fx / X.z(), 0.0, -K.fx * X.x() / (X.z() * X.z()), 0.0, K.fy / X.z(),
      -K.fy * X.y() / (X.z() * X.z());
  const Eigen::Matrix2d A0 = J * T_c_w.rotation() * R_w_a.leftCols<2>() * m_px;
  const double det0 = A0.determinant();
  if (!(det0 > 0.0)) return AlignOutcome::kRefused;  // seen from behind the anchor's plane
  // The level where the warp is closest to a unit scale.
  std::size_t lc = 0;
  double best = std::numeric_limits<double>::max();
  for (std::size_t l = 0; l < levels.size(); ++l) {
    const double c = std::abs(std::log(det0 / (level_to_x0_[l] * level_to_y0_[l])));
    if (c < best) {
      best = c;
      lc = l;
    }
  }
  Eigen::Matrix2d A = A0;
  A.row(0) /= level_to_x0_[lc];
  A.row(1) /= level_to_y0_[lc];
  // A warp that stretches one direction much more than the other: the views see the surface
  // at very different angles, where the fronto-parallel model of the anchor is least right.
  const Eigen::Vector2d sv = Eigen::JacobiSVD<Eigen::Matrix2d>(A).singularValues();
  if (sv(0) > opts_.align_max_anisotropy * sv(1)) return AlignOutcome::kRefused;
  features::WarpedPatch ref{};
  Eigen::Vector2f uv = to_level(kp, lc);
  const Eigen::Vector2f start = uv;
  if (!features::warp_anchor_patch(a.pixels, a.centre, A.inverse().cast<float>(), ref)) {
    return AlignOutcome::kRefused;
  }
  const features::AlignResult r =
      features::align_patch(levels[lc], ref, kAlignIterations, kAlignTolerancePx, uv);
  if (r.iterations == 0) return AlignOutcome::kRefused;  // left the image, or no texture
  if (!r.converged || static_cast<double>(r.rms) > opts_.align_max_rms) {
    return AlignOutcome::kRefusedResidual;
  }
  const double dx = (uv.x() - start.x()) * level_to_x0_[lc];
  const double dy = (uv.y() - start.y()) * level_to_y0_[lc];
  const double max_shift = opts_.align_max_shift_px * static_cast<double>(kp.scale);
  if (dx * dx + dy * dy > max_shift * max_shift) return AlignOutcome::kRefusedShift;
  kp.x += static_cast<float>(dx);
  kp.y += static_cast<float>(dy);
  kp.anchored = 1;
  return AlignOutcome::kAligned;
}

void KeyframeBuilder::count(AlignOutcome o, KeyframeBuildReport& rep) {
  if (o == AlignOutcome::kAligned) ++rep.aligned_keypoints;
  if (o != AlignOutcome::kAligned) ++rep.align_refused;
  if (o == AlignOutcome::kRefusedResidual) ++rep.align_refused_residual;
  if (o == AlignOutcome::kRefusedShift) ++rep.align_refused_shift;
}

void KeyframeBuilder::align_tracked(const map::KeyframeJob& job, KeyframeBuildReport& rep) {
  const auto n = static_cast<std::size_t>(job.num_keypoints);
  const SE3d T_c_w = job.T_w_c.inverse();
  for (std::size_t i = 0; i < n; ++i) {
    const std::uint32_t p = ids_[i];
    if (p == map::kNoId || p >= anchors_.size()) continue;
    const Anchor& a = anchors_[p];
    if (a.point_gen == map::kNoGeneration || a.point_gen != map_.point_generation(p)) continue;
    map::PointView pv;
    if (!map_.read_point(p, pv)) continue;
    count(align_to_anchor(a, images_[image_next_].levels, pv.p_w, T_c_w, job.K, kps_[i]), rep);
  }
}

void KeyframeBuilder::set_anchors(const map::KeyframeJob& job, map::KeyframeId kf) {
  KeyframeImage& img = images_[image_next_];
  img.kf = kf;
  img.gen = map_.keyframe_generation(kf);
  const auto n = static_cast<std::size_t>(job.num_keypoints);
  for (std::size_t i = 0; i < n; ++i) {
    const std::uint32_t p = map_.keyframe_point(kf, static_cast<std::uint32_t>(i));
    if (p == map::kNoId || p >= anchors_.size()) continue;
    Anchor& a = anchors_[p];
    const map::Generation g = map_.point_generation(p);
    if (a.point_gen == g) continue;  // anchored already
    map::PointView pv;
    if (!map_.read_point(p, pv) ||
        !sample_anchor(img.levels, kps_[i], job.T_w_c, pv.p_w, job.K.fx, a)) {
      continue;
    }
    a.kf = kf;
    a.kf_gen = img.gen;
    a.point_gen = g;
    (void)map_.set_keypoint_anchored(kf, static_cast<std::uint32_t>(i), true);
  }
}

void KeyframeBuilder::align_new_observations(const geometry::Pinhole& K, KeyframeBuildReport& rep) {
  for (const NewObservation& o : new_obs_) {
    if (o.point >= anchors_.size()) continue;
    const Anchor& a = anchors_[o.point];
    if (a.point_gen == map::kNoGeneration || a.point_gen != map_.point_generation(o.point)) {
      continue;
    }
    const std::vector<cv::Mat>* levels = keyframe_levels(o.kf);
    SE3d T_w_v;
    map::PointView pv;
    if (levels == nullptr || !map_.keyframe_pose(o.kf, T_w_v) || !map_.read_point(o.point, pv)) {
      continue;
    }
    const auto kps = map_.keyframe_keypoints(o.kf);
    if (o.kp >= kps.size()) continue;
    features::Keypoint kp = kps[o.kp];
    const AlignOutcome out = align_to_anchor(a, *levels, pv.p_w, T_w_v.inverse(), K, kp);
    count(out, rep);
    if (out == AlignOutcome::kAligned && map_.set_keypoint_position(o.kf, o.kp, kp.x, kp.y)) {
      (void)map_.set_keypoint_anchored(o.kf, o.kp, true);
    }
  }
}

}  // namespace mer::depth
