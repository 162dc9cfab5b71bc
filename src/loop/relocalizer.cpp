#include "loop/relocalizer.h"

#include <algorithm>
#include <cmath>
#include <limits>

#include <Eigen/Geometry>

#include "core/chi2.h"
#include "loop/descriptor_match.h"
#include "platform/clock.h"

namespace mer::loop {

namespace {

/// Squared reprojection error / sigma^2 of an inlier (2 dof, 95 %), as the tracker's gate.
/// Keypoint grid of the projection search: cells over the keypoints' bounding box.
constexpr int kGridCols = 48;
constexpr int kGridRows = 36;
/// Covisible keyframes read per candidate.
constexpr std::size_t kMaxCovisible = 64;

}  // namespace

Relocalizer::Relocalizer(const RelocalizerOptions& opts, map::Map& map, KeyframeDatabase& db,
                         int map_reader, bool deterministic)
    : opts_(opts), map_(map), db_(db), reader_(map_reader), deterministic_(deterministic) {
  const map::MapOptions& mo = map.options();
  const auto nkp = static_cast<std::size_t>(std::max(1, opts_.max_keypoints));
  const std::size_t max_kfs =
      1 + static_cast<std::size_t>(std::max(opts_.match_neighbours, opts_.local_keyframes));
  const std::size_t max_pts = max_kfs * static_cast<std::size_t>(mo.max_keypoints_per_keyframe);
  // One correspondence per frame keypoint at most (matches are one-to-one on keypoints).
  pnp_ = std::make_unique<geometry::PnpRansac>(opts_.pnp, nkp);
  hits_.resize(static_cast<std::size_t>(opts_.max_candidates));
  covis_.resize(kMaxCovisible);
  kfs_.reserve(max_kfs);
  point_stamp_.assign(static_cast<std::size_t>(mo.max_points), 0U);
  pts_p_w_.reserve(max_pts);
  pts_desc_.reserve(max_pts);
  pts_id_.reserve(max_pts);
  kp_best_.resize(nkp);
  kp_point_.resize(nkp);
  corr_X_.resize(nkp);
  corr_uv_.resize(nkp);
  corr_kp_.resize(nkp);
  corr_pid_.resize(nkp);
  corr_sigma_.resize(nkp);
  corr_mask_.resize(nkp);
  cell_start_.resize(static_cast<std::size_t>(kGridCols * kGridRows) + 1);
  cell_kp_.resize(nkp);
  kp_cell_.resize(nkp);
}

Relocalizer::~Relocalizer() = default;

RelocResult Relocalizer::spin_once(const RelocQuery& q) {
  const auto t0 = platform::monotonic_now_ns();
  RelocResult r;
  if (reader_ >= 0) map_.reader_quiescent(reader_);
  const std::size_t n_kp = std::min({q.keypoints.size(), q.descriptors.size(), kp_best_.size()});
  if (n_kp == 0 || !(q.K.fx > 0.0) || !(q.K.fy > 0.0)) {
    r.ms = platform::elapsed_ms(t0);
    return r;
  }
  const RelocQuery frame{q.seq, q.t_ns, q.keypoints.first(n_kp), q.descriptors.first(n_kp), q.K};

  // 1. Retrieval.
  std::size_t nh = 0;
  {
    const std::lock_guard<platform::PiMutex> lock(db_.mutex());
    db_.refresh_live();
    nh = db_.query(frame.descriptors, hits_);
  }
  r.retrieved = static_cast<int>(nh);
  build_grid(frame, n_kp);

  for (std::size_t h = 0; h < nh; ++h) {
    if (!deterministic_ && h > 0 && platform::elapsed_ms(t0) > opts_.max_time_ms) {
      r.timed_out = true;
      break;
    }
    const RetrievalHit& hit = hits_[h];
    if (map_.keyframe_generation(hit.id) != hit.generation) continue;     // culled meanwhile
    if (map_.segment_discarded(map_.keyframe_segment(hit.id))) continue;  // a failed start's
    ++r.candidates_tried;
    if (try_keyframe(frame, hit.id, r)) {
      r.generation = hit.generation;
      break;
    }
  }
  r.ms = platform::elapsed_ms(t0);
  return r;
}

RelocResult Relocalizer::localize_against(const RelocQuery& q, map::KeyframeId kf) {
  const auto t0 = platform::monotonic_now_ns();
  RelocResult r;
  if (reader_ >= 0) map_.reader_quiescent(reader_);
  const std::size_t n_kp = std::min({q.keypoints.size(), q.descriptors.size(), kp_best_.size()});
  if (n_kp == 0 || !(q.K.fx > 0.0) || !(q.K.fy > 0.0) || !map_.keyframe_is_live(kf)) {
    r.ms = platform::elapsed_ms(t0);
    return r;
  }
  const RelocQuery frame{q.seq, q.t_ns, q.keypoints.first(n_kp), q.descriptors.first(n_kp), q.K};
  build_grid(frame, n_kp);
  r.candidates_tried = 1;
  if (try_keyframe(frame, kf, r)) r.generation = map_.keyframe_generation(kf);
  r.ms = platform::elapsed_ms(t0);
  return r;
}

bool Relocalizer::try_keyframe(const RelocQuery& frame, map::KeyframeId id, RelocResult& r) {
  // 2. The candidate and its best covisible keyframes: descriptor matches, PnP-RANSAC.
  last_corr_ = 0;
  kfs_.clear();
  kfs_.push_back(id);
  const std::size_t nc = map_.covisible_keyframes(id, covis_);
  const auto n_local = std::min<std::size_t>(nc, static_cast<std::size_t>(opts_.local_keyframes));
  const auto n_match = std::min<std::size_t>(nc, static_cast<std::size_t>(opts_.match_neighbours));
  // Order: the match set first, so the points it gathers are a prefix of the local map's.
  for (std::size_t k = 0; k < std::max(n_local, n_match); ++k) kfs_.push_back(covis_[k].id);
  ++stamp_;
  if (stamp_ == 0) {  // wrapped: forget every stamp
    std::fill(point_stamp_.begin(), point_stamp_.end(), 0U);
    stamp_ = 1;
  }
  pts_p_w_.clear();
  pts_desc_.clear();
  pts_id_.clear();
  const std::size_t n_match_pts = gather_points(1 + n_match);
  const int m = match_descriptors(frame, n_match_pts);
  r.matches = m;
  r.pnp_inliers = 0;
  r.inliers = 0;
  if (m < opts_.min_matches) return false;
  geometry::PnpInput in;
  const auto um = static_cast<std::size_t>(m);
  in.X_w = std::span<const Eigen::Vector3d>(corr_X_.data(), um);
  in.uv = std::span<const Eigen::Vector2d>(corr_uv_.data(), um);
  in.sigma = std::span<const float>(corr_sigma_.data(), um);
  in.K = frame.K;
  const geometry::PnpResult pr = pnp_->solve(in, std::span<std::uint8_t>(corr_mask_.data(), um));
  r.pnp_inliers = pr.num_inliers;
  if (!pr.ok) return false;

  // 3. Refinement on the local map's points found by projection.
  SE3d T = pr.T_c_w;
  const std::size_t n_local_pts = gather_points(kfs_.size());
  const int mp = match_projection(frame, n_local_pts, T);
  const int inliers = mp >= opts_.min_inliers ? refine(frame, mp, T) : 0;
  r.inliers = inliers;
  if (inliers < opts_.min_inliers) return false;
  r.success = true;
  last_corr_ = static_cast<std::size_t>(mp);
  r.T_c_w = T;  // rotation back onto SO(3) after the refinement's updates
  r.T_c_w.linear() = Eigen::Quaterniond(T.linear()).normalized().toRotationMatrix();
  r.keyframe = id;
  return true;
}

std::size_t Relocalizer::last_inliers(std::vector<std::uint32_t>& keypoints,
                                      std::vector<Eigen::Vector3d>& X_w,
                                      std::vector<map::PointId>* points) const {
  std::size_t n = 0;
  for (std::size_t i = 0; i < last_corr_; ++i) {
    if (corr_mask_[i] == 0) continue;
    keypoints.push_back(corr_kp_[i]);
    X_w.push_back(corr_X_[i]);
    if (points != nullptr) points->push_back(corr_pid_[i]);
    ++n;
  }
  return n;
}

std::size_t Relocalizer::gather_points(std::size_t num_kfs) {
  // kfs_[0, num_kfs); keyframes already gathered add nothing new (their points are stamped).
  for (std::size_t k = 0; k < num_kfs && k < kfs_.size(); ++k) {
    const map::KeyframeId id = kfs_[k];
    const std::uint32_t n = map_.keyframe_num_keypoints(id);
    for (std::uint32_t j = 0; j < n && pts_p_w_.size() < pts_p_w_.capacity(); ++j) {
      const map::PointId p = map_.keyframe_point(id, j);
      if (p == map::kNoId || p >= point_stamp_.size() || point_stamp_[p] == stamp_) continue;
      map::PointView v;
      if (!map_.read_point(p, v)) continue;
      point_stamp_[p] = stamp_;
      pts_p_w_.push_back(v.p_w);
      pts_desc_.push_back(v.descriptor);
      pts_id_.push_back(p);
    }
  }
  return pts_p_w_.size();
}

int Relocalizer::match_descriptors(const RelocQuery& q, std::size_t n) {
  const std::size_t n_kp = q.keypoints.size();
  std::fill_n(kp_best_.begin(), n_kp, std::numeric_limits<int>::max());
  std::fill_n(kp_point_.begin(), n_kp, -1);
  // Per point, the nearest frame keypoint (ratio test); per keypoint, the nearest such point.
  for (std::size_t i = 0; i < n; ++i) {
    const NearestTwo nn = nearest_two(
        pts_desc_[i], n_kp, [&](std::size_t k) -> const auto& { return q.descriptors[k]; });
    if (!nn.passes(opts_.max_descriptor_distance, opts_.ratio) || nn.best >= kp_best_[nn.index]) {
      continue;
    }
    kp_best_[nn.index] = nn.best;
    kp_point_[nn.index] = static_cast<std::int32_t>(i);
  }
  return collect_correspondences(q);
}

int Relocalizer::collect_correspondences(const RelocQuery& q) {
  int m = 0;
  for (std::size_t k = 0; k < q.keypoints.size(); ++k) {
    if (kp_point_[k] < 0) continue;
    const auto mi = static_cast<std::size_t>(m++);
    const features::Keypoint& kp = q.keypoints[k];
    corr_X_[mi] = pts_p_w_[static_cast<std::size_t>(kp_point_[k])];
    corr_uv_[mi] = Eigen::Vector2d(kp.x, kp.y);
    corr_kp_[mi] = static_cast<std::uint32_t>(k);
    corr_pid_[mi] = pts_id_[static_cast<std::size_t>(kp_point_[k])];
    corr_sigma_[mi] = kp.scale > 0.0F ? kp.scale : 1.0F;
  }
  return m;
}

void Relocalizer::build_grid(const RelocQuery& q, std::size_t n) {
  double x0 = std::numeric_limits<double>::infinity();
  double y0 = x0;
  double x1 = -x0;
  double y1 = -x0;
  for (std::size_t k = 0; k < n; ++k) {
    x0 = std::min(x0, static_cast<double>(q.keypoints[k].x));
    x1 = std::max(x1, static_cast<double>(q.keypoints[k].x));
    y0 = std::min(y0, static_cast<double>(q.keypoints[k].y));
    y1 = std::max(y1, static_cast<double>(q.keypoints[k].y));
  }
  grid_x0_ = x0;
  grid_y0_ = y0;
  grid_cols_ = kGridCols;
  grid_rows_ = kGridRows;
  cell_w_ = std::max(1.0, (x1 - x0) / kGridCols + 1e-6);
  cell_h_ = std::max(1.0, (y1 - y0) / kGridRows + 1e-6);
  std::fill(cell_start_.begin(), cell_start_.end(), 0U);
  for (std::size_t k = 0; k < n; ++k) {
    const int cx =
        std::clamp(static_cast<int>((q.keypoints[k].x - x0) / cell_w_), 0, kGridCols - 1);
    const int cy =
        std::clamp(static_cast<int>((q.keypoints[k].y - y0) / cell_h_), 0, kGridRows - 1);
    kp_cell_[k] = static_cast<std::uint32_t>(cy * kGridCols + cx);
    ++cell_start_[kp_cell_[k] + 1];
  }
  for (std::size_t c = 1; c < cell_start_.size(); ++c) cell_start_[c] += cell_start_[c - 1];
  // Fill with each cell's start as its cursor.
  for (std::size_t k = 0; k < n; ++k)
    cell_kp_[cell_start_[kp_cell_[k]]++] = static_cast<std::uint32_t>(k);
  // cell_start_[c] now holds the end of cell c: shift back to starts.
  for (std::size_t c = cell_start_.size() - 1; c > 0; --c) cell_start_[c] = cell_start_[c - 1];
  cell_start_[0] = 0;
}

int Relocalizer::match_projection(const RelocQuery& q, std::size_t n, const SE3d& T_c_w) {
  const std::size_t n_kp = q.keypoints.size();
  std::fill_n(kp_best_.begin(), n_kp, std::numeric_limits<int>::max());
  std::fill_n(kp_point_.begin(), n_kp, -1);
  double max_scale = 1.0;
  for (std::size_t k = 0; k < n_kp; ++k)
    max_scale = std::max(max_scale, static_cast<double>(q.keypoints[k].scale));
  const double r_max = opts_.search_radius_px * max_scale;
  for (std::size_t i = 0; i < n; ++i) {
    const Eigen::Vector3d p_c = T_c_w * pts_p_w_[i];
    if (!(p_c.z() > 0.0)) continue;
    const Eigen::Vector2d uv = q.K.project(p_c);
    const int cx0 = static_cast<int>(std::floor((uv.x() - r_max - grid_x0_) / cell_w_));
    const int cx1 = static_cast<int>(std::floor((uv.x() + r_max - grid_x0_) / cell_w_));
    const int cy0 = static_cast<int>(std::floor((uv.y() - r_max - grid_y0_) / cell_h_));
    const int cy1 = static_cast<int>(std::floor((uv.y() + r_max - grid_y0_) / cell_h_));
    if (cx1 < 0 || cy1 < 0 || cx0 >= grid_cols_ || cy0 >= grid_rows_) continue;
    int best = std::numeric_limits<int>::max();
    std::uint32_t best_k = 0;
    for (int cy = std::max(cy0, 0); cy <= std::min(cy1, grid_rows_ - 1); ++cy) {
      for (int cx = std::max(cx0, 0); cx <= std::min(cx1, grid_cols_ - 1); ++cx) {
        const auto c = static_cast<std::size_t>(cy * grid_cols_ + cx);
        for (std::uint32_t e = cell_start_[c]; e < cell_start_[c + 1]; ++e) {
          const std::uint32_t k = cell_kp_[e];
          const features::Keypoint& kp = q.keypoints[k];
          const double r = opts_.search_radius_px * kp.scale;
          const double dx = kp.x - uv.x();
          const double dy = kp.y - uv.y();
          if (dx * dx + dy * dy > r * r) continue;
          const int d = features::hamming(pts_desc_[i], q.descriptors[k]);
          if (d < best) {
            best = d;
            best_k = k;
          }
        }
      }
    }
    if (best > opts_.max_projection_distance || best >= kp_best_[best_k]) continue;
    kp_best_[best_k] = best;
    kp_point_[best_k] = static_cast<std::int32_t>(i);
  }
  return collect_correspondences(q);
}

int Relocalizer::refine(const RelocQuery& q, int m, SE3d& T_c_w) {
  const auto um = static_cast<std::size_t>(m);
  geometry::PnpInput in;
  in.X_w = std::span<const Eigen::Vector3d>(corr_X_.data(), um);
  in.uv = std::span<const Eigen::Vector2d>(corr_uv_.data(), um);
  in.sigma = std::span<const float>(corr_sigma_.data(), um);
  in.K = q.K;
  geometry::RefineOptions ro;
  ro.iterations = opts_.pnp.refine_iterations;
  ro.huber_px = opts_.pnp.huber_px;
  int inliers = 0;
  for (int pass = 0; pass < 2; ++pass) {
    (void)geometry::refine_pose(in,
                                pass == 0 ? std::span<const std::uint8_t>{}
                                          : std::span<const std::uint8_t>(corr_mask_.data(), um),
                                T_c_w, nullptr, ro);
    inliers = 0;
    for (std::size_t i = 0; i < um; ++i) {
      const Eigen::Vector3d p_c = T_c_w * corr_X_[i];
      const double s2 = static_cast<double>(corr_sigma_[i]) * corr_sigma_[i];
      const bool ok =
          p_c.z() > 0.0 && (q.K.project(p_c) - corr_uv_[i]).squaredNorm() < kChi2TwoDof95 * s2;
      corr_mask_[i] = ok ? 1 : 0;
      inliers += ok ? 1 : 0;
    }
  }
  return inliers;
}

}  // namespace mer::loop
