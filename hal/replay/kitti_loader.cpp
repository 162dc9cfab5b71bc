#include "hal/replay/kitti_loader.h"

#include <array>
#include <cmath>
#include <cstdio>
#include <filesystem>

#include "hal/replay/dataset_parsers.h"

namespace mer::hal {
namespace {
constexpr const char* kCalib = "calib.txt";
constexpr const char* kTimes = "times.txt";
constexpr const char* kPoses = "poses.txt";
constexpr const char* kImageFormat = "image_0/%06zu.png";
constexpr std::size_t kImageNameSize = 48;  // "image_0/" + up to 20 digits + ".png"
constexpr double kNsPerS = 1e9;
}  // namespace

KittiLoader::KittiLoader(std::string dir, const CalibrationOptions& calib)
    : FolderLoader("kitti", std::move(dir), calib, false, 1.0) {}

Status KittiLoader::open() {
  if (Status s = check_folder(); !s.is_ok()) return s;
  const std::string calib_path = path(kCalib);
  auto calib_text = read_text_file(calib_path);
  if (!calib_text.is_ok()) return input_error(uri() + ": " + calib_text.status().message());
  auto calib = parse_kitti_calib(calib_text.value(), calib_path);
  if (!calib.is_ok()) return calib.status();

  const std::string times_path = path(kTimes);
  auto times_text = read_text_file(times_path);
  if (!times_text.is_ok()) return input_error(uri() + ": " + times_text.status().message());
  auto times = parse_kitti_times(times_text.value(), times_path);
  if (!times.is_ok()) return times.status();

  frames_.clear();
  frames_.reserve(times.value().size());
  for (std::size_t i = 0; i < times.value().size(); ++i) {
    std::array<char, kImageNameSize> name{};
    std::snprintf(name.data(), name.size(), kImageFormat, i);
    FolderFrame f;
    // parse_kitti_times() checked the range: the conversion cannot overflow.
    f.t_ns = std::llround(times.value()[i] * kNsPerS);
    f.image = path(name.data());
    f.listed_at = times_path + ":" + std::to_string(i + 1);
    frames_.push_back(std::move(f));
  }

  ground_truth_ = {};
  has_ground_truth_ = false;
  const std::string poses_path = path(kPoses);
  std::error_code ec;
  if (std::filesystem::exists(poses_path, ec)) {
    auto text = read_text_file(poses_path);
    if (!text.is_ok()) return text.status();
    auto poses = parse_kitti_poses(text.value(), poses_path);
    if (!poses.is_ok()) return poses.status();
    if (poses.value().size() > frames_.size()) {
      return input_error(poses_path + ": " + std::to_string(poses.value().size()) + " poses for " +
                         std::to_string(frames_.size()) + " frames in " + times_path + " (line " +
                         std::to_string(frames_.size() + 1) + " has no frame)");
    }
    ground_truth_.source = poses_path;
    for (std::size_t i = 0; i < poses.value().size(); ++i) {
      frames_[i].has_ground_truth = true;
      frames_[i].T_w_c_gt = poses.value()[i];
      ground_truth_.poses.push_back({frames_[i].t_ns, poses.value()[i]});
    }
    has_ground_truth_ = true;
  }

  if (Status s = probe_image_size(); !s.is_ok()) return s;
  const KittiCalib& k = calib.value();
  intrinsics_.fx = k.fx;
  intrinsics_.fy = k.fy;
  intrinsics_.cx = k.cx;
  intrinsics_.cy = k.cy;
  intrinsics_.dist = {};
  intrinsics_.focal_known = true;
  apply_calibration_override();
  return Status::ok();
}

}  // namespace mer::hal
