#include "frontend/keyframe_policy.h"

#include <algorithm>
#include <cmath>

namespace mer::frontend {
namespace {
constexpr double kNsToS = 1e-9;
}  // namespace

const char* to_string(KeyframeReason r) {
  switch (r) {
    case KeyframeReason::kNone:
      return "none";
    case KeyframeReason::kTooFewInliers:
      return "too_few_inliers";
    case KeyframeReason::kPoorSpread:
      return "poor_spread";
    case KeyframeReason::kKlJump:
      return "kl_jump";
    case KeyframeReason::kMaxSpacing:
      return "max_spacing";
    case KeyframeReason::kInitialization:
      return "initialization";
    case KeyframeReason::kRelocalization:
      return "relocalization";
  }
  return "?";
}

void KeyframeHistogram::clear() {
  used_ = 0;
  overflow_ = 0;
  total_ = 0;
}

void KeyframeHistogram::add(std::uint32_t kf) {
  ++total_;
  for (int i = 0; i < used_; ++i) {
    if (ids_[static_cast<std::size_t>(i)] == kf) {
      ++counts_[static_cast<std::size_t>(i)];
      return;
    }
  }
  if (used_ < kBins) {
    ids_[static_cast<std::size_t>(used_)] = kf;
    counts_[static_cast<std::size_t>(used_)] = 1;
    ++used_;
    return;
  }
  ++overflow_;
}

int KeyframeHistogram::count_of(std::uint32_t kf) const {
  for (int i = 0; i < used_; ++i) {
    if (ids_[static_cast<std::size_t>(i)] == kf) return counts_[static_cast<std::size_t>(i)];
  }
  return 0;
}

double KeyframeHistogram::kl_divergence(const KeyframeHistogram& p, const KeyframeHistogram& q,
                                        double eps) {
  if (p.total_ == 0 || q.total_ == 0) return 0.0;
  // Support: the union of both histograms' keyframes plus the overflow bin. Each side's
  // probabilities are floored at eps and renormalized over that support.
  std::array<std::uint32_t, 2 * kBins> support{};
  int n = 0;
  for (int i = 0; i < p.used_; ++i)
    support[static_cast<std::size_t>(n++)] = p.ids_[static_cast<std::size_t>(i)];
  for (int i = 0; i < q.used_; ++i) {
    const std::uint32_t id = q.ids_[static_cast<std::size_t>(i)];
    if (p.count_of(id) == 0) support[static_cast<std::size_t>(n++)] = id;
  }
  const int bins = n + 1;  // + overflow
  auto prob = [&](const KeyframeHistogram& h, int bin) {
    const int c = bin < n ? h.count_of(support[static_cast<std::size_t>(bin)]) : h.overflow_;
    return static_cast<double>(c) / h.total_;
  };
  double zp = 0.0;
  double zq = 0.0;
  for (int b = 0; b < bins; ++b) {
    zp += std::max(prob(p, b), eps);
    zq += std::max(prob(q, b), eps);
  }
  double kl = 0.0;
  for (int b = 0; b < bins; ++b) {
    const double pb = std::max(prob(p, b), eps) / zp;
    const double qb = std::max(prob(q, b), eps) / zq;
    kl += pb * std::log(pb / qb);
  }
  return kl;
}

KeyframePolicy::KeyframePolicy(const KeyframePolicyOptions& opts, int width, int height)
    : opts_(opts), width_(width), height_(height) {
  opts_.spread_grid_cols = std::min(opts_.spread_grid_cols, 64);
  opts_.spread_grid_rows = std::min(opts_.spread_grid_rows, 64);
}

double KeyframePolicy::spread(const KeyframeEvidence& e) {
  const int cols = opts_.spread_grid_cols;
  const int rows = opts_.spread_grid_rows;
  std::fill(occupied_.begin(), occupied_.begin() + cols * rows, std::uint8_t{0});
  int occupied = 0;
  for (std::size_t i = 0; i < e.inlier_x.size(); ++i) {
    const int cx = std::clamp(static_cast<int>(e.inlier_x[i] * cols / width_), 0, cols - 1);
    const int cy = std::clamp(static_cast<int>(e.inlier_y[i] * rows / height_), 0, rows - 1);
    std::uint8_t& o = occupied_[static_cast<std::size_t>(cy * cols + cx)];
    if (o == 0) ++occupied;
    o = 1;
  }
  return static_cast<double>(occupied) / (cols * rows);
}

KeyframeReason KeyframePolicy::decide(const KeyframeEvidence& e) {
  last_spread_ = spread(e);
  last_baseline_ratio_ = -1.0;
  last_kl_ = (have_previous_ && e.histogram != nullptr)
                 ? KeyframeHistogram::kl_divergence(*e.histogram, previous_, opts_.kl_epsilon)
                 : 0.0;
  const double since_s = static_cast<double>(e.t_ns - t_keyframe_ns_) * kNsToS;
  if (since_s >= opts_.max_spacing_s) return KeyframeReason::kMaxSpacing;
  if (since_s < opts_.min_spacing_s) return KeyframeReason::kNone;
  if (e.inliers < opts_.min_inliers) return KeyframeReason::kTooFewInliers;
  last_baseline_ratio_ =
      e.median_depth > 0.0 ? (e.centre_w - centre_at_keyframe_).norm() / e.median_depth : -1.0;
  if (last_baseline_ratio_ >= 0.0 && last_baseline_ratio_ < opts_.min_baseline_ratio) {
    return KeyframeReason::kNone;
  }
  if (e.inliers < opts_.min_inlier_ratio * inliers_at_keyframe_) {
    return KeyframeReason::kTooFewInliers;
  }
  if (last_spread_ < opts_.min_spread) return KeyframeReason::kPoorSpread;
  if (last_kl_ > opts_.kl_threshold) return KeyframeReason::kKlJump;
  return KeyframeReason::kNone;
}

void KeyframePolicy::on_frame(const KeyframeEvidence& e, bool became_keyframe) {
  if (became_keyframe) {
    t_keyframe_ns_ = e.t_ns;
    inliers_at_keyframe_ = e.inliers;
    centre_at_keyframe_ = e.centre_w;
  }
  if (e.histogram != nullptr) {
    previous_ = *e.histogram;
    have_previous_ = true;
  }
}

void KeyframePolicy::reset(int inliers, std::int64_t t_ns, const Eigen::Vector3d& centre_w) {
  t_keyframe_ns_ = t_ns;
  inliers_at_keyframe_ = inliers;
  centre_at_keyframe_ = centre_w;
  last_baseline_ratio_ = -1.0;
  have_previous_ = false;
  last_kl_ = 0.0;
}

}  // namespace mer::frontend
