#include "hal/replay/tum_loader.h"

#include <algorithm>
#include <filesystem>

#include "hal/replay/dataset_parsers.h"

namespace mer::hal {
namespace {
constexpr const char* kRgbList = "rgb.txt";
constexpr const char* kDepthList = "depth.txt";
constexpr const char* kGroundTruth = "groundtruth.txt";
}  // namespace

TumLoader::TumLoader(std::string dir, const CalibrationOptions& calib, bool rgbd,
                     double depth_scale, std::int64_t max_dt_ns)
    : FolderLoader("tum", std::move(dir), calib, rgbd, depth_scale), max_dt_ns_(max_dt_ns) {}

Status TumLoader::open() {
  if (Status s = check_folder(); !s.is_ok()) return s;
  if (!calib_.is_set()) {
    return invalid_argument(uri() +
                            ": TUM folders carry no intrinsics; give them with --intrinsics "
                            "fx,fy,cx,cy[,k1,k2,p1,p2] or in the config's camera.calibration");
  }
  const std::string rgb_path = path(kRgbList);
  auto rgb_text = read_text_file(rgb_path);
  if (!rgb_text.is_ok()) return input_error(uri() + ": " + rgb_text.status().message());
  auto rgb = parse_tum_list(rgb_text.value(), rgb_path);
  if (!rgb.is_ok()) return rgb.status();

  std::vector<TimedFile> depth;
  const std::string depth_path = path(kDepthList);
  if (with_depth_) {
    auto depth_text = read_text_file(depth_path);
    if (!depth_text.is_ok()) {
      return input_error(uri() + ": RGB-D mode needs " + kDepthList + ": " +
                         depth_text.status().message());
    }
    auto d = parse_tum_list(depth_text.value(), depth_path);
    if (!d.is_ok()) return d.status();
    depth = std::move(d.value());
  }

  frames_.clear();
  frames_.reserve(rgb.value().size());
  for (const TimedFile& tf : rgb.value()) {
    FolderFrame f;
    f.t_ns = tf.t_ns;
    f.image = path(tf.file);
    f.listed_at = rgb_path + ":" + std::to_string(tf.line);
    if (with_depth_) {
      // Nearest depth timestamp (the list is strictly increasing).
      const auto it =
          std::lower_bound(depth.begin(), depth.end(), tf.t_ns,
                           [](const TimedFile& d, std::int64_t t) { return d.t_ns < t; });
      const TimedFile* best = nullptr;
      if (it != depth.end()) best = &*it;
      if (it != depth.begin() &&
          (best == nullptr || static_cast<double>(tf.t_ns) - static_cast<double>((it - 1)->t_ns) <=
                                  static_cast<double>(best->t_ns) - static_cast<double>(tf.t_ns))) {
        best = &*(it - 1);
      }
      // |dt| computed unsigned: no overflow whatever the timestamps.
      const auto abs_dt = [](std::int64_t a, std::int64_t b) {
        return a < b ? static_cast<std::uint64_t>(b) - static_cast<std::uint64_t>(a)
                     : static_cast<std::uint64_t>(a) - static_cast<std::uint64_t>(b);
      };
      if (best != nullptr && max_dt_ns_ >= 0 &&
          abs_dt(best->t_ns, tf.t_ns) <= static_cast<std::uint64_t>(max_dt_ns_)) {
        f.depth = path(best->file);
      }
    }
    frames_.push_back(std::move(f));
  }

  ground_truth_ = {};
  const std::string gt_path = path(kGroundTruth);
  std::error_code ec;
  if (std::filesystem::exists(gt_path, ec)) {
    auto text = read_text_file(gt_path);
    if (!text.is_ok()) return text.status();
    auto gt = parse_tum_trajectory(text.value(), gt_path);
    if (!gt.is_ok()) return gt.status();
    ground_truth_ = std::move(gt.value());
  }
  assign_interpolated_ground_truth(max_dt_ns_);

  if (Status s = probe_image_size(); !s.is_ok()) return s;
  apply_calibration_override();
  return Status::ok();
}

}  // namespace mer::hal
