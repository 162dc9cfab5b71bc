#include "app/accuracy.h"

#include <filesystem>

#include "hal/ground_truth.h"
#include "tools/eval/trajectory_eval.h"

namespace mer::app {
namespace {
constexpr std::int64_t kMaxDtNs = 1'000'000;  // estimate and truth share frame timestamps
constexpr std::size_t kMinPairs = 3;          // Umeyama needs three points
}  // namespace

AccuracyReport evaluate_run(const std::string& dir, const std::string& sensor_mode,
                            const pipeline::PipelineStats& stats) {
  AccuracyReport a;
  const std::filesystem::path d(dir);
  const std::string gt_path = (d / "groundtruth.txt").string();
  const std::string est_path = (d / "trajectory.txt").string();
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

}  // namespace mer::app
