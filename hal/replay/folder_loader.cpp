#include "hal/replay/folder_loader.h"

#include <filesystem>
#include <sstream>

#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "platform/log_ring.h"

namespace mer::hal {
namespace {

constexpr double kNsPerS = 1e9;
constexpr double k16To8Bit = 1.0 / 257.0;  // 65535 -> 255

std::string size_str(int w, int h) {
  return std::to_string(w) + "x" + std::to_string(h);
}

// Reads an image as stored; empty Mat and `why` on failure (OpenCV may throw on some
// corrupt files; that is a failed read, not a crash).
cv::Mat read_image(const std::string& file, std::string& why) {
  std::error_code ec;
  if (!std::filesystem::is_regular_file(file, ec)) {
    why = "missing";
    return {};
  }
  cv::Mat img;
  try {
    img = cv::imread(file, cv::IMREAD_UNCHANGED);
  } catch (const cv::Exception& e) {
    why = std::string("unreadable (") + e.what() + ")";
    return {};
  }
  if (img.empty()) why = "unreadable or corrupt image";
  return img;
}

// Any 1/3/4-channel 8- or 16-bit image to 8-bit gray, written into `gray` in place
// (same size and type, so no reallocation of the pool buffer).
bool to_gray(const cv::Mat& img, cv::Mat& gray, std::string& why) {
  cv::Mat img8;
  if (img.depth() == CV_8U) {
    img8 = img;
  } else if (img.depth() == CV_16U) {
    img.convertTo(img8, CV_8U, k16To8Bit);
  } else {
    why = "unsupported pixel depth (expected 8 or 16 bit)";
    return false;
  }
  switch (img8.channels()) {
    case 1:
      img8.copyTo(gray);
      return true;
    case 3:
      cv::cvtColor(img8, gray, cv::COLOR_BGR2GRAY);
      return true;
    case 4:
      cv::cvtColor(img8, gray, cv::COLOR_BGRA2GRAY);
      return true;
    default:
      why = "unsupported number of channels (" + std::to_string(img8.channels()) + ")";
      return false;
  }
}

}  // namespace

FolderLoader::FolderLoader(std::string scheme, std::string dir, const CalibrationOptions& calib,
                           bool with_depth, double depth_scale)
    : scheme_(std::move(scheme)),
      dir_(std::move(dir)),
      calib_(calib),
      with_depth_(with_depth),
      depth_scale_(depth_scale) {}

std::string FolderLoader::path(const std::string& rel) const {
  return (std::filesystem::path(dir_) / rel).string();
}

Status FolderLoader::check_folder() const {
  std::error_code ec;
  if (!std::filesystem::is_directory(dir_, ec)) {
    return input_error(uri() + ": folder '" + dir_ + "' not found");
  }
  return Status::ok();
}

Status FolderLoader::probe_image_size() {
  std::string first_failure;
  const std::size_t n = std::min(frames_.size(), kMaxProbeImages);
  for (std::size_t i = 0; i < n; ++i) {
    std::string why;
    const cv::Mat img = read_image(frames_[i].image, why);
    if (!img.empty()) {
      intrinsics_.width = img.cols;
      intrinsics_.height = img.rows;
      return Status::ok();
    }
    if (first_failure.empty()) {
      first_failure = frames_[i].image + ": " + why + " (listed at " + frames_[i].listed_at + ")";
    }
  }
  return input_error(
      uri() + ": none of the first " + std::to_string(n) +
      " listed images can be read, so the image size is unknown; first: " + first_failure);
}

void FolderLoader::apply_calibration_override() {
  if (!calib_.is_set()) return;
  intrinsics_.fx = calib_.fx;
  intrinsics_.fy = calib_.fy > 0.0 ? calib_.fy : calib_.fx;
  intrinsics_.cx = calib_.cx;
  intrinsics_.cy = calib_.cy;
  intrinsics_.dist = {calib_.k1, calib_.k2, calib_.p1, calib_.p2};
  intrinsics_.focal_known = true;
}

void FolderLoader::assign_interpolated_ground_truth(std::int64_t max_dt_ns) {
  has_ground_truth_ = !ground_truth_.poses.empty();
  if (!has_ground_truth_) return;
  if (ground_truth_.duplicates_dropped > 0) {
    MER_LOG_WARN("%s: %zu ground-truth samples with a repeated timestamp dropped (first: line %d)",
                 ground_truth_.source.c_str(), ground_truth_.duplicates_dropped,
                 ground_truth_.first_duplicate_line);
  }
  for (FolderFrame& f : frames_) {
    const std::optional<SE3d> T = interpolate_pose(ground_truth_, f.t_ns, max_dt_ns);
    f.has_ground_truth = T.has_value();
    if (T) f.T_w_c_gt = *T;
  }
}

LoadStatus FolderLoader::load(std::size_t index, Frame& out, Status& status) {
  if (index >= frames_.size()) {
    status = Status(StatusCode::kEndOfStream, uri() + ": end of sequence");
    return LoadStatus::kEndOfStream;
  }
  const FolderFrame& f = frames_[index];
  const auto skip = [&](const std::string& file, const std::string& why) {
    status = input_error(file + ": " + why + " (frame " + std::to_string(index) + ", listed at " +
                         f.listed_at + ")");
    return LoadStatus::kSkip;
  };
  std::string why;
  const cv::Mat img = read_image(f.image, why);
  if (img.empty()) return skip(f.image, why);
  if (img.cols != intrinsics_.width || img.rows != intrinsics_.height) {
    return skip(f.image, "image is " + size_str(img.cols, img.rows) + ", the sequence is " +
                             size_str(intrinsics_.width, intrinsics_.height));
  }
  if (!to_gray(img, out.gray, why)) return skip(f.image, why);

  if (with_depth_) {
    if (f.depth.empty()) return skip(f.image, "no depth image associated with this frame");
    const cv::Mat d = read_image(f.depth, why);
    if (d.empty()) return skip(f.depth, why);
    if (d.type() != CV_16UC1) {
      return skip(f.depth, "depth image is not 16-bit single-channel");
    }
    if (d.cols != intrinsics_.width || d.rows != intrinsics_.height) {
      return skip(f.depth, "depth image is " + size_str(d.cols, d.rows) + ", the sequence is " +
                               size_str(intrinsics_.width, intrinsics_.height));
    }
    d.convertTo(out.depth, CV_32F, 1.0 / depth_scale_);
  }
  out.seq = index;
  out.t_ns = f.t_ns;
  out.has_ground_truth = f.has_ground_truth;
  out.T_w_c_gt = f.has_ground_truth ? f.T_w_c_gt : SE3d::Identity();
  status = Status::ok();
  return LoadStatus::kOk;
}

double FolderLoader::nominal_fps() const {
  if (frames_.size() < 2) return 0.0;
  const double span_s =
      (static_cast<double>(frames_.back().t_ns) - static_cast<double>(frames_.front().t_ns)) /
      kNsPerS;
  return span_s > 0.0 ? static_cast<double>(frames_.size() - 1) / span_s : 0.0;
}

std::string FolderLoader::describe() const {
  std::ostringstream os;
  os << uri() << " (" << size_str(intrinsics_.width, intrinsics_.height) << ", " << frames_.size()
     << " frames" << (with_depth_ ? ", depth" : "") << (has_ground_truth_ ? ", ground truth" : "")
     << ")";
  return os.str();
}

}  // namespace mer::hal
