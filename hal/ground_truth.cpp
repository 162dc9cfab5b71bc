#include "hal/ground_truth.h"

#include <algorithm>
#include <cinttypes>
#include <cmath>
#include <cstdio>
#include <filesystem>

#include "hal/replay/dataset_parsers.h"

namespace mer::hal {
namespace {
constexpr std::int64_t kNsPerS = 1'000'000'000;
}  // namespace

Result<Trajectory> load_tum_trajectory(const std::string& path) {
  auto text = read_text_file(path);
  if (!text.is_ok()) return text.status();
  return parse_tum_trajectory(text.value(), path);
}

Result<Trajectory> load_kitti_trajectory(const std::string& path, const std::string& times_path) {
  auto text = read_text_file(path);
  if (!text.is_ok()) return text.status();
  auto poses = parse_kitti_poses(text.value(), path);
  if (!poses.is_ok()) return poses.status();
  std::vector<std::int64_t> t_ns(poses.value().size());
  if (times_path.empty()) {
    for (std::size_t i = 0; i < t_ns.size(); ++i) t_ns[i] = static_cast<std::int64_t>(i) * kNsPerS;
  } else {
    auto ttext = read_text_file(times_path);
    if (!ttext.is_ok()) return ttext.status();
    auto times = parse_kitti_times(ttext.value(), times_path);
    if (!times.is_ok()) return times.status();
    if (times.value().size() < t_ns.size()) {
      return input_error(path + ": " + std::to_string(t_ns.size()) + " poses but only " +
                         std::to_string(times.value().size()) + " times in " + times_path);
    }
    for (std::size_t i = 0; i < t_ns.size(); ++i) {
      // parse_kitti_times() checked the range, so the conversion cannot overflow.
      t_ns[i] = std::llround(times.value()[i] * static_cast<double>(kNsPerS));
    }
  }
  Trajectory traj;
  traj.source = path;
  traj.poses.reserve(t_ns.size());
  for (std::size_t i = 0; i < t_ns.size(); ++i) traj.poses.push_back({t_ns[i], poses.value()[i]});
  return traj;
}

Status save_tum_trajectory(const std::string& path, const Trajectory& traj) {
  const std::string tmp = path + ".tmp";
  std::FILE* f = std::fopen(tmp.c_str(), "w");
  if (f == nullptr) return input_error(path + ": cannot open for writing");
  bool ok = std::fprintf(f, "# timestamp tx ty tz qx qy qz qw\n") > 0;
  for (const StampedPose& p : traj.poses) {
    const Eigen::Quaterniond q(p.T_w_c.linear());
    const Eigen::Vector3d& t = p.T_w_c.translation();
    const std::int64_t whole = p.t_ns / kNsPerS;
    std::int64_t frac = p.t_ns % kNsPerS;
    const char* sign = (p.t_ns < 0) ? "-" : "";
    frac = frac < 0 ? -frac : frac;
    ok = ok && std::fprintf(f, "%s%" PRId64 ".%09" PRId64 " %.9f %.9f %.9f %.9f %.9f %.9f %.9f\n",
                            sign, whole < 0 ? -whole : whole, frac, t.x(), t.y(), t.z(), q.x(),
                            q.y(), q.z(), q.w()) > 0;
  }
  ok = (std::fclose(f) == 0) && ok;
  std::error_code ec;
  if (ok) std::filesystem::rename(tmp, path, ec);
  if (!ok || ec) {
    std::filesystem::remove(tmp, ec);
    return input_error(path + ": write failed");
  }
  return Status::ok();
}

std::optional<SE3d> interpolate_pose(const Trajectory& traj, std::int64_t t_ns,
                                     std::int64_t max_dt_ns) {
  const auto& p = traj.poses;
  // First sample with t >= t_ns.
  const auto it = std::lower_bound(p.begin(), p.end(), t_ns,
                                   [](const StampedPose& s, std::int64_t t) { return s.t_ns < t; });
  if (it != p.end() && it->t_ns == t_ns) return it->T_w_c;
  if (it == p.end() || it == p.begin()) return std::nullopt;
  const StampedPose& a = *(it - 1);
  const StampedPose& b = *it;
  // Differences of ordered int64 times, computed unsigned: no overflow for any input.
  const auto gap = [](std::int64_t lo, std::int64_t hi) {
    return static_cast<std::uint64_t>(hi) - static_cast<std::uint64_t>(lo);
  };
  if (max_dt_ns < 0) return std::nullopt;
  const auto max_dt = static_cast<std::uint64_t>(max_dt_ns);
  if (gap(a.t_ns, t_ns) > max_dt || gap(t_ns, b.t_ns) > max_dt) return std::nullopt;
  const double w =
      static_cast<double>(gap(a.t_ns, t_ns)) / static_cast<double>(gap(a.t_ns, b.t_ns));
  const Eigen::Quaterniond qa(a.T_w_c.linear());
  const Eigen::Quaterniond qb(b.T_w_c.linear());
  return make_se3(qa.slerp(w, qb), (1.0 - w) * a.T_w_c.translation() + w * b.T_w_c.translation());
}

}  // namespace mer::hal
