#include "hal/libcamera/libcamera_camera.h"

#include <sys/mman.h>

#include <atomic>
#include <cerrno>
#include <charconv>
#include <cmath>
#include <cstring>
#include <map>
#include <numbers>
#include <span>
#include <vector>

#include <libcamera/libcamera.h>

#include "hal/pixel_convert.h"
#include "platform/clock.h"
#include "platform/log_ring.h"
#include "platform/notifier.h"
#include "platform/rt_thread.h"
#include "platform/spsc_ring.h"

namespace mer::hal {
namespace {

constexpr std::size_t kCompletedRing = 64;  // completed requests in flight (>= buffers)
// The thread that hands converted buffers back to libcamera (normal scheduling, any core).
constexpr platform::ThreadSpec kRequeueThread{"mer-lc-requeue", -1, 0};
constexpr std::int64_t kNsPerMs = 1'000'000;
constexpr double kUsPerS = 1e6;

struct FormatChoice {
  const char* name;
  libcamera::PixelFormat format;
  PixelFormat packed;
};

const std::vector<FormatChoice>& format_table() {
  static const std::vector<FormatChoice> kTable{
      {"R8", libcamera::formats::R8, PixelFormat::kGrey},
      {"YUYV", libcamera::formats::YUYV, PixelFormat::kYuyv},
      {"NV12", libcamera::formats::NV12, PixelFormat::kNv12},
      {"BGR888", libcamera::formats::BGR888, PixelFormat::kBgr888},
      {"RGB888", libcamera::formats::RGB888, PixelFormat::kRgb888},
      {"XRGB8888", libcamera::formats::XRGB8888, PixelFormat::kXrgb8888},
  };
  return kTable;
}

class LibcameraCamera final : public CameraSource {
 public:
  LibcameraCamera(std::string id, const LibcameraOptions& opts) : id_(std::move(id)), opts_(opts) {}
  ~LibcameraCamera() override { teardown(); }

