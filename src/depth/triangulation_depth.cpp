#include "depth/triangulation_depth.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>

#include "geometry/lie.h"
#include "geometry/triangulation.h"

namespace mer::depth {
namespace {

constexpr std::uint32_t kNoPoint = 0xFFFFFFFFu;
constexpr double kRadToDeg = 57.29577951308232;
constexpr std::size_t kMaxViews = 16;  // views used (depth.neighbours is at most 16)

bool is_free(std::span<const std::uint32_t> ids, std::size_t i) {
  return ids.empty() || ids[i] == kNoPoint;
}

}  // namespace

struct TriangulationDepth::Views {
  const DepthRequest& req;
  const geometry::Pinhole& K;
  double f = 0.0;  // mean focal length, px
  SE3d T_ck_w = SE3d::Identity();
  Eigen::Vector3d c_k = Eigen::Vector3d::Zero();  // the keyframe's centre
  std::size_t nv = 0;                             // views used
  std::array<SE3d, kMaxViews> T_cj_w{};
  std::array<Eigen::Matrix3d, kMaxViews> E{};  // x_j^T E x_k = 0
  double min_cos_parallax = 1.0;
  double bound = 0.0;       // squared reprojection bound, in sigmas^2
  std::size_t stride = 0;   // DepthResult::view_keypoint stride (the request's views)
  bool want_views = false;  // fill DepthResult::view_keypoint

