#include "hal/replay/replay_camera.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <exception>
#include <limits>
#include <thread>

#include "hal/replay/euroc_loader.h"
#include "hal/replay/kitti_loader.h"
#include "hal/replay/tum_loader.h"
#include "platform/clock.h"
#include "platform/log_ring.h"

namespace mer::hal {
namespace {

constexpr platform::ThreadSpec kPrefetchThread{"mer_replay", -1, 0};
constexpr std::int64_t kPrefetchPollNs = 1'000'000;  // prefetcher re-checks for free slots
constexpr double kNsPerS = 1e9;

void sleep_ns(std::int64_t ns) {
  if (ns > 0) std::this_thread::sleep_for(std::chrono::nanoseconds(ns));
}

}  // namespace

ReplayCamera::ReplayCamera(std::unique_ptr<FrameLoader> loader, const ReplayOptions& opts,
                           bool paced)
    : loader_(std::move(loader)), opts_(opts), paced_(paced) {}

ReplayCamera::~ReplayCamera() {
  stop();
}

Status ReplayCamera::open(std::size_t pool_size) {
  if (!loader_) return invalid_argument("replay camera: no loader");
  options::Validator validator("camera.replay.");
  opts_.visit(validator);
  if (!validator.status().is_ok()) return validator.status();
  if (pool_size <= static_cast<std::size_t>(opts_.prefetch)) {
    return invalid_argument("camera.pool_size (" + std::to_string(pool_size) +
                            ") must be greater than camera.replay.prefetch (" +
                            std::to_string(opts_.prefetch) + ")");
  }
  if (Status s = loader_->open(); !s.is_ok()) return s;
  const CameraIntrinsics& k = loader_->intrinsics();
  if (k.width <= 0 || k.height <= 0) {
    return input_error(loader_->describe() + ": image size unknown after open()");
  }
  const int w = k.width;
  const int h = k.height;
  const bool depth = loader_->has_depth();
  pool_ = std::make_unique<FramePool>(pool_size, [w, h, depth](Frame& fr, std::size_t) {
    fr.gray = cv::Mat(h, w, CV_8UC1);
    if (depth) fr.depth = cv::Mat(h, w, CV_32FC1);
  });
  ready_ = std::make_unique<platform::SpscRing<Item, kRingSize>>();
  opened_ = true;
  return Status::ok();
}

Status ReplayCamera::start() {
  if (!opened_) return runtime_error("replay camera: start() before a successful open()");
  if (started_) return runtime_error(loader_->describe() + ": start() called twice");
  started_ = true;
  start_mono_ns_ = platform::monotonic_now_ns();
  if (!thread_.start(kPrefetchThread, [this] { prefetch_loop(); })) {
    stopped_ = true;
    return runtime_error(loader_->describe() + ": cannot start the prefetch thread");
  }
  return Status::ok();
}

bool ReplayCamera::wait_for_room(FrameHandle& slot) {
  const auto limit = static_cast<std::size_t>(opts_.prefetch);
  for (;;) {
    if (stop_requested_.load(std::memory_order_acquire)) return false;
    const std::uint32_t seen = room_wake_.epoch();
    // Check available_approx() first so waiting does not inflate the pool's exhausted count.
    if (ready_->size_approx() < limit && pool_->available_approx() > 0) {
      slot = pool_->acquire();
      if (slot) return true;
    }
    // Slots released downstream do not notify us: poll.
    static_cast<void>(room_wake_.wait_for(seen, kPrefetchPollNs));
  }
}

bool ReplayCamera::push(Item item) {
  for (;;) {
    if (ready_->try_push(item)) {
      ready_wake_.notify();
      return true;
    }
    if (stop_requested_.load(std::memory_order_acquire)) return false;
    const std::uint32_t seen = room_wake_.epoch();
    static_cast<void>(room_wake_.wait_for(seen, kPrefetchPollNs));
  }
}

void ReplayCamera::finish_with_error(Status error) {
  MER_LOG_ERROR("%s", error.message().c_str());
  prefetch_error_ = std::move(error);
  static_cast<void>(push(Item{platform::kInvalidPoolIndex, ItemKind::kError}));
}

void ReplayCamera::prefetch_loop() {
  const std::size_t n = loader_->size();
  int consecutive_skips = 0;
  for (std::size_t i = 0; i < n; ++i) {
    FrameHandle slot;
    if (!wait_for_room(slot)) return;
    Status status;
    LoadStatus ls = LoadStatus::kError;
    const std::int64_t t0 = platform::monotonic_now_ns();
    const std::int64_t cpu0 = platform::thread_cpu_ns();
    try {
      ls = loader_->load(i, *slot, status);
    } catch (const std::exception& e) {
      status =
          runtime_error(loader_->describe() + ": frame " + std::to_string(i) + ": " + e.what());
      ls = LoadStatus::kError;
    }
    switch (ls) {
      case LoadStatus::kOk:
        consecutive_skips = 0;
        slot->produce_ns = platform::monotonic_now_ns() - t0;
        slot->produce_cpu_ns = platform::thread_cpu_ns() - cpu0;
        if (!push(Item{slot.release_raw(), ItemKind::kFrame})) return;
        break;
      case LoadStatus::kSkip:
        skipped_.fetch_add(1, std::memory_order_relaxed);
        MER_LOG_WARN("replay: skipped frame %zu: %s", i, status.message().c_str());
        if (++consecutive_skips > opts_.max_consecutive_skips) {
          finish_with_error(input_error(
              loader_->describe() + ": " + std::to_string(consecutive_skips) +
              " unusable frames in a row (camera.replay.max_consecutive_skips = " +
              std::to_string(opts_.max_consecutive_skips) + "); last: " + status.message()));
          return;
        }
        break;
      case LoadStatus::kEndOfStream:
        static_cast<void>(push(Item{platform::kInvalidPoolIndex, ItemKind::kEnd}));
        return;
      case LoadStatus::kError:
        finish_with_error(status.is_ok() ? runtime_error(loader_->describe() + ": frame " +
                                                         std::to_string(i) + ": load failed")
                                         : status);
        return;
    }
  }
  static_cast<void>(push(Item{platform::kInvalidPoolIndex, ItemKind::kEnd}));
}

AcquireStatus ReplayCamera::acquire(FrameHandle& out, std::int64_t timeout_ns) {
  if (!started_ || stopped_) return AcquireStatus::kEndOfStream;
  if (ended_) return error_seen_ ? AcquireStatus::kError : AcquireStatus::kEndOfStream;
  room_wake_.notify();  // the caller may have released slots since the last call
  std::int64_t deadline = 0;
  if (__builtin_add_overflow(platform::monotonic_now_ns(), std::max<std::int64_t>(timeout_ns, 0),
                             &deadline)) {
    deadline = std::numeric_limits<std::int64_t>::max();  // "wait forever"
  }

  if (!has_pending_) {
    for (;;) {
      const std::uint32_t seen = ready_wake_.epoch();
      if (ready_->try_pop(pending_)) break;
      const std::int64_t left = deadline - platform::monotonic_now_ns();
      if (left <= 0) return AcquireStatus::kTimeout;
      static_cast<void>(ready_wake_.wait_for(seen, left));
    }
    room_wake_.notify();
    if (pending_.kind != ItemKind::kFrame) {
      ended_ = true;
      error_seen_ = pending_.kind == ItemKind::kError;
      return error_seen_ ? AcquireStatus::kError : AcquireStatus::kEndOfStream;
    }
    has_pending_ = true;
  }

  if (paced_) {
    const std::int64_t t_ns = pool_->slot(pending_.slot).t_ns;
    if (!have_t_first_) {
      t_first_ns_ = t_ns;
      have_t_first_ = true;
    }
    // start + (t - t_first), saturating: absurd recorded gaps must not overflow.
    std::int64_t delta = 0;
    std::int64_t due = 0;
    if (__builtin_sub_overflow(t_ns, t_first_ns_, &delta) ||
        __builtin_add_overflow(start_mono_ns_, delta, &due)) {
      due = delta < 0 ? start_mono_ns_ : std::numeric_limits<std::int64_t>::max();
    }
    if (due > deadline) {
      sleep_ns(deadline - platform::monotonic_now_ns());
      return AcquireStatus::kTimeout;
    }
    sleep_ns(due - platform::monotonic_now_ns());
  }
  out = pool_->adopt(pending_.slot);
  has_pending_ = false;
  out->t_ready_ns = platform::monotonic_now_ns();
  return AcquireStatus::kFrame;
}

void ReplayCamera::stop() {
  if (stopped_) return;
  stopped_ = true;
  if (!started_) return;
  stop_requested_.store(true, std::memory_order_release);
  room_wake_.notify_all();
  thread_.join();
  // Give every decoded but undelivered slot back to the pool.
  Item item;
  while (ready_->try_pop(item)) {
    if (item.kind == ItemKind::kFrame) pool_->adopt(item.slot).reset();
  }
  if (has_pending_) {
    pool_->adopt(pending_.slot).reset();
    has_pending_ = false;
  }
}

CameraCapabilities ReplayCamera::capabilities() const {
  return CameraCapabilities{paced_, loader_->has_depth(), loader_->has_ground_truth(),
                            loader_->nominal_fps()};
}

std::string ReplayCamera::describe() const {
  return loader_->describe();
}

const Status& ReplayCamera::last_error() const {
  static const Status kNoError;
  return error_seen_ ? prefetch_error_ : kNoError;
}

Result<std::unique_ptr<CameraSource>> make_replay_camera(const std::string& scheme,
                                                         const std::string& path,
                                                         const ReplayOptions& opts,
                                                         const CalibrationOptions& calib, bool rgbd,
                                                         bool paced) {
  const auto max_dt_ns = static_cast<std::int64_t>(std::llround(opts.max_time_diff_s * kNsPerS));
  std::unique_ptr<FrameLoader> loader;
  if (scheme == "tum") {
    loader = std::make_unique<TumLoader>(path, calib, rgbd, opts.depth_scale, max_dt_ns);
  } else if (scheme == "euroc" || scheme == "kitti") {
    if (rgbd) {
      return invalid_argument("--mode rgbd: '" + scheme + ":" + path +
                              "' has no depth images (use --mode mono, or a tum: folder)");
    }
    if (scheme == "euroc") {
      loader = std::make_unique<EurocLoader>(path, calib, max_dt_ns);
    } else {
      loader = std::make_unique<KittiLoader>(path, calib);
    }
  } else {
    return invalid_argument("replay: unknown dataset scheme '" + scheme +
                            "' (expected tum, euroc or kitti)");
  }
  return std::unique_ptr<CameraSource>(
      std::make_unique<ReplayCamera>(std::move(loader), opts, paced));
}

SourceCounters ReplayCamera::counters() const {
  SourceCounters c;
  c.skipped = skipped();
  // The loader's damage is written on the prefetch thread: read it once that has stopped.
  if (!thread_.joinable()) c.damage = loader_->damage_report();
  return c;
}

}  // namespace mer::hal