  Status open(std::size_t pool_size) override {
    if (Status s = options::validate(opts_); !s.is_ok()) return s;
    teardown();  // a second open() starts from scratch (one CameraManager per process)
    manager_ = std::make_unique<libcamera::CameraManager>();
    if (int r = manager_->start(); r != 0) {
      return input_error("libcamera: CameraManager::start failed: " +
                         std::string(std::strerror(-r)));
    }
    const auto cams = manager_->cameras();
    std::string available;
    for (const auto& c : cams) available += (available.empty() ? "" : ", ") + c->id();
    if (available.empty()) available = "none";
    if (id_ == "auto" && !cams.empty()) {
      camera_ = cams.front();
    } else if (!id_.empty() && id_.find_first_not_of("0123456789") == std::string::npos) {
      std::size_t idx = 0;
      const auto [end, ec] = std::from_chars(id_.data(), id_.data() + id_.size(), idx);
      if (ec == std::errc() && end == id_.data() + id_.size() && idx < cams.size()) {
        camera_ = cams[idx];
      }
    } else {
      camera_ = manager_->get(id_);
    }
    if (!camera_) {
      return input_error("libcamera:" + id_ + ": no such camera (available: " + available + ")");
    }
    if (int r = camera_->acquire(); r != 0) {
      camera_.reset();
      return input_error("libcamera:" + id_ + ": cannot acquire camera: " + std::strerror(-r) +
                         (r == -EBUSY ? " (in use by another process)" : ""));
    }
    acquired_ = true;
    config_ = camera_->generateConfiguration({libcamera::StreamRole::Viewfinder});
    if (!config_ || config_->empty()) {
      return input_error("libcamera:" + id_ + ": no viewfinder configuration");
    }
    libcamera::StreamConfiguration& sc = config_->at(0);
    sc.size = {static_cast<unsigned>(opts_.width), static_cast<unsigned>(opts_.height)};
    sc.bufferCount = static_cast<unsigned>(opts_.buffers);
    // Pick the pixel format: the requested one, or the first supported of the table.
    const auto supported = sc.formats().pixelformats();
    const FormatChoice* choice = nullptr;
    for (const auto& f : format_table()) {
      const bool wanted = opts_.pixel_format == "auto" || opts_.pixel_format == f.name;
      const bool ok = std::find(supported.begin(), supported.end(), f.format) != supported.end();
      if (wanted && ok) {
        choice = &f;
        break;
      }
    }
    if (choice == nullptr) {
      std::string fmts;
      for (const auto& f : supported) fmts += (fmts.empty() ? "" : ", ") + f.toString();
      return input_error("libcamera:" + id_ + ": pixel format " + opts_.pixel_format +
                         " not supported (camera offers: " + fmts + ")");
    }
    sc.pixelFormat = choice->format;
    packed_ = choice->packed;
    if (config_->validate() == libcamera::CameraConfiguration::Invalid) {
      return input_error("libcamera:" + id_ + ": configuration " + sc.toString() + " is invalid");
    }
    if (int r = camera_->configure(config_.get()); r != 0) {
      return input_error("libcamera:" + id_ + ": configure(" + sc.toString() +
                         ") failed: " + std::strerror(-r));
    }
    stream_ = sc.stream();
    stride_ = sc.stride;
    // Pipelines without FrameDurationLimits (vimc) stream at their own rate: the requested
    // rate cannot be applied, so the nominal rate is unknown (0) rather than a guess.
    frame_rate_control_ = camera_->controls().count(&libcamera::controls::FrameDurationLimits) != 0;
    if (!frame_rate_control_) {
      MER_LOG_WARN("libcamera:%s: no FrameDurationLimits control: fps %.1f not applied",
                   id_.c_str(), opts_.fps);
    }
    const int w = static_cast<int>(sc.size.width);
    const int h = static_cast<int>(sc.size.height);
    if (w != opts_.width || h != opts_.height) {
      MER_LOG_WARN("libcamera:%s: size adjusted to %dx%d", id_.c_str(), w, h);
    }
    allocator_ = std::make_unique<libcamera::FrameBufferAllocator>(camera_);
    if (allocator_->allocate(stream_) < 0) {
      return input_error("libcamera:" + id_ + ": buffer allocation failed");
    }
    const auto& buffers = allocator_->buffers(stream_);
    if (buffers.size() > kCompletedRing) {
      return invalid_argument("key 'camera.libcamera.buffers': at most " +
                              std::to_string(kCompletedRing));
    }
    for (std::size_t i = 0; i < buffers.size(); ++i) {
      libcamera::FrameBuffer* fb = buffers[i].get();
      const auto& plane = fb->planes().front();
      // Map the whole dmabuf behind the first plane once; planes are offsets into it.
      const int fd = plane.fd.get();
      if (mappings_.count(fd) == 0) {
        std::size_t length = 0;
        for (const auto& p : fb->planes()) {
          if (p.fd.get() == fd) length = std::max<std::size_t>(length, p.offset + p.length);
        }
        void* mem = ::mmap(nullptr, length, PROT_READ, MAP_SHARED, fd, 0);
        if (mem == MAP_FAILED) {
          return input_error("libcamera:" + id_ + ": mmap failed: " + std::strerror(errno));
        }
        mappings_[fd] = {static_cast<std::uint8_t*>(mem), length};
      }
      const auto& [base, mapped] = mappings_[fd];
      planes_.emplace_back(base + plane.offset,
                           mapped > plane.offset ? mapped - plane.offset : std::size_t{0});
      std::unique_ptr<libcamera::Request> req = camera_->createRequest(i);
      if (!req || req->addBuffer(stream_, fb) != 0) {
        return input_error("libcamera:" + id_ + ": cannot create request " + std::to_string(i));
      }
      requests_.push_back(std::move(req));
    }
    // libcamera reports no calibration: a focal guess from the assumed field of view, marked
    // unknown (calibrate with --intrinsics, or let focal estimation refine it).
    const double focal = 0.5 * w / std::tan(0.5 * opts_.hfov_deg * std::numbers::pi / 180.0);
    intrinsics_ = CameraIntrinsics{w, h, focal, focal, 0.5 * (w - 1), 0.5 * (h - 1), {}, false};
    pool_ = std::make_unique<FramePool>(
        pool_size, [w, h](Frame& f, std::size_t) { f.gray = cv::Mat(h, w, CV_8UC1); });
    description_ = "libcamera:" + camera_->id() + " (" + sc.toString() + ")";
    return Status::ok();
  }

