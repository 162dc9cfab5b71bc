#pragma once
/// @file camera.h
/// CameraSource: the one interface behind every producer of frames — the synthetic camera,
/// dataset replay (TUM, EuRoC, KITTI, native recordings), V4L2 and libcamera devices.
///
/// Frames live in a fixed pool owned by the source (capacity set at open(); no allocation
/// after start()). acquire() hands out a move-only FrameHandle; dropping or releasing the
/// handle returns the buffer to the pool. Timestamps are int64 nanoseconds on the monotonic
/// clock for live devices, or the recording's own time base for replay.

#include <array>
#include <cstdint>
#include <memory>
#include <string>

#include <opencv2/core/mat.hpp>

#include "core/pose.h"
#include "core/status.h"
#include "platform/fixed_pool.h"

namespace mer::hal {

/// Pinhole intrinsics with optional radial-tangential distortion (k1, k2, p1, p2).
struct CameraIntrinsics {
  int width = 0;                 ///< image width, px
  int height = 0;                ///< image height, px
  double fx = 0.0;               ///< focal length x, px
  double fy = 0.0;               ///< focal length y, px
  double cx = 0.0;               ///< principal point x, px
  double cy = 0.0;               ///< principal point y, px
  std::array<double, 4> dist{};  ///< k1, k2, p1, p2 (radtan); zeros when rectified
  bool focal_known = true;       ///< false when fx/fy are only a guess (focal estimation)
};

/// What a source can do and provides.
struct CameraCapabilities {
  bool live = false;              ///< true for devices (frames can be dropped), false for replay
  bool has_depth = false;         ///< frames carry a depth image (RGB-D, synthetic)
  bool has_ground_truth = false;  ///< frames carry the true pose T_w_c
  double nominal_fps = 0.0;       ///< frame rate the source produces at (0: unknown)
};

/// One image with its metadata; lives in a pool slot. The Mats are headers over buffers
/// allocated once per slot at open(); sources write into them in place.
struct Frame {
  std::uint64_t seq = 0;             ///< sequence number from the source (gaps mean source drops)
  std::int64_t t_ns = 0;             ///< capture time, ns
  std::int64_t t_ready_ns = 0;       ///< monotonic time the frame was complete in its buffer
  std::int64_t produce_ns = 0;       ///< time the source spent producing it (convert/render), ns
  std::int64_t produce_cpu_ns = 0;   ///< CPU time of that work (on whichever thread did it), ns
  cv::Mat gray;                      ///< 8-bit single-channel image (CV_8UC1)
  cv::Mat depth;                     ///< metres (CV_32FC1); empty when !has_depth
  bool has_ground_truth = false;     ///< ground truth available for this frame
  SE3d T_w_c_gt = SE3d::Identity();  ///< true camera-to-world pose (synthetic, datasets)
};

using FramePool = platform::FixedPool<Frame>;
using FrameHandle = platform::PoolHandle<Frame>;

/// Result of acquire(): a frame, or why there is none.
enum class AcquireStatus {
  kFrame,        ///< `out` holds a frame
  kTimeout,      ///< nothing within the timeout; call again
  kEndOfStream,  ///< finite source exhausted
  kPoolEmpty,    ///< every pool buffer is in use downstream (counted by the caller)
  kError,        ///< device or file error; see last_error()
};

/// What a source dropped or survived, for summary.json (all zero when nothing happened).
struct SourceCounters {
  std::uint64_t skipped = 0;       ///< unusable recorded frames skipped (replay)
  std::uint64_t error_frames = 0;  ///< frames the device flagged as corrupt (dropped)
  std::uint64_t seq_gaps = 0;      ///< frames the device/driver skipped (sequence jumps)
  std::uint64_t restarts = 0;      ///< successful recoveries after a device error
  std::string damage;              ///< where a recording is damaged (empty: intact)
};

/// The interface every camera implements. Not thread-safe: one capture thread calls
/// start/acquire/stop; handles may be released on any thread.
class CameraSource {
 public:
  virtual ~CameraSource() = default;

  /// Opens the device or dataset and allocates the frame pool (`pool_size` buffers).
  virtual Status open(std::size_t pool_size) = 0;
  /// Starts streaming. After this no allocation happens in acquire().
  virtual Status start() = 0;
  /// Waits up to `timeout_ns` for the next frame and hands it out in `out`.
  virtual AcquireStatus acquire(FrameHandle& out, std::int64_t timeout_ns) = 0;
  /// Returns a frame's buffer to the pool (same as destroying the handle).
  void release(FrameHandle&& frame) { frame.reset(); }
  /// Stops streaming; acquire() then returns kEndOfStream.
  virtual void stop() = 0;
  /// Calibration of the images this source produces.
  virtual const CameraIntrinsics& intrinsics() const = 0;
  /// What this source provides.
  virtual CameraCapabilities capabilities() const = 0;
  /// Human-readable description (URI, device name, scenario).
  virtual std::string describe() const = 0;
  /// The last error reported by acquire() (empty when none).
  virtual const Status& last_error() const = 0;
  /// The frame pool; the pipeline re-wraps raw slot indices passed through rings.
  virtual FramePool& pool() = 0;
  /// Drops and recoveries so far. Call from the capture thread or after stop().
  virtual SourceCounters counters() const { return {}; }
};

}  // namespace mer::hal
