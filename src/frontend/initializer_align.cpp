// Photometric refinement of the initializer's matches (tracking.init.align; the contract is in
// initializer.h): each reference keypoint's patch, taken once from the reference's pyramid at
// the keypoint's level, is aligned in the frame's pyramid at the same level, starting from the
// descriptor match. Every frame then measures the surface point the reference saw.
#include <algorithm>
#include <cmath>

#include <opencv2/imgproc.hpp>

#include "frontend/initializer.h"

namespace mer::frontend {
namespace {

constexpr int kAlignIterations = 10;        // Gauss-Newton steps of a match alignment
constexpr float kAlignTolerancePx = 0.01F;  // converged: last update shorter (level px)

}  // namespace

void Initializer::build_levels(const cv::Mat& gray, std::vector<cv::Mat>& levels) {
  const auto n = static_cast<std::size_t>(num_levels_);
  levels.resize(n);
  if (level_to_x0_.size() != n) {
    level_to_x0_.assign(n, 1.0);
    level_to_y0_.assign(n, 1.0);
  }
  gray.copyTo(levels[0]);
  double s = 1.0;
  for (std::size_t l = 1; l < n; ++l) {
    // The extractor's level sizes (orb_extractor.cpp), area-averaged from level 0.
    s *= scale_factor_;
    const int w = std::max(1, static_cast<int>(std::lround(gray.cols / s)));
    const int h = std::max(1, static_cast<int>(std::lround(gray.rows / s)));
    cv::resize(gray, levels[l], cv::Size(w, h), 0.0, 0.0, cv::INTER_AREA);
    level_to_x0_[l] = static_cast<double>(gray.cols) / w;
    level_to_y0_[l] = static_cast<double>(gray.rows) / h;
  }
}

Eigen::Vector2f Initializer::to_level(float x, float y, std::size_t l) const {
  // Pixel centres aligned, as the extractor places keypoints.
  return {static_cast<float>((x + 0.5) / level_to_x0_[l] - 0.5),
          static_cast<float>((y + 0.5) / level_to_y0_[l] - 0.5)};
}

Eigen::Vector2d Initializer::from_level(const Eigen::Vector2f& uv, std::size_t l) const {
  return {(uv.x() + 0.5) * level_to_x0_[l] - 0.5, (uv.y() + 0.5) * level_to_y0_[l] - 0.5};
}

void Initializer::sample_reference_patches() {
  const std::size_t n = ref_kps_.size();
  ref_patch_ok_.assign(n, 0);
  if (ref_patch_.size() < n) ref_patch_.resize(n);  // (reserve sized it: no allocation)
  const Eigen::Matrix2f identity = Eigen::Matrix2f::Identity();
  for (std::size_t i = 0; i < n; ++i) {
    const auto l = static_cast<std::size_t>(
        std::clamp<int>(ref_kps_[i].level, 0, static_cast<int>(ref_levels_.size()) - 1));
    const Eigen::Vector2f at = to_level(ref_kps_[i].x, ref_kps_[i].y, l);
    features::AnchorPixels anchor{};
    Eigen::Vector2f centre;
    if (!features::sample_anchor_patch(ref_levels_[l], at.x(), at.y(), anchor, centre)) continue;
    // The aligned patch is centred on the keypoint: its offsets (c - 4.5, r - 4.5) sample the
    // anchor around `centre` unwarped.
    if (!features::warp_anchor_patch(anchor, centre, identity, ref_patch_[i])) continue;
    ref_patch_ok_[i] = 1;
  }
}

int Initializer::align_matches(const hal::Frame& frame) {
  build_levels(frame.gray, cur_levels_);
  const auto& o = opts_.align;
  std::size_t out = 0;
  for (std::size_t j = 0; j < init_uv0_.size(); ++j) {
    const auto i = static_cast<std::size_t>(init_ref_idx_[j]);
    bool keep = true;
    Eigen::Vector2d uv1 = init_uv1_[j];
    if (ref_patch_ok_[i] == 0) {
      keep = !o.drop_refused;
    } else {
      const auto l = static_cast<std::size_t>(
          std::clamp<int>(ref_kps_[i].level, 0, static_cast<int>(cur_levels_.size()) - 1));
      Eigen::Vector2f uv = to_level(static_cast<float>(uv1.x()), static_cast<float>(uv1.y()), l);
      const Eigen::Vector2f start = uv;
      const features::AlignResult r = features::align_patch(
          cur_levels_[l], ref_patch_[i], kAlignIterations, kAlignTolerancePx, uv);
      const bool ok = r.iterations > 0 && r.converged && static_cast<double>(r.rms) <= o.max_rms &&
                      static_cast<double>((uv - start).norm()) <= o.max_shift_px;
      if (ok) {
        uv1 = from_level(uv, l);
      } else {
        keep = !o.drop_refused;
      }
    }
    if (!keep) {
      ref_match_[i] = kNoMatch;
      continue;
    }
    init_uv0_[out] = init_uv0_[j];
    init_uv1_[out] = uv1;
    init_ref_idx_[out] = init_ref_idx_[j];
    init_cur_idx_[out] = init_cur_idx_[j];
    ref_prev_[i] = uv1;
    ++out;
  }
  init_uv0_.resize(out);
  init_uv1_.resize(out);
  init_ref_idx_.resize(out);
  init_cur_idx_.resize(out);
  return static_cast<int>(out);
}

}  // namespace mer::frontend
