#pragma once
/// @file v4l2_camera.h
/// `v4l2:/dev/videoN` — a live camera through raw V4L2 ioctls with mmap streaming.
///
/// open(): QUERYCAP (single-planar VIDEO_CAPTURE + STREAMING), ENUM_FMT /
/// ENUM_FRAMESIZES / ENUM_FRAMEINTERVALS to pick and validate the format, size and rate,
/// S_FMT, S_PARM (the frame rate is always set), REQBUFS + QUERYBUF + mmap, and the frame
/// pool (one gray image per slot). start(): QBUF all, STREAMON. acquire(): ppoll bounded
/// by the caller's timeout, DQBUF, conversion of the luma straight into the pool slot's
/// image (no intermediate copy, no allocation), QBUF back. stop(): STREAMOFF.
///
/// Timestamps: the driver's buffer timestamp when the buffer says
/// V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC (the same clock as platform::monotonic_now_ns());
/// otherwise the frame is stamped at dequeue (driver_timestamps() is false and a warning
/// is logged once).
///
/// Errors: every failing call is reported as "v4l2:<device>: <call> failed: <strerror>
/// (<ERRNO>)[: hint]". Buffers flagged V4L2_BUF_FLAG_ERROR are dropped, counted and
/// re-queued; gaps in the driver's sequence numbers are counted. A device that disappears
/// or fails mid-stream (ENODEV/EIO from DQBUF, POLLERR, no frame for dequeue_timeout_ms)
/// stops the camera cleanly (acquire() returns kError, last_error() says why) or, with
/// on_error: retry, is closed and reopened after retry_delay_ms up to max_retries times
/// while acquire() returns kTimeout. Nothing blocks longer than the caller's timeout
/// (the retry delay is waited in slices of it).
///
/// Frame::seq extends the driver's 32-bit sequence to 64 bits and keeps increasing across
/// restarts.

#include <array>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <string>

#include "core/status.h"
#include "hal/camera.h"
#include "hal/pixel_convert.h"
#include "hal/v4l2/v4l2_options.h"

namespace mer::hal {

/// Counters of a V4L2 camera since open().
struct V4l2Stats {
  std::uint64_t frames = 0;           ///< frames handed out by acquire()
  std::uint64_t error_frames = 0;     ///< buffers flagged V4L2_BUF_FLAG_ERROR (dropped, re-queued)
  std::uint64_t short_frames = 0;     ///< buffers with fewer bytes than the format needs (dropped)
  std::uint64_t sequence_gaps = 0;    ///< frames the driver skipped (sum of sequence jumps - 1)
  std::uint64_t stream_errors = 0;    ///< mid-stream device errors (each stops or restarts)
  std::uint64_t restarts = 0;         ///< successful reopen + restart cycles (on_error: retry)
  std::uint64_t reopen_failures = 0;  ///< failed reopen attempts (on_error: retry)
};

/// The V4L2 camera. Not thread-safe (one capture thread); handles may be released anywhere.
class V4l2Camera final : public CameraSource {
 public:
  /// `device` is the device node path ("/dev/video0"); nothing is opened yet.
  V4l2Camera(std::string device, const V4l2Options& opts);
  /// Error frames, sequence gaps and restarts from stats().
  SourceCounters counters() const override {
    const V4l2Stats& st = stats();
    return SourceCounters{0, st.error_frames + st.short_frames, st.sequence_gaps, st.restarts, {}};
  }
  /// Stops streaming, unmaps the buffers and closes the device.
  ~V4l2Camera() override;
  V4l2Camera(const V4l2Camera&) = delete;
  V4l2Camera& operator=(const V4l2Camera&) = delete;