  Status start() override {
    if (!camera_ || requests_.empty()) return runtime_error("libcamera: start() before open()");
    if (running_) return Status::ok();
    // Indices left over from before a stop() are stale: the requests are queued afresh.
    std::uint32_t stale = 0;
    while (completed_.try_pop(stale)) {
    }
    while (returned_.try_pop(stale)) {
    }
    if (!connected_) {
      camera_->requestCompleted.connect(this, &LibcameraCamera::on_request_completed);
      connected_ = true;
    }
    libcamera::ControlList controls(camera_->controls());
    const auto frame_us = static_cast<std::int64_t>(kUsPerS / opts_.fps);
    if (frame_rate_control_) {
      controls.set(libcamera::controls::FrameDurationLimits,
                   libcamera::Span<const std::int64_t, 2>({frame_us, frame_us}));
    }
    if (int r = camera_->start(&controls); r != 0) {
      return input_error(description_ + ": start failed: " + std::strerror(-r));
    }
    seq_offset_ = next_seq_;
    running_ = true;
    requeue_error_.store(0, std::memory_order_relaxed);
    for (auto& req : requests_) {
      // After a stop() the requests were cancelled; libcamera asserts on re-queueing a
      // request that is not pending, so every request is reset first (a no-op when new).
      req->reuse(libcamera::Request::ReuseBuffers);
      if (int r = camera_->queueRequest(req.get()); r != 0) {
        stop();
        return input_error(description_ + ": queueRequest failed: " + std::strerror(-r));
      }
    }
    requeue_stop_.store(false, std::memory_order_relaxed);
    if (!requeue_thread_.start(kRequeueThread, [this] { requeue_loop(); })) {
      stop();
      return runtime_error(description_ + ": cannot start the requeue thread");
    }
    return Status::ok();
  }

  AcquireStatus acquire(FrameHandle& out, std::int64_t timeout_ns) override {
    if (!running_) return AcquireStatus::kEndOfStream;
    const std::int64_t deadline =
        platform::saturating_add_ns(platform::monotonic_now_ns(), timeout_ns);
    std::uint32_t index = 0;
    while (true) {
      const std::uint32_t epoch = completed_wake_.epoch();
      if (const int r = requeue_error_.load(std::memory_order_acquire); r != 0) {
        last_error_ = input_error(description_ + ": queueRequest failed: " + std::strerror(r));
        return AcquireStatus::kError;
      }
      if (completed_.try_pop(index)) break;
      const std::int64_t left = deadline - platform::monotonic_now_ns();
      if (left <= 0) return AcquireStatus::kTimeout;
      (void)completed_wake_.wait_for(
          epoch, std::min<std::int64_t>(left, opts_.dequeue_timeout_ms * kNsPerMs));
    }
    libcamera::Request* req = requests_[index].get();
    libcamera::FrameBuffer* fb = req->buffers().begin()->second;
    const libcamera::FrameMetadata& md = fb->metadata();
    AcquireStatus result = AcquireStatus::kFrame;
    if (md.status != libcamera::FrameMetadata::FrameSuccess) {
      ++frame_errors_;
      result = AcquireStatus::kTimeout;  // dropped and counted; the caller asks again
    } else {
      FrameHandle h = pool_->acquire();
      if (!h) {
        result = AcquireStatus::kPoolEmpty;
      } else {
        const std::int64_t t0 = platform::monotonic_now_ns();
        const std::int64_t cpu0 = platform::thread_cpu_ns();
        const ImageLayout layout{h->gray.cols, h->gray.rows, static_cast<int>(stride_)};
        if (!convert_to_gray(packed_, planes_[index], layout, h->gray)) {
          ++frame_errors_;  // buffer shorter than the configured layout: drop and count
          result = AcquireStatus::kTimeout;
        } else {
          // libcamera's 32-bit sequence restarts at every start(): continue numbering.
          h->seq = seq_offset_ + md.sequence;
          next_seq_ = h->seq + 1;
          h->t_ns = static_cast<std::int64_t>(md.timestamp);
          h->t_ready_ns = platform::monotonic_now_ns();
          h->produce_ns = h->t_ready_ns - t0;
          h->produce_cpu_ns = platform::thread_cpu_ns() - cpu0;
          out = std::move(h);
        }
      }
    }
    // Hand the buffer back through the requeue thread: Request::reuse() and
    // Camera::queueRequest() allocate inside libcamera (0.0.3: 5 operator new per request,
    // the pending-buffer set node and the cross-thread call message), which the capture
    // thread must not. The ring holds every request index, so the push cannot fail.
    (void)returned_.try_push(index);
    returned_wake_.notify();
    return result;
  }

  void stop() override {
    if (running_) {
      requeue_stop_.store(true, std::memory_order_release);
      returned_wake_.notify_all();
      requeue_thread_.join();
      // Cancels the requests in flight (completed as RequestCancelled, ignored below).
      camera_->stop();
      running_ = false;
    }
  }

