#include "app/accuracy.h"

#include <algorithm>
#include <filesystem>
#include <string>

#include "app/summary.h"
#include "hal/ground_truth.h"
#include "pipeline/output_stage.h"
#include "tools/eval/trajectory_eval.h"

namespace mer::app {
namespace {
constexpr std::int64_t kMaxDtNs = 1'000'000;  // estimate and truth share frame timestamps
constexpr std::size_t kMinPairs = 3;          // Umeyama needs three points
}  // namespace

AccuracyReport evaluate_run(const std::string& dir, const std::string& sensor_mode,
                            const pipeline::PipelineStats& stats, const std::string& trajectory) {
  AccuracyReport a;
  const std::filesystem::path d(dir);
  const std::string gt_path = (d / "groundtruth.txt").string();
  const std::string est_path = (d / trajectory).string();
  std::error_code ec;
  if (dir.empty() || std::filesystem::file_size(gt_path, ec) == 0 || ec) {
    a.note = "no ground truth from this source";
    return a;
  }
  auto gt = hal::load_tum_trajectory(gt_path);
  if (!gt.is_ok()) {
    a.note = gt.status().message();
    return a;
  }
  a.gt_frames = gt.value().poses.size();
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
  const auto pairs = eval::associate(gt.value(), est.value(), kMaxDtNs);
  if (pairs.size() < kMinPairs) {
    a.note = "fewer than 3 tracked frames";
    return a;
  }
  const eval::Alignment al = sensor_mode == "rgbd" ? eval::Alignment::kSe3 : eval::Alignment::kSim3;
  const eval::EvalResult r = eval::evaluate(gt.value(), est.value(), pairs, al);
  a.available = true;
  a.alignment = eval::alignment_name(al);
  a.pairs = r.pairs;
  a.scale = r.scale;
  a.ate_rmse_m = r.ate_rmse_m;
  a.ate_mean_m = r.ate_mean_m;
  a.ate_median_m = r.ate_median_m;
  a.ate_max_m = r.ate_max_m;
  // Path length of the ground truth between the first and last associated frame.
  const auto& g = gt.value().poses;
  const std::int64_t t_first = est.value().poses.front().t_ns;
  const std::int64_t t_last = est.value().poses.back().t_ns;
  for (std::size_t i = 1; i < g.size(); ++i) {
    if (g[i - 1].t_ns < t_first - kMaxDtNs || g[i].t_ns > t_last + kMaxDtNs) continue;
    a.path_length_m += (g[i].T_w_c.translation() - g[i - 1].T_w_c.translation()).norm();
  }
  a.ate_pct_of_path = a.path_length_m > 0.0 ? 100.0 * a.ate_rmse_m / a.path_length_m : 0.0;
  // Tracked fraction from the initialization on: frames at or after the first tracked one.
  std::uint64_t since_init = 0;
  for (const auto& p : g) since_init += p.t_ns >= t_first - kMaxDtNs ? 1 : 0;
  if (stats.frames_processed > 0 && since_init > 0) {
    a.tracked_after_init_pct =
        100.0 * static_cast<double>(tracked) / static_cast<double>(since_init);
  }
  return a;
}

Status write_final_ba_trajectory(const std::string& dir,
                                 const std::vector<pipeline::KeyframeCorrection>& corrections) {
  const std::filesystem::path d(dir);
  if (corrections.empty()) return invalid_argument("final BA: the map has no keyframe");
  auto est = hal::load_tum_trajectory((d / "trajectory.txt").string());
  if (!est.is_ok()) return est.status();
  std::string text;
  char line[256];
  for (const StampedPose& p : est.value().poses) {
    // Latest keyframe at or before the frame (keyframes are in time order).
    auto it = std::upper_bound(
        corrections.begin(), corrections.end(), p.t_ns,
        [](std::int64_t t, const pipeline::KeyframeCorrection& c) { return t < c.t_ns; });
    const pipeline::KeyframeCorrection& c = it == corrections.begin() ? *it : *(it - 1);
    const SE3d T = c.T_w_c_after * c.T_w_c_before.inverse() * p.T_w_c;
    const int n = pipeline::format_tum_line(line, sizeof line, p.t_ns, T);
    if (n > 0) text.append(line, static_cast<std::size_t>(n));
  }
  return write_file_atomic((d / "trajectory_final_ba.txt").string(), text);
}

}  // namespace mer::app