  /// Opens and configures the device (see the file comment) and allocates `pool_size`
  /// frames (kept when open() is called again with the same size and geometry). Errors
  /// name the device and the failing call (input_error: missing, busy, not a capture
  /// device, format/size/rate not offered).
  Status open(std::size_t pool_size) override;
  /// Queues every buffer and starts streaming. A STREAMON failure is reported and leaves
  /// the camera opened but stopped (start() may be called again).
  Status start() override;
  /// Waits up to `timeout_ns` for the next good frame (error-flagged and short buffers
  /// are dropped and waiting continues). kPoolEmpty when no pool slot is free (the
  /// device is not touched), kError after a fatal device error (see last_error()).
  AcquireStatus acquire(FrameHandle& out, std::int64_t timeout_ns) override;
  /// Stops streaming (STREAMOFF); acquire() then returns kEndOfStream. The device stays
  /// open and start() may resume (after a fatal error the device is closed: open() again).
  void stop() override;
  /// Image size with a focal length guessed from hfov_deg (focal_known = false).
  const CameraIntrinsics& intrinsics() const override { return intrinsics_; }
  /// Live source, no depth, no ground truth, the frame rate the driver accepted.
  CameraCapabilities capabilities() const override;
  /// "v4l2:/dev/video0 (card, 640x480 YUYV @ 25 Hz, 4 buffers)".
  std::string describe() const override;
  /// Last error (kept after a successful restart, for the record).
  const Status& last_error() const override { return last_error_; }
  /// The frame pool (valid after open()).
  FramePool& pool() override { return *pool_; }

  /// Counters since open().
  const V4l2Stats& stats() const noexcept { return stats_; }
  /// Buffers flagged V4L2_BUF_FLAG_ERROR that were dropped.
  std::uint64_t error_frames() const noexcept { return stats_.error_frames; }
  /// Frames the driver skipped according to its sequence numbers.
  std::uint64_t sequence_gaps() const noexcept { return stats_.sequence_gaps; }
  /// The capture format chosen at open().
  PixelFormat pixel_format() const noexcept { return format_; }
  /// Frame rate the driver accepted (VIDIOC_S_PARM), Hz; 0 when it cannot set one.
  double fps() const noexcept { return fps_; }
  /// True when frame timestamps are the driver's (monotonic clock); false when frames
  /// are stamped at dequeue. Known after the first frame.
  bool driver_timestamps() const noexcept { return driver_timestamps_; }
  /// The device node path.
  const std::string& device() const noexcept { return device_; }

 private:
  enum class State { kClosed, kOpen, kStreaming, kRecovering, kStopped, kFailed };

  /// One mmap'ed driver buffer.
  struct MappedBuffer {
    void* data = nullptr;    // mmap address (MAP_FAILED never stored)
    std::size_t length = 0;  // mapped bytes
  };

  Status open_device();      // open + QUERYCAP + format + rate + REQBUFS + mmap
  Status select_format();    // ENUM_FMT + ENUM_FRAMESIZES + S_FMT
  Status select_rate();      // ENUM_FRAMEINTERVALS + S_PARM
  Status map_buffers();      // REQBUFS + QUERYBUF + mmap
  Status start_streaming();  // QBUF all + STREAMON
  void close_device() noexcept;
  Status errno_error(const char* call, int err) const;
  bool requeue(std::uint32_t index, Status& error);
  AcquireStatus stream_error(Status error);
  AcquireStatus recover(std::int64_t timeout_ns);
  std::uint64_t track_sequence(std::uint32_t driver_seq) noexcept;

  std::string device_;
  V4l2Options opts_;
  State state_ = State::kClosed;
  int fd_ = -1;
  std::string card_;  // QUERYCAP card name
  PixelFormat format_ = PixelFormat::kGrey;
  ImageLayout layout_;
  double fps_ = 0.0;
  std::array<MappedBuffer, kV4l2MaxBuffers> buffers_{};
  std::uint32_t buffer_count_ = 0;
  CameraIntrinsics intrinsics_;
  std::unique_ptr<FramePool> pool_;
  Status last_error_;
  Status first_stream_error_;  // error that started the current recovery
  V4l2Stats stats_;
  bool driver_timestamps_ = false;
  bool timestamp_checked_ = false;
  bool have_seq_ = false;  // a buffer was dequeued in the current stream
  bool ever_seq_ = false;  // a buffer was dequeued since open()
  std::uint32_t last_driver_seq_ = 0;
  std::uint64_t seq_ = 0;              // 64-bit sequence number of the last buffer
  std::int64_t last_progress_ns_ = 0;  // start or last dequeue, for stall detection
  std::int64_t next_attempt_ns_ = 0;   // recovery: time of the next reopen attempt
  int recover_attempts_ = 0;           // reopen attempts in the current recovery
};

/// Creates (does not open) the camera for device node `device`; invalid options are an
/// error naming the key.
Result<std::unique_ptr<CameraSource>> make_v4l2_camera(const std::string& device,
                                                       const V4l2Options& opts);

}  // namespace mer::hal