  double sigma2(int level) const {
    return static_cast<double>(features::level_sigma2(req.level_sigma2, level));
  }
};

Status TriangulationDepth::infer(const DepthRequest& req, DepthResult& out) {
  const std::size_t n = req.keypoints.size();
  if (out.depth.size() < n || out.confidence.size() < n || out.support_view.size() < n ||
      out.support_keypoint.size() < n) {
    return invalid_argument("triangulation depth: output buffers smaller than the keypoints");
  }
  std::fill_n(out.depth.begin(), n, 0.0F);
  std::fill_n(out.confidence.begin(), n, 0.0F);
  std::fill_n(out.support_view.begin(), n, kNoSupport);
  std::fill_n(out.support_keypoint.begin(), n, kNoSupport);
  out.num_valid = 0;
  Views g{req, req.K};
  g.stride = req.views.size();
  g.want_views = !out.view_keypoint.empty();
  if (g.want_views && out.view_keypoint.size() < n * g.stride) {
    return invalid_argument("triangulation depth: view_keypoint smaller than keypoints x views");
  }
  if (g.want_views) std::fill_n(out.view_keypoint.begin(), n * g.stride, kNoSupport);
  g.f = 0.5 * (req.K.fx + req.K.fy);
  g.T_ck_w = req.T_w_c.inverse();
  g.c_k = req.T_w_c.translation();
  g.min_cos_parallax = std::cos(opts_.min_parallax_deg / kRadToDeg);

  // Per view: relative geometry and the epipolar matches of every free keypoint.
  g.nv = std::min(req.views.size(), kMaxViews);
  for (std::size_t vi = 0; vi < g.nv; ++vi) {
    g.T_cj_w[vi] = req.views[vi].T_w_c.inverse();
    const SE3d T_cj_ck = g.T_cj_w[vi] * req.T_w_c;
    g.E[vi] = geometry::hat(T_cj_ck.translation()) * T_cj_ck.linear();
  }
  match_.assign(n * g.nv, kNoSupport);
  for (std::size_t vi = 0; vi < g.nv; ++vi) match_view(g, vi);

  // Per keypoint: triangulate with the widest-baseline view, then keep every other view
  // whose match agrees (reprojects within bounds) and re-triangulate over all of them.
  g.bound = opts_.max_reprojection_sigmas * opts_.max_reprojection_sigmas;
  out.fates = KeypointFates{};
  for (std::size_t i = 0; i < n; ++i) {
    if (is_free(req.point_ids, i)) triangulate_keypoint(g, i, out);
  }
  return Status::ok();
}

void TriangulationDepth::match_view(const Views& g, std::size_t vi) {
  const DepthRequest& req = g.req;
  const geometry::Pinhole& K = g.K;
  const std::size_t n = req.keypoints.size();
  const std::size_t nv = g.nv;
  const DepthView& view = req.views[vi];
  const std::size_t m = view.keypoints.size();
  if ((view.T_w_c.translation() - g.c_k).norm() < std::numeric_limits<double>::epsilon()) return;
  best_dist_.assign(m, std::numeric_limits<int>::max());
  best_of_.assign(m, kNoSupport);
  candidates_.clear();
  for (std::size_t j = 0; j < m; ++j) {
    if (!is_free(view.point_ids, j)) continue;
    const features::Keypoint& kq = view.keypoints[j];
    candidates_.push_back({K.unproject({kq.x, kq.y}),
                           opts_.epipolar_sigmas * std::sqrt(g.sigma2(kq.level)),
                           static_cast<std::uint32_t>(j), kq.level});
  }
  if (candidates_.empty()) return;  // no free keypoint in this view: nothing to match
  // Counting sort by level, stable in j.
  int min_level = std::numeric_limits<int>::max();
  int max_level = std::numeric_limits<int>::min();
  for (const Candidate& c : candidates_) {
    min_level = std::min(min_level, c.level);
    max_level = std::max(max_level, c.level);
  }
  const auto bucket = [&](int level) { return static_cast<std::size_t>(level - min_level); };
  level_begin_.assign(bucket(max_level) + 2, 0);
  for (const Candidate& c : candidates_) ++level_begin_[bucket(c.level) + 1];
  for (std::size_t b = 1; b < level_begin_.size(); ++b) level_begin_[b] += level_begin_[b - 1];
  by_level_.resize(candidates_.size());
  level_next_.assign(level_begin_.begin(), level_begin_.end());
  for (const Candidate& c : candidates_) by_level_[level_next_[bucket(c.level)]++] = c;
  for (std::size_t i = 0; i < n; ++i) {
    if (!is_free(req.point_ids, i)) continue;
    const features::Keypoint& kp = req.keypoints[i];
    const Eigen::Vector3d x_k = K.unproject({kp.x, kp.y});
    const Eigen::Vector3d l = g.E[vi] * x_k;  // epipolar line in view j (normalized coords)
    const double l_norm = std::hypot(l.x(), l.y());
    if (l_norm < std::numeric_limits<double>::epsilon()) continue;
    int best = std::numeric_limits<int>::max();
    int second = std::numeric_limits<int>::max();
    std::size_t best_j = m;
    const int lo = std::max(min_level, kp.level - opts_.max_level_difference);
    const int hi = std::min(max_level, kp.level + opts_.max_level_difference);
    if (lo > hi) continue;
    const auto first = by_level_.begin() + static_cast<std::ptrdiff_t>(level_begin_[bucket(lo)]);
    const auto last = by_level_.begin() + static_cast<std::ptrdiff_t>(level_begin_[bucket(hi) + 1]);
    for (auto it = first; it != last; ++it) {
      const Candidate& c = *it;
      const double dist_px = std::abs(l.dot(c.x)) / l_norm * g.f;
      if (dist_px > c.band_px) continue;
      const int d = features::hamming(req.descriptors[i], view.descriptors[c.j]);
      // Ties go to the lowest keypoint index, whatever the order the levels come in.
      if (d < best || (d == best && c.j < best_j)) {
        second = best;
        best = d;
        best_j = c.j;
      } else if (d < second) {
        second = d;
      }
    }
    if (best_j == m || best > opts_.max_hamming) continue;
    if (second != std::numeric_limits<int>::max() && best > opts_.ratio * second) continue;
    // One-to-one per view: a keypoint of the view goes to its closest descriptor.
    if (best_of_[best_j] != kNoSupport) {
      if (best_dist_[best_j] <= best) continue;
      match_[best_of_[best_j] * nv + vi] = kNoSupport;
    }
    best_of_[best_j] = static_cast<std::uint32_t>(i);
    best_dist_[best_j] = best;
    match_[i * nv + vi] = static_cast<std::uint32_t>(best_j);
  }
}

void TriangulationDepth::triangulate_keypoint(const Views& g, std::size_t i,
                                              DepthResult& out) const {
  const DepthRequest& req = g.req;
  const geometry::Pinhole& K = g.K;
  const std::size_t nv = g.nv;
  KeypointFates& fate = out.fates;
  ++fate.free;
  const features::Keypoint& kp = req.keypoints[i];
  const Eigen::Vector3d x_k = K.unproject({kp.x, kp.y});
  std::size_t best_v = nv;
  double best_cos = 1.0;
  bool matched = false;
  Eigen::Vector3d X_best = Eigen::Vector3d::Zero();
  for (std::size_t vi = 0; vi < nv; ++vi) {
    const std::uint32_t j = match_[i * nv + vi];
    if (j == kNoSupport) continue;
    matched = true;
    const features::Keypoint& kq = req.views[vi].keypoints[j];
    Eigen::Vector3d X_w;
    if (!geometry::triangulate_two_view(g.T_ck_w, g.T_cj_w[vi], x_k, K.unproject({kq.x, kq.y}),
                                        X_w)) {
      continue;
    }
    const Eigen::Vector3d r_k = X_w - g.c_k;
    const Eigen::Vector3d r_j = X_w - req.views[vi].T_w_c.translation();
    const double cos_parallax = r_k.dot(r_j) / (r_k.norm() * r_j.norm());
    if (cos_parallax < best_cos) {
      best_cos = cos_parallax;
      best_v = vi;
      X_best = X_w;
    }
  }
  if (!matched) {
    ++fate.no_match;
    return;
  }
  if (best_v == nv || best_cos > g.min_cos_parallax) {
    ++fate.low_parallax;
    return;
  }
  // Views consistent with X_best.
  std::array<SE3d, kMaxViews + 1> poses;
  std::array<Eigen::Vector3d, kMaxViews + 1> rays;
  std::size_t nviews = 0;
  std::array<std::uint32_t, kMaxViews + 1> view_of{};  // view index per entry (0: keyframe)
  poses[nviews] = g.T_ck_w;
  rays[nviews++] = x_k;
  for (std::size_t vi = 0; vi < nv; ++vi) {
    const std::uint32_t j = match_[i * nv + vi];
    if (j == kNoSupport) continue;
    const features::Keypoint& kq = req.views[vi].keypoints[j];
    const Eigen::Vector3d p_j = g.T_cj_w[vi] * X_best;
    if (p_j.z() <= 0.0) continue;
    if ((K.project(p_j) - Eigen::Vector2d(kq.x, kq.y)).squaredNorm() >
        g.bound * g.sigma2(kq.level)) {
      continue;
    }
    poses[nviews] = g.T_cj_w[vi];
    view_of[nviews] = static_cast<std::uint32_t>(vi);
    rays[nviews++] = K.unproject({kq.x, kq.y});
  }
  if (nviews < 2 || static_cast<int>(nviews) < opts_.min_views) {
    ++fate.few_views;
    return;
  }
  Eigen::Vector3d X_w = X_best;
  if (nviews > 2 && !geometry::triangulate_multi_view(
                        std::span<const SE3d>(poses.data(), nviews),
                        std::span<const Eigen::Vector3d>(rays.data(), nviews), X_w)) {
    X_w = X_best;
  }
  const Eigen::Vector3d p_k = g.T_ck_w * X_w;
  if (p_k.z() <= 0.0 ||
      (K.project(p_k) - Eigen::Vector2d(kp.x, kp.y)).squaredNorm() > g.bound * g.sigma2(kp.level)) {
    ++fate.rejected;
    return;
  }
  // Scale consistency: the distances to the two cameras must agree with the pyramid
  // levels the keypoints were found at (a wrong match on repetitive texture often pairs
  // keypoints whose scales contradict the triangulated distances).
  const features::Keypoint& kq_best = req.views[best_v].keypoints[match_[i * nv + best_v]];
  const double dist_ratio =
      (X_w - g.c_k).norm() / (X_w - req.views[best_v].T_w_c.translation()).norm();
  const double level_ratio = static_cast<double>(kq_best.scale) / static_cast<double>(kp.scale);
  if (dist_ratio * opts_.max_scale_inconsistency < level_ratio ||
      dist_ratio > level_ratio * opts_.max_scale_inconsistency) {
    ++fate.rejected;
    return;
  }
  const double parallax_deg = std::acos(std::clamp(best_cos, -1.0, 1.0)) * kRadToDeg;
  out.depth[i] = static_cast<float>(p_k.z());
  // Confidence: parallax of the widest baseline, more if more views agree.
  const double views_factor = static_cast<double>(nviews - 1) / static_cast<double>(nv);
  out.confidence[i] =
      static_cast<float>(std::min(1.0, parallax_deg / opts_.full_confidence_parallax_deg) *
                         (0.5 + 0.5 * views_factor));
  out.support_view[i] = static_cast<std::uint32_t>(best_v);
  out.support_keypoint[i] = match_[i * nv + best_v];
  if (g.want_views) {
    // Views that agreed with the first estimate and still reproject near the final one.
    for (std::size_t e = 1; e < nviews; ++e) {
      const std::size_t vi = view_of[e];
      const std::uint32_t j = match_[i * nv + vi];
      const features::Keypoint& kq = req.views[vi].keypoints[j];
      const Eigen::Vector3d p_j = g.T_cj_w[vi] * X_w;
      if (p_j.z() <= 0.0 || (K.project(p_j) - Eigen::Vector2d(kq.x, kq.y)).squaredNorm() >
                                g.bound * g.sigma2(kq.level)) {
        continue;
      }
      out.view_keypoint[i * g.stride + vi] = j;
    }
  }
  ++out.num_valid;
  ++fate.depth;
}

}  // namespace mer::depth