  const CameraIntrinsics& intrinsics() const override { return intrinsics_; }
  CameraCapabilities capabilities() const override {
    return CameraCapabilities{true, false, false, frame_rate_control_ ? opts_.fps : 0.0};
  }
  std::string describe() const override {
    return description_.empty() ? "libcamera:" + id_ : description_;
  }
  const Status& last_error() const override { return last_error_; }
  FramePool& pool() override { return *pool_; }
  SourceCounters counters() const override { return SourceCounters{0, frame_errors_, 0, 0, {}}; }

 private:
  // Runs on libcamera's thread: pass the buffer index on, nothing else.
  void on_request_completed(libcamera::Request* req) {
    if (req->status() == libcamera::Request::RequestCancelled) return;
    if (!completed_.try_push(static_cast<std::uint32_t>(req->cookie()))) ++ring_overflows_;
    completed_wake_.notify();
  }

  // The requeue thread: reuse + queue the requests acquire() is done with.
  void requeue_loop() {
    std::uint32_t index = 0;
    for (;;) {
      const std::uint32_t epoch = returned_wake_.epoch();
      while (returned_.try_pop(index)) {
        libcamera::Request* req = requests_[index].get();
        req->reuse(libcamera::Request::ReuseBuffers);
        if (int r = camera_->queueRequest(req); r != 0) {
          requeue_error_.store(-r, std::memory_order_release);
          completed_wake_.notify();
        }
      }
      if (requeue_stop_.load(std::memory_order_acquire)) return;
      returned_wake_.wait(epoch);
    }
  }

  void teardown() {
    stop();
    if (connected_) {
      camera_->requestCompleted.disconnect(this, &LibcameraCamera::on_request_completed);
      connected_ = false;
    }
    requests_.clear();
    for (auto& [fd, m] : mappings_) ::munmap(m.first, m.second);
    mappings_.clear();
    if (allocator_ && stream_ != nullptr) allocator_->free(stream_);
    allocator_.reset();
    if (acquired_) camera_->release();
    acquired_ = false;
    camera_.reset();
    config_.reset();
    if (manager_) manager_->stop();
    manager_.reset();
  }

  std::string id_;
  LibcameraOptions opts_;
  std::unique_ptr<libcamera::CameraManager> manager_;
  std::shared_ptr<libcamera::Camera> camera_;
  std::unique_ptr<libcamera::CameraConfiguration> config_;
  std::unique_ptr<libcamera::FrameBufferAllocator> allocator_;
  libcamera::Stream* stream_ = nullptr;
  std::vector<std::unique_ptr<libcamera::Request>> requests_;
  std::map<int, std::pair<std::uint8_t*, std::size_t>> mappings_;
  std::vector<std::span<const std::uint8_t>> planes_;  // first plane of each buffer
  PixelFormat packed_ = PixelFormat::kGrey;
  std::size_t stride_ = 0;
  bool acquired_ = false;
  bool running_ = false;
  std::uint64_t seq_offset_ = 0;     // added to libcamera's sequence (restarts at start())
  std::uint64_t next_seq_ = 0;       // one past the last sequence number handed out
  bool frame_rate_control_ = false;  // the camera has FrameDurationLimits (fps is applied)
  bool connected_ = false;           // requestCompleted is connected to on_request_completed
  platform::SpscRing<std::uint32_t, kCompletedRing> completed_;  // libcamera -> acquire()
  platform::Notifier completed_wake_;
  platform::SpscRing<std::uint32_t, kCompletedRing> returned_;  // acquire() -> requeue thread
  platform::Notifier returned_wake_;
  platform::RtThread requeue_thread_;
  std::atomic<bool> requeue_stop_{false};
  std::atomic<int> requeue_error_{0};  // errno of a failed queueRequest, 0 if none
  std::uint64_t frame_errors_ = 0;
  std::uint64_t ring_overflows_ = 0;
  CameraIntrinsics intrinsics_;
  std::unique_ptr<FramePool> pool_;
  std::string description_;
  Status last_error_;
};

}  // namespace

bool libcamera_backend_built() {
  return true;
}

Result<std::unique_ptr<CameraSource>> make_libcamera_camera(const std::string& id,
                                                            const LibcameraOptions& opts) {
  return std::unique_ptr<CameraSource>(std::make_unique<LibcameraCamera>(id, opts));
}

}  // namespace mer::hal
