#include "depth/keyframe_builder.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <mutex>

#include <Eigen/SVD>
#include <opencv2/imgproc.hpp>

#include "core/chi2.h"
#include "core/median.h"
#include "depth/external_depth.h"
#include "depth/plane_sweep_depth.h"
#include "depth/rgbd_depth.h"
#include "depth/triangulation_depth.h"
#include "platform/clock.h"
#include "platform/log_ring.h"

namespace mer::depth {
namespace {

constexpr std::size_t kMaxObservationsRead = 64;  // observations scanned per tracked point
constexpr int kPointRefineIterations = 5;         // Gauss-Newton steps of a point refinement
constexpr std::size_t kMinDepthHintPoints = 10;   // tracked points giving a depth range
constexpr double kDepthHintLowQuantile = 0.05;    // the range: these quantiles of their depth
constexpr double kDepthHintHighQuantile = 0.95;

}  // namespace

KeyframeBuilder::KeyframeBuilder(const DepthOptions& opts, SensorMode mode, map::Map& map,
                                 std::vector<float> level_sigma2, double metric_depth_sigma_rel,
                                 DepthMapSource* depth_maps)
    : opts_(opts),
      rgbd_(mode == SensorMode::kRgbd),
      merge_duplicates_(opts.fuse_merge_duplicates == MergeMode::kOn ||
                        (opts.fuse_merge_duplicates == MergeMode::kAuto && rgbd_)),
      map_(map),
      level_sigma2_(std::move(level_sigma2)),
      metric_depth_sigma_rel_(metric_depth_sigma_rel),
      depth_maps_(depth_maps) {}

Status KeyframeBuilder::init() {
  DepthBackend backend = opts_.backend;
  if (backend == DepthBackend::kAuto) {
    backend = rgbd_ ? DepthBackend::kRgbd : DepthBackend::kTriangulation;
  }
  backend_kind_ = backend;
  if (backend == DepthBackend::kRgbd) {
    if (!rgbd_) {
      return invalid_argument("key 'depth.backend': 'rgbd' needs pipeline.mode rgbd");
    }
    backend_ = std::make_unique<RgbdDepth>(opts_.rgbd);
    fit_depth_ = metric_depth_sigma_rel_ > 0.0;
  } else if (backend == DepthBackend::kPlaneSweep) {
    auto ps = std::make_unique<PlaneSweepDepth>(opts_.plane_sweep);
    if (Status s = ps->stereo().status(); !s.is_ok()) {
      return invalid_argument("section 'depth.plane_sweep.stereo': " + s.message());
    }
    backend_ = std::move(ps);
  } else if (backend == DepthBackend::kExternal) {
    if (depth_maps_ == nullptr) {
      return invalid_argument(
          "key 'depth.backend': 'external' needs depth maps (key 'depth.external.folder')");
    }
    backend_ = std::make_unique<ExternalDepth>(opts_.external, *depth_maps_);
    fit_depth_ = metric_depth_sigma_rel_ > 0.0 && backend_->scale() == DepthScale::kMetric && rgbd_;
  } else {
    backend_ = std::make_unique<TriangulationDepth>(opts_.triangulation);
  }
  const auto n = static_cast<std::size_t>(map_.options().max_keypoints_per_keyframe);
  depth_.resize(n);
  confidence_.resize(n);
  support_view_.resize(n);
  support_kp_.resize(n);
  view_kp_.resize(n * static_cast<std::size_t>(opts_.neighbours));
  ratios_.reserve(n);
  recent_.reserve(static_cast<std::size_t>(opts_.plane_sweep.sources));
  touched_.reserve(n * 2);
  obs_.resize(kMaxObservationsRead);
  obs_pose_.resize(kMaxObservationsRead);
  obs_uv_.resize(kMaxObservationsRead);
  obs_w_.resize(kMaxObservationsRead);
  obs_depth_.resize(kMaxObservationsRead);
  obs_depth_w_.resize(kMaxObservationsRead);
  neighbour_points_.resize(static_cast<std::size_t>(opts_.neighbours));
  for (auto& v : neighbour_points_) v.resize(n);
  views_.reserve(static_cast<std::size_t>(opts_.neighbours));
  ids_.resize(n);
  fuse_dist_.resize(n);
  kps_.resize(n);
  if (opts_.align_keypoints) {
    anchors_.resize(static_cast<std::size_t>(map_.options().max_points));
    images_.resize(static_cast<std::size_t>(opts_.align_keyframe_images));
    new_obs_.reserve(n * static_cast<std::size_t>(opts_.neighbours));
  }
  return Status::ok();
}

map::KeyframeId KeyframeBuilder::newest_in_segment(std::uint16_t segment) const {
  const map::KeyframeId newest = map_.newest_keyframe();
  if (newest == map::kNoId || map_.keyframe_segment(newest) == segment) return newest;
  // Another segment made the last keyframe: the newest of this one, by creation order.
  map::KeyframeId best = map::kNoId;
  std::uint64_t best_serial = 0;
  for (map::KeyframeId id = 0; id < map_.num_keyframes(); ++id) {
    if (!map_.keyframe_is_live(id) || map_.keyframe_segment(id) != segment) continue;
    const std::uint64_t serial = map_.keyframe_serial(id);
    if (best == map::kNoId || serial > best_serial) {
      best = id;
      best_serial = serial;
    }
  }
  return best;
}

void KeyframeBuilder::pick_neighbours(const map::KeyframeJob& job) {
  // Keyframes observing the tracked points, by count; the newest keyframe always qualifies.
  // Only keyframes of the job's segment: another segment's are in an unrelated world frame.
  neighbour_ids_.clear();
  std::vector<std::pair<std::uint32_t, std::uint32_t>> counts;  // (kf, count), small
  for (int i = 0; i < job.num_keypoints; ++i) {
    const std::uint32_t p = ids_[static_cast<std::size_t>(i)];
    if (p == map::kNoId || map_.point_is_bad(p)) continue;
    const std::size_t no = map_.point_observations(p, obs_);
    for (std::size_t o = 0; o < no; ++o) {
      const std::uint32_t kf = obs_[o].first;
      if (map_.keyframe_segment(kf) != job.segment) continue;
      auto it =
          std::find_if(counts.begin(), counts.end(), [kf](const auto& c) { return c.first == kf; });
      if (it == counts.end()) {
        counts.emplace_back(kf, 1);
      } else {
        ++it->second;
      }
    }
  }
  std::stable_sort(counts.begin(), counts.end(),
                   [](const auto& a, const auto& b) { return a.second > b.second; });
  const map::KeyframeId newest = newest_in_segment(job.segment);
  if (newest != map::kNoId) neighbour_ids_.push_back(newest);
  for (const auto& c : counts) {
    if (static_cast<int>(neighbour_ids_.size()) >= opts_.neighbours) break;
    if (c.first != newest) neighbour_ids_.push_back(c.first);
  }
}

int KeyframeBuilder::fuse_local_points(const map::KeyframeJob& job) {
  // Map points of the covisible keyframes, projected into the new keyframe and matched to its
  // keypoints (ORB-SLAM's SearchInNeighbors): points that tracking missed get their
  // observation here instead of a duplicate by triangulation, so tracks grow longer and
  // refinement / BA see wider baselines; a point matching a keypoint that tracks another
  // point is that point's duplicate and the two are merged (fuse_merge_duplicates).
  const auto n = static_cast<std::size_t>(job.num_keypoints);
  merged_ = 0;
  const map::KeyframeId newest = newest_in_segment(job.segment);
  if (opts_.fuse_keyframes <= 0 || n == 0 || newest == map::kNoId) return 0;
  fuse_kfs_.assign(neighbour_ids_.begin(), neighbour_ids_.end());  // of the job's segment
  std::vector<map::CovisibleKeyframe> covis(static_cast<std::size_t>(opts_.fuse_keyframes));
  const std::size_t nc = map_.covisible_keyframes(newest, covis);
  for (std::size_t i = 0; i < nc; ++i) {
    if (map_.keyframe_segment(covis[i].id) != job.segment) continue;
    if (std::find(fuse_kfs_.begin(), fuse_kfs_.end(), covis[i].id) == fuse_kfs_.end()) {
      fuse_kfs_.push_back(covis[i].id);
    }
  }
  if (static_cast<int>(fuse_kfs_.size()) > opts_.fuse_keyframes) {
    fuse_kfs_.resize(static_cast<std::size_t>(opts_.fuse_keyframes));
  }
  fuse_points_.clear();
  for (const std::uint32_t kf : fuse_kfs_) {
    const auto nk = static_cast<std::uint32_t>(map_.keyframe_keypoints(kf).size());
    for (std::uint32_t k = 0; k < nk; ++k) {
      const std::uint32_t p = map_.keyframe_point(kf, k);
      if (p != map::kNoId && !map_.point_is_bad(p)) fuse_points_.push_back(p);
    }
  }
  std::sort(fuse_points_.begin(), fuse_points_.end());
  fuse_points_.erase(std::unique(fuse_points_.begin(), fuse_points_.end()), fuse_points_.end());
  // Points the keyframe already tracks are not candidates.
  std::vector<std::uint32_t> tracked;
  for (std::size_t i = 0; i < n; ++i) {
    if (ids_[i] != map::kNoId) tracked.push_back(ids_[i]);
  }
  std::sort(tracked.begin(), tracked.end());

  const SE3d T_c_w = job.T_w_c.inverse();
  const Eigen::Vector3d centre = job.T_w_c.translation();
  const geometry::Pinhole& K = job.K;
  const int levels = static_cast<int>(level_sigma2_.size());
  auto level_scale = [&](int l) { return std::sqrt(level_sigma2(l)); };
  const double log_scale = std::log(std::max(1.0001, levels > 1 ? level_scale(1) : 1.2));
  // Merging needs old and new points in one scale: RGB-D mode's metric depth gives it; a
  // monocular map's scale drifts between them (merges there bent the map).
  const bool merge = merge_duplicates_;
  std::fill_n(fuse_dist_.begin(), n, std::numeric_limits<int>::max());
  std::vector<std::uint32_t> fused_point(n, map::kNoId);
  for (const std::uint32_t p : fuse_points_) {
    if (std::binary_search(tracked.begin(), tracked.end(), p)) continue;
    map::PointView pv;
    if (!map_.read_point(p, pv)) continue;
    const Eigen::Vector3d p_c = T_c_w * pv.p_w;
    if (p_c.z() <= 0.0) continue;
    const Eigen::Vector2d uv = K.project(p_c);
    const Eigen::Vector3d ray = pv.p_w - centre;
    const double dist = ray.norm();
    if (pv.normal.squaredNorm() > 0.0F &&
        ray.dot(pv.normal.cast<double>()) <
            opts_.fuse_min_view_cos * dist * static_cast<double>(pv.normal.norm())) {
      continue;
    }
    int pred = -1;
    if (pv.max_distance > 0.0F && dist > 0.0) {
      pred = std::clamp(static_cast<int>(std::ceil(std::log(pv.max_distance / dist) / log_scale)),
                        0, std::max(0, levels - 1));
    }
    const double r = opts_.fuse_radius_px * (pred >= 0 ? level_scale(pred) : 1.0);
    int best = std::numeric_limits<int>::max();
    std::size_t best_k = n;
    for (std::size_t k = 0; k < n; ++k) {
      if (ids_[k] != map::kNoId && !merge) continue;
      const features::Keypoint& kp = job.keypoints[k];
      if (pred >= 0 && std::abs(kp.level - pred) > 1) continue;
      const double dx = kp.x - uv.x();
      const double dy = kp.y - uv.y();
      if (dx * dx + dy * dy > r * r) continue;
      // chi2 (2 dof, 95 %) gate on the reprojection error at the keypoint's level.
      if (dx * dx + dy * dy > kChi2TwoDof95 * level_scale(kp.level) * level_scale(kp.level))
        continue;
      const int d = features::hamming(pv.descriptor, job.descriptors[k]);
      if (d < best) {
        best = d;
        best_k = k;
      }
    }
    if (best_k == n || best > opts_.fuse_max_hamming) continue;
    if (best >= fuse_dist_[best_k]) continue;
    fuse_dist_[best_k] = best;
    fused_point[best_k] = p;
  }
  int fused = 0;
  for (std::size_t k = 0; k < n; ++k) {
    const std::uint32_t p = fused_point[k];
    if (p == map::kNoId) continue;
    if (ids_[k] == map::kNoId) {
      ids_[k] = p;
      ++fused;
      continue;
    }
    // Keypoint k tracks point q and matches p as well: one point, created twice (e.g. before
    // and after a loop). The one with more observations stays.
    const std::uint32_t q = ids_[k];
    if (map_.point_is_bad(q) || map_.point_is_bad(p)) continue;
    const bool keep_p = map_.point_num_observations(p) > map_.point_num_observations(q);
    const std::uint32_t keep = keep_p ? p : q;
    const std::uint32_t drop = keep_p ? q : p;
    // The kept position must explain every observation of the other point.
    if (!explains_observations(keep, drop, K)) continue;
    if (map_.merge_points(keep, drop) < 0) continue;
    ids_[k] = keep;
    ++merged_;
  }
  return fused;
}

double KeyframeBuilder::level_sigma2(int level) const {
  return static_cast<double>(features::level_sigma2(level_sigma2_, level));
}

bool KeyframeBuilder::explains_observations(std::uint32_t keep, std::uint32_t drop,
                                            const geometry::Pinhole& K) {
  map::PointView pv;
  if (!map_.read_point(keep, pv)) return false;
  const std::size_t no = map_.point_observations(drop, obs_);
  for (std::size_t i = 0; i < no; ++i) {
    SE3d T_w_c;
    if (!map_.keyframe_pose(obs_[i].first, T_w_c)) return false;
    const std::span<const features::Keypoint> kps = map_.keyframe_keypoints(obs_[i].first);
    if (obs_[i].second >= kps.size()) return false;
    const features::Keypoint& kp = kps[obs_[i].second];
    const Eigen::Vector3d p_c = T_w_c.inverse() * pv.p_w;
    if (!(p_c.z() > 0.0)) return false;
    if ((K.project(p_c) - Eigen::Vector2d(kp.x, kp.y)).squaredNorm() >
        kChi2TwoDof95 * level_sigma2(kp.level)) {
      return false;
    }
  }
  return true;
}

void KeyframeBuilder::refine_point(std::uint32_t p, const geometry::Pinhole& K) {
  const std::size_t no = map_.point_observations(p, obs_);
  if (no < 2) return;
  map::PointView pv;
  if (!map_.read_point(p, pv)) return;
  Eigen::Vector3d X = pv.p_w;
  std::size_t used = 0;
  for (std::size_t o = 0; o < no && used < obs_pose_.size(); ++o) {
    SE3d T_w_c;
    if (!map_.keyframe_pose(obs_[o].first, T_w_c)) continue;
    const auto kps = map_.keyframe_keypoints(obs_[o].first);
    if (obs_[o].second >= kps.size()) continue;
    const features::Keypoint& kp = kps[obs_[o].second];
    obs_pose_[used] = T_w_c.inverse();
    obs_uv_[used] = Eigen::Vector2d(kp.x, kp.y);
    obs_w_[used] = 1.0 / level_sigma2(kp.level);
    obs_depth_[used] = 0.0;
    obs_depth_w_[used] = 0.0;
    if (fit_depth_) {
      const double d = map_.keyframe_depth(obs_[o].first, obs_[o].second);
      const double c = map_.keyframe_depth_confidence(obs_[o].first, obs_[o].second);
      if (d > 0.0 && c > 0.0) {
        const double sigma = metric_depth_sigma_rel_ * d / std::sqrt(c);
        obs_depth_[used] = d;
        obs_depth_w_[used] = 1.0 / (sigma * sigma);
      }
    }
    ++used;
  }
  if (used < 2 && !(used == 1 && obs_depth_w_[0] > 0.0)) return;
  for (int it = 0; it < kPointRefineIterations; ++it) {
    Eigen::Matrix3d H = Eigen::Matrix3d::Zero();
    Eigen::Vector3d g = Eigen::Vector3d::Zero();
    for (std::size_t o = 0; o < used; ++o) {
      const Eigen::Vector3d pc = obs_pose_[o] * X;
      if (pc.z() <= 0.0) return;
      const double iz = 1.0 / pc.z();
      const Eigen::Vector2d r = K.project(pc) - obs_uv_[o];
      Eigen::Matrix<double, 2, 3> J_p;
      J_p << K.fx * iz, 0.0, -K.fx * pc.x() * iz * iz, 0.0, K.fy * iz, -K.fy * pc.y() * iz * iz;
      const Eigen::Matrix<double, 2, 3> J = J_p * obs_pose_[o].linear();
      H += obs_w_[o] * J.transpose() * J;
      g += obs_w_[o] * J.transpose() * r;
      if (obs_depth_w_[o] > 0.0) {  // 3D-3D along the ray: d z / d X = row 2 of R_c_w
        const Eigen::RowVector3d J_z = obs_pose_[o].linear().row(2);
        H += obs_depth_w_[o] * J_z.transpose() * J_z;
        g += obs_depth_w_[o] * J_z.transpose() * (pc.z() - obs_depth_[o]);
      }
    }
    const Eigen::Vector3d dx = H.ldlt().solve(-g);
    if (!dx.allFinite()) return;
    X += dx;
    if (dx.norm() < 1e-9 * (1.0 + X.norm())) break;
  }
  // Accept only when every observation agrees.
  const double bound =
      opts_.triangulation.max_reprojection_sigmas * opts_.triangulation.max_reprojection_sigmas;
  for (std::size_t o = 0; o < used; ++o) {
    const Eigen::Vector3d pc = obs_pose_[o] * X;
    if (pc.z() <= 0.0) return;
    if ((K.project(pc) - obs_uv_[o]).squaredNorm() * obs_w_[o] > bound) return;
    const double dz = pc.z() - obs_depth_[o];
    if (obs_depth_w_[o] > 0.0 && dz * dz * obs_depth_w_[o] > bound) return;
  }
  map_.set_point_position(p, X);
}

const map::KeyframeJob& KeyframeBuilder::resolve_merged_segment(const map::KeyframeJob& tracked) {
  geometry::Sim3d S;
  const std::uint16_t segment = map_.merged_segment(tracked.segment, S);
  if (segment == tracked.segment) return tracked;
  // Tracked in a segment merged since: its poses move into the frame of the segment it joined
  // (the buffers are reused from the last time; a copy of the image shares its pixels).
  merged_job_ = tracked;
  merged_job_.segment = segment;
  merged_job_.T_w_c = geometry::apply_to_pose(S, tracked.T_w_c);
  for (int r = 0; r < tracked.num_recent; ++r) {
    merged_job_.recent_T_w_c[static_cast<std::size_t>(r)] =
        geometry::apply_to_pose(S, tracked.recent_T_w_c[static_cast<std::size_t>(r)]);
  }
  ++totals_.merged_segment_jobs;
  return merged_job_;
}

KeyframeBuildReport KeyframeBuilder::insert_segment_start(const map::KeyframeJob& job) {
  const map::SegmentStart& st = job.start;
  KeyframeBuildReport rep;
  rep.segment_start = true;
  const bool mono = st.num_views == 2;
  // Monocular: the reference view is the world frame and the job's frame the second view;
  // RGB-D: the job's frame alone.
  const auto n = static_cast<std::size_t>(job.num_keypoints);
  map::KeyframeInput cur;
  cur.segment = job.segment;
  cur.seq = job.seq;
  cur.t_ns = job.t_ns;
  cur.T_w_c = job.T_w_c;
  cur.keypoints = std::span<const features::Keypoint>(job.keypoints.data(), n);
  cur.descriptors = std::span<const features::Descriptor>(job.descriptors.data(), n);
  cur.depth = std::span<const float>(st.depth.data(), n);
  cur.depth_confidence = std::span<const float>(st.confidence.data(), n);
  const auto m = static_cast<std::size_t>(mono ? st.ref_num_keypoints : 0);
  map::KeyframeInput ref;
  ref.segment = job.segment;
  ref.seq = st.ref_seq;
  ref.t_ns = st.ref_t_ns;
  ref.T_w_c = SE3d::Identity();
  ref.keypoints = std::span<const features::Keypoint>(st.ref_keypoints.data(), m);
  ref.descriptors = std::span<const features::Descriptor>(st.ref_descriptors.data(), m);
  ref.depth = std::span<const float>(st.ref_depth.data(), m);
  ref.depth_confidence = std::span<const float>(st.ref_confidence.data(), m);
  if (map_.segment_start(job.segment).state != map::SegmentStartState::kPending) {
    // A segment starts once: one refused before holds nothing and is not written now.
    MER_LOG_ERROR("map segment %u: started or refused before; its start is not inserted",
                  unsigned{job.segment});
    ++totals_.failures;
    return rep;
  }
  const Result<map::KeyframeId> first = map_.add_keyframe(mono ? ref : cur);
  const Result<map::KeyframeId> second =
      mono && first.is_ok() ? map_.add_keyframe(cur) : Result<map::KeyframeId>(first);
  if (!first.is_ok() || !second.is_ok()) {
    MER_LOG_ERROR("map segment %u: its start could not be inserted: %s", unsigned{job.segment},
                  (!first.is_ok() ? first.status() : second.status()).message().c_str());
    ++totals_.failures;
    map_.publish_segment_start(job.segment, map::SegmentStartState::kRefused, map::kNoId,
                               map::kNoId);
    return rep;
  }
  int added = 0;
  for (int i = 0; i < st.num_points; ++i) {
    const auto ui = static_cast<std::size_t>(i);
    const Result<map::PointId> p =
        map_.add_point(st.points_w[ui], first.value(), st.first_keypoint[ui]);
    if (!p.is_ok()) break;
    if (mono) (void)map_.add_observation(p.value(), second.value(), st.second_keypoint[ui]);
    map_.update_point(p.value());
    ++added;
  }
  if (mono) map_.update_covisibility(second.value());
  map_.publish_segment_start(job.segment, map::SegmentStartState::kInserted, first.value(),
                             second.value());
  rep.keyframe = second.value();
  rep.new_points = added;
  ++totals_.segment_starts;
  totals_.start_points += static_cast<std::uint64_t>(added);
  return rep;
}

KeyframeBuildReport KeyframeBuilder::spin_once(const map::KeyframeJob& tracked) {
  // The whole pass is one writer section: depth inference reads writer-side state
  // (observations of the neighbours' points) and the insertion must see it unchanged.
  const std::lock_guard<platform::PiMutex> lock(map_.writer_lock());
  if (tracked.kind == map::KeyframeJobKind::kSegmentStart) return insert_segment_start(tracked);
  const map::KeyframeJob& job = resolve_merged_segment(tracked);
  const auto t0 = platform::monotonic_now_ns();
  KeyframeBuildReport rep;
  load_job(job);

  // 1. Neighbours, projection of their points, and depth inference.
  pick_neighbours(job);
  rep.fused_observations = fuse_local_points(job);
  rep.merged_points = merged_;
  if (!anchors_.empty()) {
    build_pyramid(job.gray);
    align_tracked(job, rep);
  }
  const DepthResult out = infer_depth(job, rep);
  // 2. Scale alignment with the 3D-2D matches.
  align_depth_scale(job, rep);
  // 3. Insert the keyframe with its local depth.
  const map::KeyframeId kf = insert_keyframe(job);
  if (kf == map::kNoId) return rep;
  rep.keyframe = kf;
  // 4-5. Observations of the tracked points, new points, refinement.
  add_structure(job, kf, out, rep);
  rep.ok = true;
  add_to_totals(rep, platform::elapsed_ms(t0));
  return rep;
}

void KeyframeBuilder::load_job(const map::KeyframeJob& job) {
  const auto n = static_cast<std::size_t>(job.num_keypoints);
  std::copy_n(job.keypoints.begin(), n, kps_.begin());
  std::copy_n(job.point_ids.begin(), n, ids_.begin());
  // A tracked point culled since (its slot possibly reused by another point) is not tracked.
  for (std::size_t i = 0; i < n && job.point_gens.size() >= n; ++i) {
    if (ids_[i] != map::kNoId && map_.point_generation(ids_[i]) != job.point_gens[i]) {
      ids_[i] = map::kNoId;
    }
  }
}

DepthResult KeyframeBuilder::infer_depth(const map::KeyframeJob& job, KeyframeBuildReport& rep) {
  const auto n = static_cast<std::size_t>(job.num_keypoints);
  const std::span<const features::Keypoint> kps(kps_.data(), n);
  const std::span<const features::Descriptor> descs(job.descriptors.data(), n);
  const std::span<const std::uint32_t> ids(ids_.data(), n);
  views_.clear();
  for (std::size_t v = 0; v < neighbour_ids_.size(); ++v) {
    const std::uint32_t kf = neighbour_ids_[v];
    DepthView view;
    view.id = kf;
    if (!map_.keyframe_pose(kf, view.T_w_c)) continue;
    view.keypoints = map_.keyframe_keypoints(kf);
    view.descriptors = map_.keyframe_descriptors(kf);
    std::vector<std::uint32_t>& pts = neighbour_points_[views_.size()];
    for (std::size_t k = 0; k < view.keypoints.size(); ++k) {
      pts[k] = map_.keyframe_point(kf, static_cast<std::uint32_t>(k));
    }
    view.point_ids = std::span<const std::uint32_t>(pts.data(), view.keypoints.size());
    views_.push_back(view);
  }
  rep.neighbours = static_cast<int>(views_.size());
  DepthRequest req;
  req.t_ns = job.t_ns;
  req.T_w_c = job.T_w_c;
  req.K = job.K;
  req.keypoints = kps;
  req.descriptors = descs;
  req.point_ids = ids;
  if (job.has_sensor_depth) req.sensor_depth = std::span<const float>(job.sensor_depth.data(), n);
  req.level_sigma2 = level_sigma2_;
  req.gray = &job.gray;
  req.views = views_;
  recent_.clear();
  for (int r = 0; r < job.num_recent; ++r) {
    recent_.push_back({&job.recent_gray[static_cast<std::size_t>(r)],
                       job.recent_T_w_c[static_cast<std::size_t>(r)]});
  }
  req.recent = recent_;
  // Depth range of the tracked map-points (5th-95th percentile) for range-sweeping backends.
  {
    const SE3d T_c_w_hint = job.T_w_c.inverse();
    ratios_.clear();
    for (std::size_t i = 0; i < n; ++i) {
      if (ids[i] == map::kNoId) continue;
      map::PointView pv;
      if (!map_.read_point(ids[i], pv)) continue;
      const double z = (T_c_w_hint * pv.p_w).z();
      if (z > 0.0) ratios_.push_back(z);
    }
    if (ratios_.size() >= kMinDepthHintPoints) {
      std::sort(ratios_.begin(), ratios_.end());
      const auto at = [&](double q) {
        return ratios_[static_cast<std::size_t>(q * static_cast<double>(ratios_.size() - 1))];
      };
      req.depth_hint_min = at(kDepthHintLowQuantile);
      req.depth_hint_max = at(kDepthHintHighQuantile);
    }
  }
  DepthResult out;
  out.depth = std::span<float>(depth_.data(), n);
  out.confidence = std::span<float>(confidence_.data(), n);
  out.support_view = std::span<std::uint32_t>(support_view_.data(), n);
  out.support_keypoint = std::span<std::uint32_t>(support_kp_.data(), n);
  out.view_keypoint = std::span<std::uint32_t>(view_kp_.data(), n * views_.size());
  const Status ds = backend_->infer(req, out);
  if (!ds.is_ok()) {
    if (out.input_missing) {
      ++totals_.depth_missing;
      MER_LOG_WARN("keyframe %llu: no depth: %s", static_cast<unsigned long long>(job.seq),
                   ds.message().c_str());
    } else {
      ++totals_.depth_errors;
      MER_LOG_WARN("keyframe %llu: depth inference failed: %s",
                   static_cast<unsigned long long>(job.seq), ds.message().c_str());
    }
    std::fill_n(depth_.begin(), n, 0.0F);
    out.num_valid = 0;
  }
  rep.depth_valid = out.num_valid;
  if (out.fates.free == 0) {
    // A backend that does not match across views: free keypoints, and those with a depth.
    for (std::size_t i = 0; i < n; ++i) {
      if (ids[i] != map::kNoId) continue;
      ++out.fates.free;
      out.fates.depth += depth_[i] > 0.0F;
    }
  }
  rep.fates = out.fates;
  return out;
}

void KeyframeBuilder::align_depth_scale(const map::KeyframeJob& job, KeyframeBuildReport& rep) {
  const auto n = static_cast<std::size_t>(job.num_keypoints);
  const std::span<const std::uint32_t> ids(ids_.data(), n);
  // Ratio of map depth to inferred depth.
  const SE3d T_c_w = job.T_w_c.inverse();
  ratios_.clear();
  for (std::size_t i = 0; i < n; ++i) {
    if (ids[i] == map::kNoId || depth_[i] <= 0.0F) continue;
    map::PointView pv;
    if (!map_.read_point(ids[i], pv)) continue;
    const double z = (T_c_w * pv.p_w).z();
    if (z > 0.0) ratios_.push_back(z / depth_[i]);
  }
  rep.scale_samples = static_cast<int>(ratios_.size());
  if (!ratios_.empty()) rep.scale_ratio = upper_median(ratios_);
  // Depth already in map units (triangulation) or metric in an RGB-D (metric) map is kept;
  // anything else is aligned, and refused without enough samples.
  const bool needs_alignment = backend_->scale() == DepthScale::kUnknown ||
                               (backend_->scale() == DepthScale::kMetric && !rgbd_);
  if (needs_alignment) {
    if (rep.scale_samples >= opts_.min_scale_samples) {
      for (std::size_t i = 0; i < n; ++i) depth_[i] *= static_cast<float>(rep.scale_ratio);
      rep.scale_applied = true;
    } else {
      std::fill_n(depth_.begin(), n, 0.0F);
    }
  }
}

map::KeyframeId KeyframeBuilder::insert_keyframe(const map::KeyframeJob& job) {
  const auto n = static_cast<std::size_t>(job.num_keypoints);
  map::KeyframeInput in;
  in.segment = job.segment;
  in.seq = job.seq;
  in.t_ns = job.t_ns;
  in.T_w_c = job.T_w_c;
  in.keypoints = std::span<const features::Keypoint>(kps_.data(), n);
  in.descriptors = std::span<const features::Descriptor>(job.descriptors.data(), n);
  in.depth = std::span<const float>(depth_.data(), n);
  in.depth_confidence = std::span<const float>(confidence_.data(), n);
  const Result<map::KeyframeId> added = map_.add_keyframe(in);
  if (!added.is_ok()) {
    ++totals_.failures;
    MER_LOG_WARN("keyframe %llu not created: %s", static_cast<unsigned long long>(job.seq),
                 added.status().message().c_str());
    return map::kNoId;
  }
  return added.value();
}

void KeyframeBuilder::add_structure(const map::KeyframeJob& job, map::KeyframeId kf,
                                    const DepthResult& out, KeyframeBuildReport& rep) {
  const auto n = static_cast<std::size_t>(job.num_keypoints);
  const std::span<const features::Keypoint> kps(kps_.data(), n);
  const std::span<const std::uint32_t> ids(ids_.data(), n);
  // 4. 3D-2D edges of the tracked map-points.
  touched_.clear();
  for (std::size_t i = 0; i < n; ++i) {
    if (ids[i] == map::kNoId || map_.point_is_bad(ids[i])) continue;
    if (map_.add_observation(ids[i], kf, static_cast<std::uint32_t>(i))) {
      ++rep.tracked_observations;
      touched_.push_back(ids[i]);
    }
  }

  // 5. New map-points from confident local 3D points.
  new_obs_.clear();
  for (std::size_t i = 0; i < n; ++i) {
    if (ids[i] != map::kNoId || depth_[i] <= 0.0F || confidence_[i] < opts_.min_confidence) {
      continue;
    }
    if (map_.keyframe_point(kf, static_cast<std::uint32_t>(i)) != map::kNoId) continue;
    const Eigen::Vector3d p_c = job.K.unproject({kps[i].x, kps[i].y}) * depth_[i];
    const Result<map::PointId> p =
        map_.add_point(job.T_w_c * p_c, kf, static_cast<std::uint32_t>(i));
    if (!p.is_ok()) break;  // map full: counted by the map, logged once below
    ++rep.new_points;
    const std::uint32_t sv = support_view_[i];
    if (sv != kNoSupport && sv < views_.size() &&
        map_.add_observation(p.value(), views_[sv].id, support_kp_[i]) && !anchors_.empty()) {
      new_obs_.push_back({p.value(), views_[sv].id, support_kp_[i]});
    }
    if (!out.view_keypoint.empty()) {
      for (std::size_t v = 0; v < views_.size(); ++v) {
        const std::uint32_t j = out.view_keypoint[i * views_.size() + v];
        if (j == kNoSupport || v == sv) continue;
        if (map_.add_observation(p.value(), views_[v].id, j)) {
          ++rep.view_observations;
          if (!anchors_.empty()) new_obs_.push_back({p.value(), views_[v].id, j});
        }
      }
    }
    touched_.push_back(p.value());
  }
  // Structure refinement: a tracked point seen from a new keyframe gets a wider baseline;
  // re-estimate its position over all its observations (Gauss-Newton on reprojection error,
  // poses fixed) so depth errors of young low-parallax points do not persist.
  for (std::size_t t = 0; t < static_cast<std::size_t>(rep.tracked_observations); ++t) {
    refine_point(touched_[t], job.K);
  }
  for (const std::uint32_t p : touched_) map_.update_point(p);
  map_.update_covisibility(kf);
  if (!anchors_.empty()) {
    set_anchors(job, kf);
    align_new_observations(job.K, rep);
    image_next_ = (image_next_ + 1) % images_.size();
  }
}

void KeyframeBuilder::add_to_totals(const KeyframeBuildReport& rep, double ms) {
  ++totals_.keyframes;
  totals_.new_points += static_cast<std::uint64_t>(rep.new_points);
  totals_.observations += static_cast<std::uint64_t>(rep.tracked_observations);
  totals_.fused_observations += static_cast<std::uint64_t>(rep.fused_observations);
  totals_.merged_points += static_cast<std::uint64_t>(rep.merged_points);
  totals_.view_observations += static_cast<std::uint64_t>(rep.view_observations);
  totals_.aligned_keypoints += static_cast<std::uint64_t>(rep.aligned_keypoints);
  totals_.align_refused += static_cast<std::uint64_t>(rep.align_refused);
  totals_.align_refused_residual += static_cast<std::uint64_t>(rep.align_refused_residual);
  totals_.align_refused_shift += static_cast<std::uint64_t>(rep.align_refused_shift);
  totals_.depth_valid += static_cast<std::uint64_t>(rep.depth_valid);
  totals_.fates.add(rep.fates);
  totals_.total_ms += ms;
  totals_.max_ms = std::max(totals_.max_ms, ms);
}

}  // namespace mer::depth
