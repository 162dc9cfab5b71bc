#include "hal/replay/euroc_loader.h"

#include <filesystem>

#include "hal/replay/dataset_parsers.h"

namespace mer::hal {
namespace {
constexpr const char* kCamIndex = "cam0/data.csv";
constexpr const char* kCamImages = "cam0/data";
constexpr const char* kCamSensor = "cam0/sensor.yaml";
constexpr const char* kGroundTruth = "state_groundtruth_estimate0/data.csv";
}  // namespace

EurocLoader::EurocLoader(std::string dir, const CalibrationOptions& calib, std::int64_t max_dt_ns)
    : FolderLoader("euroc", std::move(dir), calib, false, 1.0), max_dt_ns_(max_dt_ns) {}

Status EurocLoader::open() {
  if (Status s = check_folder(); !s.is_ok()) return s;
  namespace fs = std::filesystem;
  std::error_code ec;
  // DIR/mav0/cam0 (the usual layout) or DIR/cam0 (DIR is mav0 itself).
  const fs::path mav0 =
      fs::is_directory(fs::path(dir_) / "mav0", ec) ? fs::path(dir_) / "mav0" : fs::path(dir_);

  const std::string index_path = (mav0 / kCamIndex).string();
  auto index_text = read_text_file(index_path);
  if (!index_text.is_ok()) return input_error(uri() + ": " + index_text.status().message());
  auto index = parse_euroc_csv(index_text.value(), index_path);
  if (!index.is_ok()) return index.status();

  const std::string sensor_path = (mav0 / kCamSensor).string();
  auto sensor_text = read_text_file(sensor_path);
  if (!sensor_text.is_ok()) return input_error(uri() + ": " + sensor_text.status().message());
  auto sensor = parse_euroc_sensor(sensor_text.value(), sensor_path);
  if (!sensor.is_ok()) return sensor.status();
  const EurocSensor& cam = sensor.value();
  T_b_c_ = cam.T_b_s;

  frames_.clear();
  frames_.reserve(index.value().size());
  for (const TimedFile& tf : index.value()) {
    FolderFrame f;
    f.t_ns = tf.t_ns;
    f.image = (mav0 / kCamImages / tf.file).string();
    f.listed_at = index_path + ":" + std::to_string(tf.line);
    frames_.push_back(std::move(f));
  }

  ground_truth_ = {};
  const std::string gt_path = (mav0 / kGroundTruth).string();
  if (fs::exists(gt_path, ec)) {
    auto text = read_text_file(gt_path);
    if (!text.is_ok()) return text.status();
    auto gt = parse_euroc_groundtruth(text.value(), gt_path);
    if (!gt.is_ok()) return gt.status();
    ground_truth_ = std::move(gt.value());
    for (StampedPose& p : ground_truth_.poses) p.T_w_c = p.T_w_c * T_b_c_;  // T_w_b * T_b_c
  }
  assign_interpolated_ground_truth(max_dt_ns_);

  if (Status s = probe_image_size(); !s.is_ok()) return s;
  if (intrinsics_.width != cam.width || intrinsics_.height != cam.height) {
    return input_error(sensor_path + ": resolution " + std::to_string(cam.width) + "x" +
                       std::to_string(cam.height) + " does not match the images (" +
                       std::to_string(intrinsics_.width) + "x" +
                       std::to_string(intrinsics_.height) + ")");
  }
  intrinsics_.fx = cam.fu;
  intrinsics_.fy = cam.fv;
  intrinsics_.cx = cam.cu;
  intrinsics_.cy = cam.cv;
  intrinsics_.dist = cam.dist;
  intrinsics_.focal_known = true;
  apply_calibration_override();
  return Status::ok();
}

}  // namespace mer::hal
