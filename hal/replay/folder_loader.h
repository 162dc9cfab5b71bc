#pragma once
/// @file folder_loader.h
/// FolderLoader: the part the dataset-folder loaders (TUM, EuRoC, KITTI) share — a list of
/// frames (time, image file, optional depth file, optional ground-truth pose) built at
/// open(), and load(), which decodes one listed PNG into a pool slot.
///
/// What is an error and what is a counted skip (the same for every folder layout):
/// - open() errors (Status kInputError, naming the file and line): missing folder, missing
///   index/calibration file, empty index, malformed index line, non-monotonic or duplicate
///   timestamp, malformed ground truth, none of the first kMaxProbeImages listed images
///   readable (the image size cannot be known).
/// - load() skips (LoadStatus::kSkip, message naming the image file and the index line that
///   lists it; ReplayCamera counts and logs them): image missing, unreadable or corrupt,
///   of a different size than the sequence's, of an unsupported pixel type; in RGB-D mode
///   also a frame without an associated depth image or with a bad depth image.

#include <cstdint>
#include <string>
#include <vector>

#include "hal/calibration.h"
#include "hal/replay/frame_loader.h"

namespace mer::hal {

/// Images probed at open() to learn the image size (the first readable one wins).
inline constexpr std::size_t kMaxProbeImages = 16;

/// One listed frame of a dataset folder.
struct FolderFrame {
  std::int64_t t_ns = 0;             ///< timestamp, ns
  std::string image;                 ///< full path of the image
  std::string depth;                 ///< full path of the depth image ("" when none)
  std::string listed_at;             ///< "index file:line" that lists it (for messages)
  bool has_ground_truth = false;     ///< a ground-truth pose is known at t_ns
  SE3d T_w_c_gt = SE3d::Identity();  ///< that pose (camera-to-world)
};

/// Base of the dataset-folder loaders: subclasses fill the protected members in open().
class FolderLoader : public FrameLoader {
 public:
  std::size_t size() const override { return frames_.size(); }
  const CameraIntrinsics& intrinsics() const override { return intrinsics_; }
  bool has_depth() const override { return with_depth_; }
  bool has_ground_truth() const override { return has_ground_truth_; }
  /// Decodes frame `index` (color or gray PNG of 8 or 16 bits -> 8-bit gray; 16-bit depth
  /// PNG / depth_scale -> metres, 0 stays 0 = no measurement). Allocates (decoding).
  LoadStatus load(std::size_t index, Frame& out, Status& status) override;
  /// (frames - 1) / (t_last - t_first), 0 with fewer than two frames.
  double nominal_fps() const override;
  std::string describe() const override;
  const Trajectory& ground_truth() const override { return ground_truth_; }

  /// The listed frames (valid after open()).
  const std::vector<FolderFrame>& frames() const { return frames_; }

 protected:
  /// `scheme` and `dir` name the source in messages ("tum", "/data/fr1_xyz").
  FolderLoader(std::string scheme, std::string dir, const CalibrationOptions& calib,
               bool with_depth, double depth_scale);

  /// "scheme:dir" for messages.
  std::string uri() const { return scheme_ + ":" + dir_; }
  /// `dir_ + "/" + rel`.
  std::string path(const std::string& rel) const;
  /// Error unless dir_ is an existing folder.
  Status check_folder() const;
  /// Sets intrinsics_.width/height from the first readable image among the first
  /// kMaxProbeImages frames; error naming the images when none can be read.
  Status probe_image_size();
  /// Applies the calibration override (when set) to intrinsics_, keeping the image size.
  void apply_calibration_override();
  /// Gives each frame the ground-truth pose interpolated at its time (interpolate_pose()
  /// with `max_dt_ns`); sets has_ground_truth_ when the trajectory is not empty.
  void assign_interpolated_ground_truth(std::int64_t max_dt_ns);

  std::string scheme_;
  std::string dir_;
  CalibrationOptions calib_;
  bool with_depth_;
  double depth_scale_;
  std::vector<FolderFrame> frames_;
  CameraIntrinsics intrinsics_;
  Trajectory ground_truth_;
  bool has_ground_truth_ = false;
};

}  // namespace mer::hal
