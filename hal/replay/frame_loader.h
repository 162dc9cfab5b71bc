#pragma once
/// @file frame_loader.h
/// FrameLoader: what a recorded source (TUM, EuRoC, KITTI folders, native .merrec files)
/// implements so that ReplayCamera can turn it into a CameraSource.
///
/// ReplayCamera owns the frame pool and a low-priority prefetch thread that calls
/// load() ahead of the consumer, decoding into pool buffers; the capture thread's acquire()
/// only hands out frames that are already decoded, so it neither allocates nor blocks on
/// file I/O. Loaders may allocate inside load() (image decoding does).

#include <cstddef>
#include <cstdint>
#include <string>

#include "core/status.h"
#include "hal/camera.h"
#include "hal/ground_truth.h"

namespace mer::hal {

/// What load() reports for one frame.
enum class LoadStatus {
  kOk,           ///< the frame was decoded into the slot
  kSkip,         ///< this frame is unusable but the stream goes on (counted and logged)
  kEndOfStream,  ///< no frame at this index or after it (e.g. truncated recording)
  kError,        ///< unrecoverable: stop the stream (message in the Status)
};

/// One recorded sequence, read frame by frame in index order.
class FrameLoader {
 public:
  virtual ~FrameLoader() = default;

  /// Opens the sequence: reads indexes, calibration, ground truth; checks the first image
  /// so the image size is known. Errors name the file (and line) at fault.
  virtual Status open() = 0;
  /// Number of frames listed (an upper bound when the source may end early).
  virtual std::size_t size() const = 0;
  /// Image size and calibration (valid after open()).
  virtual const CameraIntrinsics& intrinsics() const = 0;
  /// True when frames carry depth (RGB-D), so pool slots get a depth buffer.
  virtual bool has_depth() const = 0;
  /// True when frames carry a ground-truth pose.
  virtual bool has_ground_truth() const = 0;
  /// Decodes frame `index` into `out` (buffers already sized from intrinsics(), 8-bit gray;
  /// depth CV_32FC1 in metres when has_depth()). Sets seq, t_ns and ground truth; `status`
  /// receives the reason for kSkip/kError/kEndOfStream (file and line).
  virtual LoadStatus load(std::size_t index, Frame& out, Status& status) = 0;
  /// Frame rate the sequence was recorded at (from timestamps), 0 when unknown.
  virtual double nominal_fps() const = 0;
  /// Where the source is damaged (e.g. a truncated recording), empty when intact.
  virtual std::string damage_report() const { return {}; }
  /// Human-readable description ("kitti:/data/00 (1241x376, 4541 frames)").
  virtual std::string describe() const = 0;
  /// The sequence's whole ground-truth trajectory (camera-to-world, at the ground truth's
  /// own rate, for evaluation), empty when there is none. Valid after open().
  virtual const Trajectory& ground_truth() const {
    static const Trajectory kNone;
    return kNone;
  }
};

}  // namespace mer::hal
