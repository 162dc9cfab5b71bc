// The window decision of the monocular start (Initializer, initializer.h): a refused two-view
// pair decided on the frames tracked since the reference, each motion candidate solved with
// them, the best one tested for evidence and stability, and the start's points triangulated
// from every view.
#include <algorithm>
#include <array>
#include <cmath>
#include <limits>

#include "core/chi2.h"
#include "core/median.h"
#include "frontend/initializer.h"
#include "geometry/lie.h"
#include "geometry/triangulation.h"
#include "platform/log_ring.h"

namespace mer::frontend {
namespace {

constexpr int kViewsFirstIterations = 5;  // views placed on the candidate's points first
// Two candidates this close (rotation and translation direction, deg) are the same motion.
constexpr double kSameCandidateDeg = 0.5;
// Floor of the variance of per-point cost differences (identical costs: no evidence either way
// beyond the mean).
constexpr double kMinVariance = 1e-12;
constexpr double kRadToDeg = 57.29577951308232;

/// Squared Sampson distance (px^2 at focal `f`) of the normalized rays x0, x1 from the epipolar
/// geometry of motion T (camera 1 from camera 0).
double sampson_px2(const SE3d& T, const Eigen::Vector3d& x0, const Eigen::Vector3d& x1, double f) {
  const Eigen::Matrix3d E = geometry::hat(T.translation()) * T.linear();
  const Eigen::Vector3d e_x0 = E * x0;
  const Eigen::Vector3d et_x1 = E.transpose() * x1;
  const double num = x1.dot(e_x0);
  const double den = e_x0.head<2>().squaredNorm() + et_x1.head<2>().squaredNorm();
  return den > 0.0 ? f * f * num * num / den : 0.0;
}

double angle_deg(const Eigen::Vector3d& a, const Eigen::Vector3d& b) {
  const double na = a.norm();
  const double nb = b.norm();
  if (na <= 0.0 || nb <= 0.0) return 180.0;
  return std::acos(std::clamp(a.dot(b) / (na * nb), -1.0, 1.0)) * kRadToDeg;
}

}  // namespace

bool Initializer::decide_on_window(const hal::Frame& frame, std::span<const SE3d> candidates,
                                   const geometry::Pinhole& K, InitDecision& d) {
  const std::size_t nc = std::min(candidates.size(), kMaxWindowCandidates);
  if (select_window_points(candidates.first(nc), K) == 0) {
    d.refusal = InitRefusal::kWindowTooFewPoints;
    return false;
  }
  const WindowVote vote = vote_on_window(frame, candidates.first(nc), K);
  // 3. Released, the best motion must stay where it is: a solution of all the frames that
  //    moves away from it means the motion is not determined yet (low parallax trades
  //    rotation for translation).
  const int cur = win_views_;
  geometry::WindowBundleAdjuster& ba = ba_[static_cast<std::size_t>(vote.slot)];
  for (int v = 0; v <= cur; ++v) win_T_[static_cast<std::size_t>(v)] = ba.pose(v);
  ba.fix_view(-1);
  ba.set_scale_view(cur);
  ba.solve(opts_.window.iterations, false);
  const SE3d& T_free = ba.pose(cur);
  const SE3d& T = win_T_[static_cast<std::size_t>(cur)];
  const double moved_rot_deg = geometry::rotation_angle(T_free.linear(), T.linear()) * kRadToDeg;
  const double moved_dir_deg = angle_deg(T_free.translation(), T.translation());
  MER_LOG_DEBUG(
      "frame %llu: window of %d frames from frame %llu, %zu candidates, evidence %.1f sigmas, "
      "released motion moved %.3f deg (rotation) and %.2f deg (direction)",
      static_cast<unsigned long long>(frame.seq), win_views_,
      static_cast<unsigned long long>(ref_seq_), nc, vote.evidence, moved_rot_deg, moved_dir_deg);
  if (vote.evidence < opts_.window.min_evidence_sigmas) {
    d.refusal = InitRefusal::kWindowAmbiguous;
    return false;
  }
  if (moved_rot_deg > opts_.window.max_moved_rotation_deg ||
      moved_dir_deg > opts_.window.max_moved_direction_deg) {
    d.refusal = InitRefusal::kWindowUncertain;
    return false;
  }

  double median_parallax = 0.0;
  const int good = triangulate_window(T, K, median_parallax);
  if (good < opts_.two_view.min_triangulated || median_parallax < opts_.two_view.min_parallax_deg) {
    d.refusal = InitRefusal::kWindowTooFewPoints;
    return false;
  }
  d.T_c_w = T;
  d.window_views = win_views_;
  MER_LOG_INFO(
      "initialized at frame %llu from frame %llu: window of %d frames, %zu motion candidate(s) "
      "(evidence %.1f sigmas), released motion moved %.3f deg / %.2f deg, %d points, parallax "
      "%.2f deg",
      static_cast<unsigned long long>(frame.seq), static_cast<unsigned long long>(ref_seq_),
      win_views_, nc, std::isfinite(vote.evidence) ? vote.evidence : 0.0, moved_rot_deg,
      moved_dir_deg, good, median_parallax);
  return true;
}

std::size_t Initializer::select_window_points(std::span<const SE3d> candidates,
                                              const geometry::Pinhole& K) {
  const geometry::TwoViewOptions& tvo = opts_.two_view;
  // The adjustment's points, spread evenly over the matches that were tracked through every
  // frame of the window (a track lost and found again is more often a wrong match) and lie on
  // an epipolar line of some candidate (the others are wrong whatever the motion).
  const std::size_t n = init_uv0_.size();
  win_consistent_.clear();
  const auto nkk = static_cast<std::size_t>(max_keypoints_);
  for (std::size_t j = 0; j < n; ++j) {
    const auto ri = static_cast<std::size_t>(init_ref_idx_[j]);
    bool continuous = true;
    for (int w = 0; w < win_views_ && continuous; ++w) {
      continuous = std::isfinite(win_uv_[static_cast<std::size_t>(w) * nkk + ri].x());
    }
    if (!continuous) continue;
    const double sigma = tvo.sigma_px * std::pow(scale_factor_, ref_kps_[ri].level);
    const Eigen::Vector3d x0 = K.unproject(init_uv0_[j]);
    const Eigen::Vector3d x1 = K.unproject(init_uv1_[j]);
    for (const SE3d& candidate : candidates) {
      if (sampson_px2(candidate, x0, x1, K.fx) <= kChi2OneDof95 * sigma * sigma) {
        win_consistent_.push_back(static_cast<std::int32_t>(j));
        break;
      }
    }
  }
  const std::size_t nconsistent = win_consistent_.size();
  const auto max_points = static_cast<std::size_t>(opts_.window.max_points);
  const std::size_t step = std::max<std::size_t>(1, (nconsistent + max_points - 1) / max_points);
  win_sel_.clear();
  for (std::size_t j = 0; j < nconsistent && win_sel_.size() < max_points; j += step) {
    win_sel_.push_back(win_consistent_[j]);
  }
  return win_sel_.size();
}

Initializer::WindowVote Initializer::vote_on_window(const hal::Frame& frame,
                                                    std::span<const SE3d> candidates,
                                                    const geometry::Pinhole& K) {
  const std::size_t nc = candidates.size();
  const std::size_t np = win_sel_.size();
  const auto max_points = static_cast<std::size_t>(opts_.window.max_points);
  // 1. Each candidate motion held fixed, the frames in between and the points solved: its
  //    cost per point, truncated (wrong tracks cost the gate).
  WindowVote vote;
  std::size_t& best = vote.best;
  std::array<double, kMaxWindowCandidates> total{};
  for (std::size_t c = 0; c < nc; ++c) {
    const int slot = c == 0 ? 0 : 1 - vote.slot;
    solve_candidate(frame, candidates[c], K, slot);
    const geometry::WindowBundleAdjuster& ba = ba_[static_cast<std::size_t>(slot)];
    for (std::size_t p = 0; p < np; ++p) {
      const double cp = ba.point_truncated_cost(static_cast<int>(p), kChi2TwoDof95);
      point_cost_[c * max_points + p] = cp;
      total[c] += cp;
    }
    if (c == 0 || total[c] < total[best]) {
      best = c;
      vote.slot = slot;
    }
  }
  // 2. The best must beat every other (distinct) candidate by a significant margin: the mean
  //    of the per-point cost differences, over its standard error (a paired test).
  for (std::size_t c = 0; c < nc; ++c) {
    if (c == best) continue;
    if (geometry::rotation_angle(candidates[c].linear(), candidates[best].linear()) * kRadToDeg <=
            kSameCandidateDeg &&
        angle_deg(candidates[c].translation(), candidates[best].translation()) <=
            kSameCandidateDeg) {
      continue;  // the same motion twice (both models found it)
    }
    double sum = 0.0;
    double sum2 = 0.0;
    for (std::size_t p = 0; p < np; ++p) {
      const double diff = point_cost_[c * max_points + p] - point_cost_[best * max_points + p];
      sum += diff;
      sum2 += diff * diff;
    }
    const double mean = sum / static_cast<double>(np);
    const double var = std::max(sum2 / static_cast<double>(np) - mean * mean, kMinVariance);
    vote.evidence = std::min(vote.evidence, mean / std::sqrt(var / static_cast<double>(np)));
  }
  return vote;
}

int Initializer::triangulate_window(const SE3d& T, const geometry::Pinhole& K,
                                    double& median_parallax) {
  const geometry::TwoViewOptions& tvo = opts_.two_view;
  // 4. The start's points: every match triangulated from all the views that saw it (the
  //    candidate's motion, the frames in between as solved with it).
  const std::size_t n = init_uv0_.size();
  const Eigen::Vector3d centre = -(T.linear().transpose() * T.translation());
  const auto nk = static_cast<std::size_t>(max_keypoints_);
  win_points_c0_.assign(n, Eigen::Vector3d::Zero());
  win_good_.assign(n, 0);
  scratch_.clear();
  for (std::size_t j = 0; j < n; ++j) {
    const auto ri = static_cast<std::size_t>(init_ref_idx_[j]);
    const double sigma = tvo.sigma_px * std::pow(scale_factor_, ref_kps_[ri].level);
    tri_T_.clear();
    tri_x_.clear();
    tri_T_.push_back(SE3d::Identity());
    tri_x_.push_back(K.unproject(init_uv0_[j]));
    for (int w = 0; w < win_views_; ++w) {
      const Eigen::Vector2f& uv = win_uv_[static_cast<std::size_t>(w) * nk + ri];
      if (!std::isfinite(uv.x())) continue;
      tri_T_.push_back(win_T_[static_cast<std::size_t>(w)]);
      tri_x_.push_back(K.unproject(uv.cast<double>()));
    }
    tri_T_.push_back(T);
    tri_x_.push_back(K.unproject(init_uv1_[j]));
    Eigen::Vector3d X;
    if (!geometry::triangulate_multi_view(tri_T_, tri_x_, X)) continue;
    bool fits = true;
    for (std::size_t k = 0; k < tri_T_.size() && fits; ++k) {
      const Eigen::Vector3d& x = tri_x_[k];
      const Eigen::Vector2d seen(K.fx * x.x() + K.cx, K.fy * x.y() + K.cy);
      fits = (K.project(tri_T_[k] * X) - seen).squaredNorm() <= kChi2TwoDof95 * sigma * sigma;
    }
    const double parallax = geometry::parallax_deg(X, Eigen::Vector3d::Zero(), centre);
    if (!fits || parallax < tvo.min_point_parallax_deg) continue;
    win_points_c0_[j] = X;
    win_good_[j] = 1;
    scratch_.push_back(parallax);
  }
  median_parallax = scratch_.empty() ? 0.0 : upper_median(scratch_);
  return static_cast<int>(scratch_.size());
}

void Initializer::solve_candidate(const hal::Frame& frame, const SE3d& T_cur_ref,
                                  const geometry::Pinhole& K, int slot) {
  geometry::WindowBundleAdjuster& ba = ba_[static_cast<std::size_t>(slot)];
  const geometry::TwoViewOptions& tv = opts_.two_view;
  ba.reset(K, kChi2TwoDof95);
  // Points: the candidate's triangulation; the others (near the epipole, behind) at the
  // median inverse depth.
  scratch_.clear();
  for (const std::int32_t j : win_sel_) {
    const auto uj = static_cast<std::size_t>(j);
    Eigen::Vector3d X;
    double rho = -1.0;
    if (geometry::triangulate_two_view(SE3d::Identity(), T_cur_ref, K.unproject(init_uv0_[uj]),
                                       K.unproject(init_uv1_[uj]), X) &&
        X.z() > 0.0) {
      rho = 1.0 / X.z();
      scratch_.push_back(rho);
    }
    const int level = ref_kps_[static_cast<std::size_t>(init_ref_idx_[uj])].level;
    ba.add_point(init_uv0_[uj], rho, tv.sigma_px * std::pow(scale_factor_, level));
  }
  const double rho_median = scratch_.empty() ? 1.0 : upper_median(scratch_);
  // Views: the frames in between, at the interpolated pose, then the current frame (fixed).
  const Eigen::Quaterniond q_cur(T_cur_ref.linear());
  const double span = static_cast<double>(frame.seq - ref_seq_);
  for (int w = 0; w < win_views_; ++w) {
    const double s = static_cast<double>(win_seq_[static_cast<std::size_t>(w)] - ref_seq_) / span;
    SE3d T = SE3d::Identity();
    T.linear() = Eigen::Quaterniond::Identity().slerp(s, q_cur).toRotationMatrix();
    T.translation() = s * T_cur_ref.translation();
    ba.add_view(T);
  }
  const int cur = ba.add_view(T_cur_ref);
  ba.fix_view(cur);
  const auto nk = static_cast<std::size_t>(max_keypoints_);
  for (std::size_t p = 0; p < win_sel_.size(); ++p) {
    const auto pi = static_cast<int>(p);
    if (ba.inv_depth(pi) < 0.0) ba.set_inv_depth(pi, rho_median);
    const auto uj = static_cast<std::size_t>(win_sel_[p]);
    const auto ri = static_cast<std::size_t>(init_ref_idx_[uj]);
    for (int w = 0; w < win_views_; ++w) {
      const Eigen::Vector2f& uv = win_uv_[static_cast<std::size_t>(w) * nk + ri];
      if (std::isfinite(uv.x())) ba.observe(w, pi, uv.cast<double>());
    }
    ba.observe(cur, pi, init_uv1_[uj]);
  }
  // Views first (on the candidate's points), then everything; then again without the
  // observations the solution does not explain (wrong tracks).
  ba.solve(kViewsFirstIterations, true);
  ba.solve(opts_.window.iterations, false);
  ba.drop_outliers(kChi2TwoDof95);
  ba.solve(opts_.window.iterations, false);
}

}  // namespace mer::frontend
