#pragma once
/// @file replay_camera.h
/// ReplayCamera: turns any FrameLoader (TUM, EuRoC, KITTI folders, native recordings) into
/// a CameraSource.
///
/// Threads: a low-priority prefetch thread ("mer_replay") calls loader->load(i) in index
/// order into free pool slots, at most `prefetch` frames ahead of the consumer, and passes
/// the ready slot indices through an SpscRing. acquire() (the capture thread) only pops
/// ready slots, so it never allocates nor touches files. When the ring is full or the pool
/// has no free slot the prefetcher waits (polling every kPrefetchPollNs); it never drops.
///
/// Stream rules:
/// - LoadStatus::kSkip: counted (skipped()) and logged with MER_LOG_WARN (file and reason);
///   the stream goes on. More than `max_consecutive_skips` skips in a row end the stream
///   with an error.
/// - LoadStatus::kError: acquire() returns kError and last_error() has the message.
/// - LoadStatus::kEndOfStream or the last index: acquire() returns kEndOfStream.
/// - paced: frame i is released at start() + (t_i - t_first) on the monotonic clock
///   (t_first = the first delivered frame's time); acquire() returns kTimeout when the next
///   frame is not due (or not decoded) within the timeout. Unpaced (lockstep): frames are
///   handed out as soon as decoded; acquire() waits for the prefetcher up to the timeout.
/// - Frame::seq is the frame's index in the sequence (gaps = skipped frames),
///   Frame::produce_ns the decode time on the prefetch thread, Frame::t_ready_ns the
///   monotonic time acquire() handed the frame out (when it "arrived").
/// - stop() wakes and joins the prefetch thread (returns within one image decode) and gives
///   every undelivered slot back to the pool; acquire() then returns kEndOfStream.

#include <atomic>
#include <cstdint>
#include <memory>
#include <string>

#include "core/options.h"
#include "hal/calibration.h"
#include "hal/camera.h"
#include "hal/replay/frame_loader.h"
#include "platform/notifier.h"
#include "platform/rt_thread.h"
#include "platform/spsc_ring.h"

namespace mer::hal {

/// Largest accepted `prefetch` (the ready ring holds kMaxReplayPrefetch + end marker).
inline constexpr int kMaxReplayPrefetch = 32;

/// Options of dataset/recording replay (config section `camera.replay`).
struct ReplayOptions {
  int prefetch = 4;
  int max_consecutive_skips = 10;
  double depth_scale = 5000.0;
  double max_time_diff_s = 0.02;

  /// Names every field once with its key, doc line and range (see core/options.h).
  template <class V>
  void visit(V& v) {
    v.field("prefetch", prefetch, "frames decoded ahead of the consumer (< camera.pool_size)",
            options::Range<int>{1, kMaxReplayPrefetch});
    v.field("max_consecutive_skips", max_consecutive_skips,
            "unusable frames in a row tolerated before the stream fails",
            options::Range<int>{0, 1000000});
    v.field("depth_scale", depth_scale, "TUM depth PNG units per metre",
            options::Range<double>{1.0, 1e6});
    v.field("max_time_diff_s", max_time_diff_s,
            "max time difference for rgb-depth association and ground-truth interpolation, s",
            options::Range<double>{0.0, 1.0});
  }
};

/// A CameraSource replaying a FrameLoader (see the file comment for the stream rules).
class ReplayCamera final : public CameraSource {
 public:
  /// `paced`: release frames at the recorded rate (threaded mode); false: as fast as the
  /// consumer asks (lockstep).
  ReplayCamera(std::unique_ptr<FrameLoader> loader, const ReplayOptions& opts, bool paced);
  /// stop().
  ~ReplayCamera() override;
  ReplayCamera(const ReplayCamera&) = delete;
  ReplayCamera& operator=(const ReplayCamera&) = delete;

  /// Validates the options, opens the loader, allocates `pool_size` slots sized from the
  /// loader's intrinsics (plus a depth buffer when it has depth). `pool_size` must exceed
  /// `prefetch`.
  Status open(std::size_t pool_size) override;
  /// Starts the prefetch thread (allocates: thread start). Once only.
  Status start() override;
  AcquireStatus acquire(FrameHandle& out, std::int64_t timeout_ns) override;
  void stop() override;
  const CameraIntrinsics& intrinsics() const override { return loader_->intrinsics(); }
  CameraCapabilities capabilities() const override;
  std::string describe() const override;
  /// The error that ended the stream; ok until acquire() has returned kError.
  const Status& last_error() const override;
  FramePool& pool() override { return *pool_; }

  /// Frames skipped so far (unusable frames, counted on the prefetch thread).
  std::uint64_t skipped() const noexcept { return skipped_.load(std::memory_order_relaxed); }
  /// Skipped frames and the loader's damage report.
  SourceCounters counters() const override;
  /// The loader (e.g. for its ground_truth()).
  const FrameLoader& loader() const { return *loader_; }

 private:
  enum class ItemKind : std::uint8_t { kFrame, kEnd, kError };
  struct Item {
    std::uint32_t slot = platform::kInvalidPoolIndex;
    ItemKind kind = ItemKind::kEnd;
  };
  static constexpr std::size_t kRingSize = 64;  // > kMaxReplayPrefetch + 1
  static_assert(kRingSize > static_cast<std::size_t>(kMaxReplayPrefetch) + 1);

  void prefetch_loop();
  // Waits until fewer than `prefetch` frames are queued and a pool slot is free; false when
  // stop was requested.
  bool wait_for_room(FrameHandle& slot);
  // Pushes `item`, waiting while the ring is full; false when stop was requested.
  bool push(Item item);
  void finish_with_error(Status error);

  std::unique_ptr<FrameLoader> loader_;
  ReplayOptions opts_;
  bool paced_;
  std::unique_ptr<FramePool> pool_;
  std::unique_ptr<platform::SpscRing<Item, kRingSize>> ready_;
  platform::Notifier ready_wake_;  // prefetcher -> consumer: an item was pushed
  platform::Notifier room_wake_;   // consumer -> prefetcher: an item was popped / stop
  platform::RtThread thread_;
  std::atomic<bool> stop_requested_{false};
  std::atomic<std::uint64_t> skipped_{0};
  Status prefetch_error_;  // written by the prefetcher before it pushes kError

  // Consumer (capture thread) state.
  bool opened_ = false;
  bool started_ = false;
  bool stopped_ = false;
  bool ended_ = false;       // kEnd or kError seen
  bool error_seen_ = false;  // last_error() may read prefetch_error_
  Item pending_{};           // popped frame not yet due (paced)
  bool has_pending_ = false;
  bool have_t_first_ = false;
  std::int64_t t_first_ns_ = 0;
  std::int64_t start_mono_ns_ = 0;
};

/// Creates (does not open) the replay camera for `scheme` in {tum, euroc, kitti} and the
/// folder `path`. `calib` is the calibration override (fx == 0: not set; TUM needs it);
/// `rgbd` asks for depth (TUM only; an error for the others); `paced` as in ReplayCamera.
/// Errors: unknown scheme, rgbd with a source without depth.
Result<std::unique_ptr<CameraSource>> make_replay_camera(const std::string& scheme,
                                                         const std::string& path,
                                                         const ReplayOptions& opts,
                                                         const CalibrationOptions& calib, bool rgbd,
                                                         bool paced);

}  // namespace mer::hal
