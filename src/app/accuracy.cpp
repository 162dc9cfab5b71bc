#include "app/accuracy.h"

#include <algorithm>
#include <array>
#include <charconv>
#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <limits>
#include <numbers>
#include <sstream>
#include <string>

#include "app/summary.h"
#include "eval/trajectory_eval.h"
#include "hal/ground_truth.h"
#include "hal/replay/dataset_parsers.h"
#include "pipeline/output_stage.h"

namespace mer::app {
namespace {
constexpr std::int64_t kMaxDtNs = 1'000'000;       // estimate and truth share frame timestamps
constexpr std::size_t kMinPairs = 3;               // Umeyama needs three points
constexpr double kMaxQuaternionNormError = 1e-6;   // written with 9 decimals
constexpr double kUnanchoredPoseTolerance = 1e-6;  // both files print the same pose, 9 decimals

/// Loads `dir`/groundtruth.txt into `gt`; false with the reason in `note` when the source had
/// none or it cannot be read.
bool load_groundtruth(const std::string& dir, hal::Trajectory& gt, std::string& note) {
  const std::string gt_path = (std::filesystem::path(dir) / "groundtruth.txt").string();
  std::error_code ec;
  if (dir.empty() || std::filesystem::file_size(gt_path, ec) == 0 || ec) {
    note = "no ground truth from this source";
    return false;
  }
  auto r = hal::load_tum_trajectory(gt_path);
  if (!r.is_ok()) {
    note = r.status().message();
    return false;
  }
  gt = std::move(r.value());
  return true;
}
/// A frame frames.csv lists as tracked: its timestamp and segment.
struct TrackedFrame {
  std::int64_t t_ns = 0;
  int segment = 0;
};

/// The frames `dir`/frames.csv lists as tracked, in file order; false with the reason in
/// `note` when the file cannot be read.
bool tracked_frames(const std::string& dir, std::vector<TrackedFrame>& out, std::string& note) {
  const std::string path = (std::filesystem::path(dir) / "frames.csv").string();
  std::ifstream in(path);
  if (!in) {
    note = "cannot read '" + path + "'";
    return false;
  }
  constexpr std::size_t kTimeColumn = 1;
  constexpr std::size_t kStateColumn = 2;
  constexpr std::size_t kSegmentColumn = 15;
  std::string line;
  std::getline(in, line);  // header
  std::vector<std::string> cols;
  while (std::getline(in, line)) {
    cols.clear();
    std::istringstream ss(line);
    for (std::string c; std::getline(ss, c, ',');) cols.push_back(c);
    if (cols.size() <= kSegmentColumn ||
        cols[kStateColumn] != frontend::to_string(frontend::TrackState::kTracked)) {
      continue;
    }
    TrackedFrame f;
    const std::string& seg = cols[kSegmentColumn];
    const auto [end, ec] = std::from_chars(seg.data(), seg.data() + seg.size(), f.segment);
    if (ec != std::errc() || end != seg.data() + seg.size()) continue;
    if (!parse_seconds_ns(cols[kTimeColumn], f.t_ns)) continue;
    out.push_back(f);
  }
  return true;
}

/// Timestamps of the frames `dir`/frames.csv lists as tracked in `segment`, sorted; false
/// with the reason in `note` when the file cannot be read.
bool segment_frame_stamps(const std::string& dir, int segment, std::vector<std::int64_t>& t_ns,
                          std::string& note) {
  std::vector<TrackedFrame> frames;
  if (!tracked_frames(dir, frames, note)) return false;
  for (const TrackedFrame& f : frames) {
    if (f.segment == segment) t_ns.push_back(f.t_ns);
  }
  std::sort(t_ns.begin(), t_ns.end());
  return true;
}

/// Length of the ground-truth path between t_first and t_last, m.
double path_length(const hal::Trajectory& gt, std::int64_t t_first, std::int64_t t_last) {
  const auto& g = gt.poses;
  double length = 0.0;
  for (std::size_t i = 1; i < g.size(); ++i) {
    if (g[i - 1].t_ns < t_first - kMaxDtNs || g[i].t_ns > t_last + kMaxDtNs) continue;
    length += (g[i].T_w_c.translation() - g[i - 1].T_w_c.translation()).norm();
  }
  return length;
}

/// The first tracked frame's timestamp in a segment of `stats` that was not discarded (one
/// read of frames.csv); `fallback` when there is none or the file cannot be read.
std::int64_t first_kept_stamp(const std::string& dir, const pipeline::PipelineStats& stats,
                              std::int64_t fallback) {
  std::vector<TrackedFrame> frames;
  std::string ignored;
  if (!tracked_frames(dir, frames, ignored)) return fallback;
  std::int64_t first = fallback;
  for (const TrackedFrame& f : frames) {
    const bool kept = std::any_of(
        stats.segments.begin(), stats.segments.end(),
        [&](const pipeline::SegmentStats& g) { return g.id == f.segment && !g.discarded; });
    if (kept) first = std::min(first, f.t_ns);
  }
  return first;
}

}  // namespace

AccuracyReport evaluate_run(const std::string& dir, SensorMode sensor_mode,
                            const pipeline::PipelineStats& stats, const std::string& trajectory,
                            int only_segment) {
  AccuracyReport a;
  const std::string est_path = (std::filesystem::path(dir) / trajectory).string();
  hal::Trajectory gt;
  if (!load_groundtruth(dir, gt, a.note)) return a;
  std::error_code ec;
  a.gt_frames = gt.poses.size();
  const std::uint64_t tracked = stats.frames_processed - stats.frames_lost;
  if (std::filesystem::file_size(est_path, ec) == 0 || ec) {
    a.note = "no tracked frame";
    return a;
  }
  auto est = hal::load_tum_trajectory(est_path);
  if (!est.is_ok()) {
    a.note = est.status().message();
    return a;
  }
  if (only_segment >= 0) {
    std::vector<std::int64_t> keep;
    if (!segment_frame_stamps(dir, only_segment, keep, a.note)) return a;
    std::erase_if(est.value().poses, [&](const StampedPose& p) {
      return !std::binary_search(keep.begin(), keep.end(), p.t_ns);
    });
    if (est.value().poses.empty()) {
      a.note = "no tracked frame in segment " + std::to_string(only_segment);
      return a;
    }
  }
  const auto pairs = eval::associate(gt, est.value(), kMaxDtNs);
  if (pairs.size() < kMinPairs) {
    a.note = "fewer than 3 tracked frames";
    return a;
  }
  const eval::Alignment al =
      sensor_mode == SensorMode::kRgbd ? eval::Alignment::kSe3 : eval::Alignment::kSim3;
  const eval::EvalResult r = eval::evaluate(gt, est.value(), pairs, al);
  a.available = true;
  a.alignment = eval::alignment_name(al);
  a.pairs = r.pairs;
  a.scale = r.scale;
  a.ate_rmse_m = r.ate_rmse_m;
  a.ate_mean_m = r.ate_mean_m;
  a.ate_median_m = r.ate_median_m;
  a.ate_max_m = r.ate_max_m;
  const auto& g = gt.poses;
  const std::int64_t t_first = est.value().poses.front().t_ns;
  const std::int64_t t_last = est.value().poses.back().t_ns;
  a.path_length_m = path_length(gt, t_first, t_last);
  a.ate_pct_of_path = a.path_length_m > 0.0 ? 100.0 * a.ate_rmse_m / a.path_length_m : 0.0;
  // The first seconds after the start, aligned on their own.
  const auto t_start_end = t_first + static_cast<std::int64_t>(kStartWindowS * 1e9);
  std::erase_if(est.value().poses, [&](const StampedPose& p) { return p.t_ns > t_start_end; });
  const auto start_pairs = eval::associate(gt, est.value(), kMaxDtNs);
  if (start_pairs.size() >= kMinPairs) {
    const eval::EvalResult h = eval::evaluate(gt, est.value(), start_pairs, al);
    a.start_pairs = h.pairs;
    a.start_ate_rmse_m = h.ate_rmse_m;
    a.start_path_length_m = path_length(gt, t_first, est.value().poses.back().t_ns);
    a.start_ate_pct_of_path =
        a.start_path_length_m > 0.0 ? 100.0 * a.start_ate_rmse_m / a.start_path_length_m : 0.0;
  }
  // Tracked fraction from the initialization on: frames at or after the first tracked one
  // of the run, in any segment (`tracked` counts them all; trajectory.txt may hold a
  // segment that started later).
  // (Not a discarded segment's: its frames count as lost, the start came later.)
  const std::int64_t t_init = only_segment >= 0 ? t_first : first_kept_stamp(dir, stats, t_first);
  std::uint64_t since_init = 0;
  for (const auto& p : g) since_init += p.t_ns >= t_init - kMaxDtNs ? 1 : 0;
  if (only_segment < 0 && stats.frames_processed > 0 && since_init > 0) {
    a.tracked_after_init_pct =
        100.0 * static_cast<double>(tracked) / static_cast<double>(since_init);
  }
  return a;
}

namespace {

/// The ground-truth pose at t_ns (nearest within kMaxDtNs); false when there is none.
bool gt_pose_at(const hal::Trajectory& gt, std::int64_t t_ns, SE3d& T_w_c) {
  const auto& p = gt.poses;
  auto it = std::lower_bound(p.begin(), p.end(), t_ns,
                             [](const StampedPose& a, std::int64_t t) { return a.t_ns < t; });
  std::int64_t best = kMaxDtNs + 1;
  for (auto c : {it, it == p.begin() ? it : std::prev(it)}) {
    if (c == p.end()) continue;
    const std::int64_t dt = std::llabs(c->t_ns - t_ns);
    if (dt < best) {
      best = dt;
      T_w_c = c->T_w_c;
    }
  }
  return best <= kMaxDtNs;
}

/// Scores the estimated relative pose (rotation R_est, translation t_est in map units) of
/// view b in view a against the truth.
void score_relative(const hal::Trajectory& gt, std::int64_t t_a, std::int64_t t_b,
                    const Eigen::Matrix3d& R_est, const Eigen::Vector3d& t_est, double scale,
                    EventAudit& e) {
  SE3d T_w_a;
  SE3d T_w_b;
  if (!gt_pose_at(gt, t_a, T_w_a) || !gt_pose_at(gt, t_b, T_w_b)) return;
  const SE3d T_a_b = T_w_a.inverse() * T_w_b;
  e.scored = true;
  e.gt_distance_m = T_a_b.translation().norm();
  e.error_m = (scale * t_est - T_a_b.translation()).norm();
  const Eigen::AngleAxisd d(R_est.transpose() * T_a_b.rotation());
  e.error_deg = d.angle() * 180.0 / std::numbers::pi;
}

double ns_to_s(std::int64_t t_ns) {
  return static_cast<double>(t_ns) * 1e-9;
}

}  // namespace

EventAuditReport audit_events(const std::string& dir, const pipeline::PipelineStats& stats,
                              const std::vector<AccuracyReport>& segments) {
  EventAuditReport rep;
  hal::Trajectory gt;
  if (!load_groundtruth(dir, gt, rep.note)) return rep;
  rep.available = true;
  auto scale_of = [&](std::uint16_t segment, double& scale) {
    for (std::size_t i = 0; i < stats.segments.size() && i < segments.size(); ++i) {
      if (stats.segments[i].id == segment && segments[i].available) {
        scale = segments[i].scale;
        return true;
      }
    }
    return false;
  };
  for (const pipeline::RelocalizationEvent& r : stats.relocalization.events) {
    EventAudit e;
    e.kind = "relocalization";
    e.confirmed = r.confirmed;
    e.found_ratio = r.found_ratio;
    e.seq = r.seq;
    e.t_s = ns_to_s(r.t_ns);
    e.other_t_s = ns_to_s(r.keyframe_t_ns);
    e.segment = r.segment;
    if (double scale = 1.0; scale_of(r.segment, scale)) {
      score_relative(gt, r.keyframe_t_ns, r.t_ns, r.T_kf_c.rotation(), r.T_kf_c.translation(),
                     scale, e);
    }
    if (e.scored) {
      ++rep.relocalizations;
      e.wrong = e.error_m > kWrongRelocalizationM;
      rep.relocalizations_wrong += e.wrong ? 1 : 0;
    }
    rep.events.push_back(e);
  }
  for (const mer::loop::LoopClosureEvent& l : stats.loop.closures) {
    EventAudit e;
    e.kind = "loop";
    e.found_new = l.found_new;
    e.found_old = l.found_old;
    e.found_usual = l.found_usual;
    e.rival_inliers = l.rival_inliers;
    e.inliers = l.inliers;
    e.drift = l.drift;
    e.connected = l.connected;
    e.seq = l.seq;
    e.t_s = ns_to_s(l.t_ns);
    e.other_t_s = ns_to_s(l.loop_t_ns);
    e.segment = l.segment;
    // sim_old_new maps the new camera's frame into the old one's: its rotation and translation
    // are the new camera's relative pose, in the old keyframe's map units.
    if (double scale = 1.0; scale_of(l.segment, scale)) {
      score_relative(gt, l.loop_t_ns, l.t_ns, l.sim_old_new.R, l.sim_old_new.t, scale, e);
    }
    if (e.scored) {
      ++rep.loops;
      e.wrong = e.error_m > kWrongLoopM;
      rep.loops_wrong += e.wrong ? 1 : 0;
    }
    rep.events.push_back(e);
  }
  return rep;
}

Status read_frame_anchors(const std::string& path, std::vector<pipeline::AnchoredFrame>& frames,
                          std::span<const double> segment_scale, std::uint16_t main_segment) {
  std::ifstream in(path);
  if (!in) return input_error("cannot read '" + path + "'");
  // t kf_t segment tx ty tz qx qy qz qw (segment 0 when it is left out: files of earlier
  // versions).
  constexpr std::size_t kFields = 10;
  std::string line;
  std::size_t k = 0;
  int line_no = 0;
  while (std::getline(in, line)) {
    ++line_no;
    if (line.empty() || line[0] == '#') continue;
    auto bad = [&](const std::string& what) {
      return input_error(path + ":" + std::to_string(line_no) + ": " + what);
    };
    std::istringstream ls(line);
    std::vector<std::string> tok;
    for (std::string t; ls >> t;) tok.push_back(t);
    if (tok.size() == kFields - 1) tok.insert(tok.begin() + 2, "0");
    if (tok.size() != kFields) {
      return bad("expected " + std::to_string(kFields) + " fields, got " +
                 std::to_string(tok.size()));
    }
    std::int64_t t_ns = 0;
    if (!hal::parse_seconds_ns(tok[0], t_ns)) return bad("bad timestamp '" + tok[0] + "'");
    char* seg_end = nullptr;
    const unsigned long segment = std::strtoul(tok[2].c_str(), &seg_end, 10);
    if (seg_end != tok[2].c_str() + tok[2].size() || tok[2][0] == '-' ||
        segment > std::numeric_limits<std::uint16_t>::max()) {
      return bad("bad segment '" + tok[2] + "'");
    }
    // A frame of a segment whose frames are not in trajectory.txt (it never joined the
    // main one) is not re-anchored.
    double scale = 1.0;
    if (!segment_scale.empty()) {
      scale = segment < segment_scale.size() ? segment_scale[segment] : 0.0;
      if (!(scale > 0.0)) continue;
    }
    if (k >= frames.size()) return bad("more frames than trajectory.txt has");
    pipeline::AnchoredFrame& f = frames[k++];
    if (t_ns != f.t_ns) return bad("timestamp " + tok[0] + " is not trajectory.txt's next");
    f.has_anchor = tok[1] != "-";
    if (f.has_anchor && !hal::parse_seconds_ns(tok[1], f.anchor_t_ns)) {
      return bad("bad keyframe timestamp '" + tok[1] + "'");
    }
    std::array<double, 7> v{};
    for (std::size_t i = 0; i < v.size(); ++i) {
      const std::string& s = tok[i + 3];
      char* end = nullptr;
      v[i] = std::strtod(s.c_str(), &end);
      if (end != s.c_str() + s.size() || !std::isfinite(v[i])) {
        return bad("bad number '" + s + "'");
      }
    }
    const Eigen::Quaterniond q(v[6], v[3], v[4], v[5]);
    if (std::abs(q.norm() - 1.0) > kMaxQuaternionNormError) return bad("quaternion not unit");
    const SE3d T = make_se3(q.normalized(), Eigen::Vector3d(v[0], v[1], v[2]));
    if (f.has_anchor) {
      // In the units of the segment it was tracked in: into trajectory.txt's.
      f.T_kf_c = T;
      f.T_kf_c.translation() *= scale;
    } else if (segment == main_segment && !T.isApprox(f.T_w_c, kUnanchoredPoseTolerance)) {
      // (A joined segment's frame was moved into trajectory.txt's frame by its merge.)
      return bad("frame without keyframe does not repeat its trajectory.txt pose");
    }
  }
  if (k != frames.size()) {
    return input_error("'" + path + "': " + std::to_string(k) + " frames, trajectory.txt has " +
                       std::to_string(frames.size()));
  }
  return Status::ok();
}

Status write_final_trajectory(const std::string& dir,
                              std::span<const pipeline::FinalKeyframePose> keyframes,
                              pipeline::FinalTrajectoryStats& stats,
                              std::span<const double> segment_scale, std::uint16_t main_segment) {
  const std::filesystem::path d(dir);
  stats = pipeline::FinalTrajectoryStats{};
  std::error_code ec;
  if (std::filesystem::file_size(d / "trajectory.txt", ec) == 0 && !ec) {
    return write_file_atomic((d / "trajectory_final.txt").string(), "");  // nothing tracked
  }
  auto est = hal::load_tum_trajectory((d / "trajectory.txt").string());
  if (!est.is_ok()) return est.status();
  if (est.value().duplicates_dropped > 0) {
    return input_error("'" + (d / "trajectory.txt").string() + "': repeated timestamps");
  }
  std::vector<pipeline::AnchoredFrame> frames(est.value().poses.size());
  for (std::size_t i = 0; i < frames.size(); ++i) {
    frames[i].t_ns = est.value().poses[i].t_ns;
    frames[i].T_w_c = est.value().poses[i].T_w_c;
  }
  if (Status s = read_frame_anchors((d / "frame_anchors.txt").string(), frames, segment_scale,
                                    main_segment);
      !s.is_ok()) {
    return s;
  }
  const std::vector<StampedPose> poses = pipeline::reanchor_frames(frames, keyframes, stats);
  std::string text;
  char line[256];
  for (const StampedPose& p : poses) {
    const int n = pipeline::format_tum_line(line, sizeof line, p.t_ns, p.T_w_c);
    if (n > 0) text.append(line, static_cast<std::size_t>(n));
  }
  return write_file_atomic((d / "trajectory_final.txt").string(), text);
}

Status run_gt_check(const std::string& dir, SensorMode sensor_mode, int max_iterations,
                    pipeline::Pipeline& pipe, eval::GroundTruthCheckReport& report,
                    AccuracyReport& converged, AccuracyReport& shuffled,
                    AccuracyReport& shuffled_detected) {
  const std::filesystem::path d(dir);
  constexpr std::array<const char*, 3> kFiles{"keyframes_gt_converged.txt",
                                              "keyframes_gt_shuffled.txt",
                                              "keyframes_gt_shuffled_detected.txt"};
  std::error_code ec;
  for (const char* name : kFiles) std::filesystem::remove(d / name, ec);  // no stale result
  const std::string gt_path = (d / "groundtruth.txt").string();
  if (dir.empty() || std::filesystem::file_size(gt_path, ec) == 0 || ec) {
    report.note = "no ground truth from this source";
    return Status::ok();
  }
  auto gt = hal::load_tum_trajectory(gt_path);
  if (!gt.is_ok()) {
    report.note = gt.status().message();
    return Status::ok();
  }
  constexpr std::uint64_t kShuffleSeed = 1;
  // A metric map (RGB-D) is aligned without scale, as its ATE is.
  const bool with_scale = sensor_mode != SensorMode::kRgbd;
  const pipeline::Pipeline::FinishedMap m = pipe.finished_map();
  report = eval::check_against_groundtruth(m.map, m.ba, m.K, gt.value().poses, kMaxDtNs, with_scale,
                                           max_iterations, kShuffleSeed);
  if (!report.ran) return Status::ok();
  const std::array<const std::vector<StampedPose>*, 3> poses{&report.converged, &report.shuffled,
                                                             &report.shuffled_detected};
  const std::array<AccuracyReport*, 3> scores{&converged, &shuffled, &shuffled_detected};
  converged.note = shuffled.note = shuffled_detected.note = "not written";
  for (std::size_t i = 0; i < kFiles.size(); ++i) {
    if (poses[i]->empty()) {  // step 5 did not run
      scores[i]->note = "not run: no anchored keypoints, or only anchored ones";
      continue;
    }
    hal::Trajectory t;
    t.poses = *poses[i];
    if (Status s = hal::save_tum_trajectory((d / kFiles[i]).string(), t); !s.is_ok()) {
      scores[i]->note = "not written: " + s.message();
      return s;
    }
    *scores[i] = evaluate_run(dir, sensor_mode, pipe.stats(), kFiles[i]);
  }
  return Status::ok();
}

}  // namespace mer::app
