// Trajectory evaluation: association, Umeyama alignment, ATE and RPE (see trajectory_eval.h).
#include "eval/trajectory_eval.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <numbers>
#include <sstream>

#include <Eigen/Geometry>

#include "geometry/lie.h"

namespace mer::eval {

std::optional<Alignment> parse_alignment(const std::string& s) {
  if (s == "none") return Alignment::kNone;
  if (s == "se3") return Alignment::kSe3;
  if (s == "sim3") return Alignment::kSim3;
  if (s == "rotation") return Alignment::kRotation;
  return std::nullopt;
}

const char* alignment_name(Alignment a) {
  switch (a) {
    case Alignment::kNone:
      return "none";
    case Alignment::kSe3:
      return "se3";
    case Alignment::kSim3:
      return "sim3";
    case Alignment::kRotation:
      return "rotation";
  }
  return "?";
}

std::vector<PosePair> associate(const hal::Trajectory& gt, const hal::Trajectory& est,
                                std::int64_t max_dt_ns) {
  struct Candidate {
    std::int64_t dt;
    std::size_t est;
    std::size_t gt;
  };
  // Every (estimate, ground truth) pair within max_dt; both lists are sorted by time, so
  // the ground-truth candidates of an estimate are one contiguous range.
  std::vector<Candidate> candidates;
  const auto& g = gt.poses;
  for (std::size_t i = 0; i < est.poses.size(); ++i) {
    const std::int64_t t = est.poses[i].t_ns;
    auto it = std::lower_bound(g.begin(), g.end(), t - max_dt_ns,
                               [](const StampedPose& p, std::int64_t v) { return p.t_ns < v; });
    for (; it != g.end() && it->t_ns <= t + max_dt_ns; ++it) {
      candidates.push_back({std::abs(it->t_ns - t), i, static_cast<std::size_t>(it - g.begin())});
    }
  }
  // Greedy by increasing |dt| (ties: earlier estimate, then earlier ground truth); a pose
  // on either side is used at most once.
  std::sort(candidates.begin(), candidates.end(), [](const Candidate& a, const Candidate& b) {
    if (a.dt != b.dt) return a.dt < b.dt;
    if (a.est != b.est) return a.est < b.est;
    return a.gt < b.gt;
  });
  std::vector<bool> est_used(est.poses.size(), false);
  std::vector<bool> gt_used(g.size(), false);
  std::vector<PosePair> pairs;
  for (const Candidate& c : candidates) {
    if (est_used[c.est] || gt_used[c.gt]) continue;
    est_used[c.est] = true;
    gt_used[c.gt] = true;
    pairs.push_back({c.gt, c.est});
  }
  std::sort(pairs.begin(), pairs.end(),
            [](const PosePair& a, const PosePair& b) { return a.est < b.est; });
  return pairs;
}

std::vector<PosePair> associate_by_index(const hal::Trajectory& gt, const hal::Trajectory& est) {
  std::vector<PosePair> pairs;
  const std::size_t n = std::min(gt.poses.size(), est.poses.size());
  pairs.reserve(n);
  for (std::size_t i = 0; i < n; ++i) pairs.push_back({i, i});
  return pairs;
}

SE3d Sim3::apply(const SE3d& T) const {
  SE3d out = SE3d::Identity();
  out.linear() = R * T.linear();
  out.translation() = apply(Eigen::Vector3d(T.translation()));
  return out;
}

Sim3 align_positions(const std::vector<Eigen::Vector3d>& src,
                     const std::vector<Eigen::Vector3d>& dst, Alignment alignment) {
  Sim3 s;
  if (alignment == Alignment::kNone || alignment == Alignment::kRotation || src.size() < 3 ||
      src.size() != dst.size()) {
    return s;
  }
  Eigen::Matrix3Xd a(3, static_cast<Eigen::Index>(src.size()));
  Eigen::Matrix3Xd b(3, static_cast<Eigen::Index>(dst.size()));
  for (std::size_t i = 0; i < src.size(); ++i) {
    a.col(static_cast<Eigen::Index>(i)) = src[i];
    b.col(static_cast<Eigen::Index>(i)) = dst[i];
  }
  const Eigen::Matrix4d T = Eigen::umeyama(a, b, alignment == Alignment::kSim3);
  // s * R: the scaled rotation block of the Umeyama transform.
  const Eigen::Matrix3d s_times_r = T.topLeftCorner<3, 3>();
  s.scale = alignment == Alignment::kSim3 ? std::cbrt(s_times_r.determinant()) : 1.0;
  s.R = s_times_r / s.scale;
  s.t = T.topRightCorner<3, 1>();
  return s;
}

namespace {

// Angle of a rotation matrix (geometry::so3_log: accurate near zero, where acos of the trace
// loses half the digits).
double rotation_angle(const Eigen::Matrix3d& R) {
  return geometry::so3_log(R).norm();
}

void compute_rpe(const std::vector<SE3d>& G, const std::vector<SE3d>& P, const RpeOptions& opt,
                 EvalResult& r) {
  const std::size_t n = G.size();
  // Cumulative ground-truth path length along the pairs.
  std::vector<double> dist(n, 0.0);
  for (std::size_t i = 1; i < n; ++i) {
    dist[i] = dist[i - 1] + (G[i].translation() - G[i - 1].translation()).norm();
  }
  double sum_t = 0.0;
  double sum_r = 0.0;
  std::size_t count = 0;
  std::size_t j = 0;
  for (std::size_t i = 0; i < n; ++i) {
    if (opt.delta_frames.has_value()) {
      if (*opt.delta_frames == 0) break;
      j = i + *opt.delta_frames;
      if (j >= n) break;
    } else {
      if (opt.delta_m <= 0.0) break;
      j = std::max(j, i + 1);
      while (j < n && dist[j] - dist[i] < opt.delta_m) ++j;
      if (j >= n) break;
    }
    const double len = dist[j] - dist[i];
    if (len <= 0.0) continue;  // no motion in the segment: per-metre errors undefined
    const SE3d dg = G[i].inverse() * G[j];
    const SE3d dp = P[i].inverse() * P[j];
    const SE3d e = dg.inverse() * dp;
    sum_t += e.translation().norm() / len;
    sum_r += rotation_angle(e.linear()) / len;
    ++count;
  }
  r.rpe_segments = count;
  if (count > 0) {
    r.rpe_trans_pct = 100.0 * sum_t / static_cast<double>(count);
    r.rpe_rot_deg_per_m = (180.0 / std::numbers::pi) * sum_r / static_cast<double>(count);
  }
}

}  // namespace

Eigen::Matrix3d align_orientations(const hal::Trajectory& gt, const hal::Trajectory& est,
                                   const std::vector<PosePair>& pairs) {
  if (pairs.empty()) return Eigen::Matrix3d::Identity();
  Eigen::Matrix3d M = Eigen::Matrix3d::Zero();
  for (const PosePair& p : pairs) {
    M += gt.poses[p.gt].T_w_c.linear() * est.poses[p.est].T_w_c.linear().transpose();
  }
  return geometry::nearest_rotation(M);
}

EvalResult evaluate(const hal::Trajectory& gt, const hal::Trajectory& est,
                    const std::vector<PosePair>& pairs, Alignment alignment,
                    const RpeOptions& rpe) {
  EvalResult r;
  r.pairs = pairs.size();
  r.alignment = alignment;
  if (pairs.empty()) return r;
  std::vector<Eigen::Vector3d> src;
  std::vector<Eigen::Vector3d> dst;
  src.reserve(pairs.size());
  dst.reserve(pairs.size());
  for (const PosePair& p : pairs) {
    src.push_back(est.poses[p.est].T_w_c.translation());
    dst.push_back(gt.poses[p.gt].T_w_c.translation());
  }
  Sim3 s = align_positions(src, dst, alignment);
  if (alignment == Alignment::kRotation) s.R = align_orientations(gt, est, pairs);
  r.scale = s.scale;

  std::vector<double> err(pairs.size());
  double sq = 0.0;
  double sum = 0.0;
  for (std::size_t i = 0; i < pairs.size(); ++i) {
    err[i] = (dst[i] - s.apply(src[i])).norm();
    sq += err[i] * err[i];
    sum += err[i];
    r.ate_max_m = std::max(r.ate_max_m, err[i]);
  }
  const auto n = static_cast<double>(pairs.size());
  r.ate_rmse_m = std::sqrt(sq / n);
  r.ate_mean_m = sum / n;
  std::vector<double> sorted = err;
  std::sort(sorted.begin(), sorted.end());
  const std::size_t m = sorted.size();
  r.ate_median_m = (m % 2 == 1) ? sorted[m / 2] : 0.5 * (sorted[m / 2 - 1] + sorted[m / 2]);

  std::vector<SE3d> G;
  std::vector<SE3d> P;
  G.reserve(pairs.size());
  P.reserve(pairs.size());
  for (const PosePair& p : pairs) {
    G.push_back(gt.poses[p.gt].T_w_c);
    P.push_back(s.apply(est.poses[p.est].T_w_c));
  }
  compute_rpe(G, P, rpe, r);

  double sq_rot = 0.0;
  for (std::size_t i = 0; i < pairs.size(); ++i) {
    const double a = rotation_angle(G[i].linear().transpose() * P[i].linear());
    sq_rot += a * a;
    r.are_max_deg = std::max(r.are_max_deg, a);
  }
  constexpr double kDeg = 180.0 / std::numbers::pi;
  r.are_rmse_deg = kDeg * std::sqrt(sq_rot / n);
  r.are_max_deg *= kDeg;
  return r;
}

namespace {

std::string num(double v) {
  if (!std::isfinite(v)) return "null";
  char buf[64];
  std::snprintf(buf, sizeof(buf), "%.9g", v);
  return buf;
}

}  // namespace

std::string to_json(const EvalResult& r) {
  std::ostringstream o;
  const bool rpe = r.rpe_segments > 0;
  o << "{\"pairs\": " << r.pairs << ", \"align\": \"" << alignment_name(r.alignment)
    << "\", \"scale\": " << num(r.scale) << ", \"ate_rmse_m\": " << num(r.ate_rmse_m)
    << ", \"ate_mean_m\": " << num(r.ate_mean_m) << ", \"ate_median_m\": " << num(r.ate_median_m)
    << ", \"ate_max_m\": " << num(r.ate_max_m)
    << ", \"rpe_trans_pct\": " << (rpe ? num(r.rpe_trans_pct) : "null")
    << ", \"rpe_rot_deg_per_m\": " << (rpe ? num(r.rpe_rot_deg_per_m) : "null")
    << ", \"are_rmse_deg\": " << num(r.are_rmse_deg) << ", \"are_max_deg\": " << num(r.are_max_deg)
    << "}";
  return o.str();
}

std::string to_text(const EvalResult& r) {
  char buf[1024];
  std::snprintf(buf, sizeof(buf),
                "pairs:      %zu\n"
                "alignment:  %s (scale %.7f)\n"
                "ATE rmse:   %.7f m\n"
                "ATE mean:   %.7f m\n"
                "ATE median: %.7f m\n"
                "ATE max:    %.7f m\n"
                "ARE rmse:   %.4f deg (max %.4f)\n",
                r.pairs, alignment_name(r.alignment), r.scale, r.ate_rmse_m, r.ate_mean_m,
                r.ate_median_m, r.ate_max_m, r.are_rmse_deg, r.are_max_deg);
  std::string s = buf;
  if (r.rpe_segments > 0) {
    std::snprintf(buf, sizeof(buf), "RPE trans:  %.4f %% (%zu segments)\nRPE rot:    %.6f deg/m\n",
                  r.rpe_trans_pct, r.rpe_segments, r.rpe_rot_deg_per_m);
  } else {
    std::snprintf(buf, sizeof(buf), "RPE:        n/a (no segment of the requested delta)\n");
  }
  return s + buf;
}

}  // namespace mer::eval
