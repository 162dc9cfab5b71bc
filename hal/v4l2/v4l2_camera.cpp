#include "hal/v4l2/v4l2_camera.h"

#include <fcntl.h>
#include <linux/videodev2.h>
#include <poll.h>
#include <sys/ioctl.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <ctime>
#include <numbers>
#include <thread>

#include "hal/v4l2/v4l2_util.h"
#include "platform/clock.h"
#include "platform/log_ring.h"

namespace mer::hal {
namespace {

constexpr std::int64_t kNsPerS = 1'000'000'000;
constexpr std::int64_t kNsPerUs = 1'000;
constexpr std::int64_t kNsPerMs = 1'000'000;
constexpr double kFpsTolerance = 0.01;           // relative: 29.97 vs 30 is "30"
constexpr std::uint32_t kFpsScale = 1000;        // timeperframe = kFpsScale / (fps * kFpsScale)
constexpr std::uint32_t kMaxEnumEntries = 256;   // bound on ENUM_* loops (buggy drivers)
constexpr std::uint32_t kMaxSeqJump = 1U << 31;  // larger "gaps" are a sequence reset
constexpr std::size_t kNumberTextSize = 32;      // buffer for one formatted number
constexpr double kRadPerDeg = std::numbers::pi / 180.0;

// Preference of pixel_format: auto (cheapest conversion first).
constexpr std::array<PixelFormat, 3> kAutoOrder{PixelFormat::kGrey, PixelFormat::kNv12,
                                                PixelFormat::kYuyv};

std::uint32_t fourcc_of(PixelFormat f) {
  switch (f) {
    case PixelFormat::kGrey:
      return V4L2_PIX_FMT_GREY;
    case PixelFormat::kYuyv:
      return V4L2_PIX_FMT_YUYV;
    case PixelFormat::kNv12:
      return V4L2_PIX_FMT_NV12;
    case PixelFormat::kRgb888:  // packed RGB: libcamera only (not offered in v4l2 options)
    case PixelFormat::kBgr888:
    case PixelFormat::kXrgb8888:
      break;
  }
  return 0;
}

bool fps_matches(double a, double b) {
  return std::abs(a - b) <= kFpsTolerance * b;
}

double fps_of(const v4l2_fract& interval) {
  return interval.numerator == 0 ? 0.0
                                 : static_cast<double>(interval.denominator) / interval.numerator;
}

std::string fps_text(double fps) {
  char buf[kNumberTextSize];
  std::snprintf(buf, sizeof buf, "%.4g", fps);
  return buf;
}

std::string size_text(std::uint32_t w, std::uint32_t h) {
  return std::to_string(w) + "x" + std::to_string(h);
}

}  // namespace

V4l2Camera::V4l2Camera(std::string device, const V4l2Options& opts)
    : device_(std::move(device)), opts_(opts) {}

V4l2Camera::~V4l2Camera() {
  close_device();
}

Status V4l2Camera::errno_error(const char* call, int err) const {
  std::string msg = "v4l2:" + device_ + ": " + call + " failed: " + errno_text(err);
  switch (err) {
    case EBUSY:
      msg += ": the device is busy (in use by another program)";
      break;
    case ENODEV:
      msg += ": the device is gone (disconnected)";
      break;
    case EIO:
      msg += ": the driver reported a fatal I/O error";
      break;
    case EACCES:
    case EPERM:
      msg += ": permission denied (is the user in the 'video' group?)";
      break;
    default:
      break;
  }
  return input_error(std::move(msg));
}

Status V4l2Camera::open(std::size_t pool_size) {
  if (Status s = options::validate(opts_); !s.is_ok()) {
    return invalid_argument("v4l2:" + device_ + ": " + s.message());
  }
  if (pool_size == 0) return invalid_argument("v4l2:" + device_ + ": pool size must be > 0");
  close_device();
  state_ = State::kClosed;
  stats_ = {};
  ever_seq_ = false;
  timestamp_checked_ = false;
  if (Status s = open_device(); !s.is_ok()) {
    close_device();
    return s;
  }
  const int w = layout_.width;
  const int h = layout_.height;
  const double f = 0.5 * w / std::tan(0.5 * opts_.hfov_deg * kRadPerDeg);
  intrinsics_ = CameraIntrinsics{w, h, f, f, 0.5 * (w - 1), 0.5 * (h - 1), {}, false};
  // Re-opening with the same geometry keeps the pool (and any frames still held downstream).
  if (!pool_ || pool_->capacity() != pool_size || pool_->slot(0).gray.cols != w ||
      pool_->slot(0).gray.rows != h) {
    if (pool_ && pool_->available_approx() != pool_->capacity()) {
      close_device();
      return invalid_argument("v4l2:" + device_ +
                              ": cannot re-open with a new geometry while frames of the old one "
                              "are still held downstream");
    }
    pool_ = std::make_unique<FramePool>(
        pool_size, [w, h](Frame& fr, std::size_t) { fr.gray = cv::Mat(h, w, CV_8UC1); });
  }
  state_ = State::kOpen;
  MER_LOG_INFO("%s", describe().c_str());
  return Status::ok();
}

Status V4l2Camera::open_device() {
  fd_ = ::open(device_.c_str(), O_RDWR | O_NONBLOCK | O_CLOEXEC);
  if (fd_ < 0) {
    const int err = errno;
    if (err == ENOENT) {
      return input_error("v4l2:" + device_ + ": cannot open: " + errno_text(err) +
                         ": no such device node");
    }
    return errno_error("open", err);
  }
  struct stat st {};
  if (::fstat(fd_, &st) != 0) return errno_error("fstat", errno);
  if (!S_ISCHR(st.st_mode)) {
    return input_error("v4l2:" + device_ + ": not a V4L2 device (not a character device)");
  }
  v4l2_capability cap{};
  if (xioctl(fd_, VIDIOC_QUERYCAP, &cap) != 0) {
    const int err = errno;
    if (err == ENOTTY || err == EINVAL) {
      return input_error("v4l2:" + device_ +
                         ": not a V4L2 device (VIDIOC_QUERYCAP failed: " + errno_text(err) + ")");
    }
    return errno_error("VIDIOC_QUERYCAP", err);
  }
  card_ = c_string(cap.card, sizeof cap.card);
  const std::uint32_t caps =
      (cap.capabilities & V4L2_CAP_DEVICE_CAPS) != 0 ? cap.device_caps : cap.capabilities;
  if ((caps & V4L2_CAP_VIDEO_CAPTURE) == 0) {
    return input_error(
        "v4l2:" + device_ + " ('" + card_ + "', driver " + c_string(cap.driver, sizeof cap.driver) +
        "): not a video capture device" +
        ((caps & V4L2_CAP_VIDEO_CAPTURE_MPLANE) != 0 ? " (multi-planar only; not supported)" : ""));
  }
  if ((caps & V4L2_CAP_STREAMING) == 0) {
    return input_error("v4l2:" + device_ + " ('" + card_ +
                       "'): no streaming I/O (V4L2_CAP_STREAMING missing; read() I/O is not "
                       "supported)");
  }
  if (Status s = select_format(); !s.is_ok()) return s;
  if (Status s = select_rate(); !s.is_ok()) return s;
  return map_buffers();
}

Status V4l2Camera::select_format() {
  // Formats offered for single-planar capture.
  std::string offered;
  std::array<bool, kAutoOrder.size()> has{};
  for (std::uint32_t i = 0; i < kMaxEnumEntries; ++i) {
    v4l2_fmtdesc d{};
    d.index = i;
    d.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    if (xioctl(fd_, VIDIOC_ENUM_FMT, &d) != 0) {
      if (errno == EINVAL) break;
      return errno_error("VIDIOC_ENUM_FMT", errno);
    }
    offered += (offered.empty() ? "" : ", ") + fourcc_text(d.pixelformat);
    for (std::size_t k = 0; k < kAutoOrder.size(); ++k) {
      if (d.pixelformat == fourcc_of(kAutoOrder[k])) has[k] = true;
    }
  }
  auto offers = [&](PixelFormat f) {
    for (std::size_t k = 0; k < kAutoOrder.size(); ++k) {
      if (kAutoOrder[k] == f) return has[k];
    }
    return false;
  };
  if (opts_.pixel_format == "auto") {
    auto it = std::find_if(kAutoOrder.begin(), kAutoOrder.end(), offers);
    if (it == kAutoOrder.end()) {
      return input_error("v4l2:" + device_ + ": offers none of GREY, NV12, YUYV (offered: " +
                         (offered.empty() ? "none" : offered) + ")");
    }
    format_ = *it;
  } else {
    const auto f = parse_pixel_format(opts_.pixel_format);
    if (!f) return invalid_argument("v4l2: unknown pixel_format '" + opts_.pixel_format + "'");
    if (!offers(*f)) {
      return input_error("v4l2:" + device_ + ": pixel format " + opts_.pixel_format +
                         " not offered (offered: " + (offered.empty() ? "none" : offered) + ")");
    }
    format_ = *f;
  }
  const std::uint32_t fourcc = fourcc_of(format_);
  const auto want_w = static_cast<std::uint32_t>(opts_.width);
  const auto want_h = static_cast<std::uint32_t>(opts_.height);

  // Frame sizes (drivers without ENUM_FRAMESIZES are checked by S_FMT alone).
  v4l2_frmsizeenum fs{};
  fs.index = 0;
  fs.pixel_format = fourcc;
  if (xioctl(fd_, VIDIOC_ENUM_FRAMESIZES, &fs) == 0) {
    bool ok = false;
    std::string sizes;
    if (fs.type == V4L2_FRMSIZE_TYPE_DISCRETE) {
      for (std::uint32_t i = 0; i < kMaxEnumEntries; ++i) {
        fs.index = i;
        if (xioctl(fd_, VIDIOC_ENUM_FRAMESIZES, &fs) != 0) break;
        sizes += (sizes.empty() ? "" : ", ") + size_text(fs.discrete.width, fs.discrete.height);
        ok = ok || (fs.discrete.width == want_w && fs.discrete.height == want_h);
      }
    } else {
      const auto& s = fs.stepwise;
      const std::uint32_t sx = std::max<std::uint32_t>(s.step_width, 1);
      const std::uint32_t sy = std::max<std::uint32_t>(s.step_height, 1);
      ok = want_w >= s.min_width && want_w <= s.max_width && want_h >= s.min_height &&
           want_h <= s.max_height && (want_w - s.min_width) % sx == 0 &&
           (want_h - s.min_height) % sy == 0;
      sizes = size_text(s.min_width, s.min_height) + " to " + size_text(s.max_width, s.max_height) +
              " in steps of " + size_text(sx, sy);
    }
    if (!ok) {
      return input_error("v4l2:" + device_ + ": size " + size_text(want_w, want_h) +
                         " not offered for " + std::string(pixel_format_name(format_)) +
                         " (offered: " + sizes + ")");
    }
  }

  v4l2_format fmt{};
  fmt.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
  fmt.fmt.pix.width = want_w;
  fmt.fmt.pix.height = want_h;
  fmt.fmt.pix.pixelformat = fourcc;
  fmt.fmt.pix.field = V4L2_FIELD_NONE;
  if (xioctl(fd_, VIDIOC_S_FMT, &fmt) != 0) return errno_error("VIDIOC_S_FMT", errno);
  const auto& pix = fmt.fmt.pix;
  if (pix.pixelformat != fourcc || pix.width != want_w || pix.height != want_h) {
    return input_error("v4l2:" + device_ + ": VIDIOC_S_FMT set " +
                       size_text(pix.width, pix.height) + " " + fourcc_text(pix.pixelformat) +
                       " instead of " + size_text(want_w, want_h) + " " +
                       std::string(pixel_format_name(format_)));
  }
  layout_.width = static_cast<int>(pix.width);
  layout_.height = static_cast<int>(pix.height);
  // Some drivers leave bytesperline 0: rows are then unpadded.
  const int min_bpl = min_bytes_per_line(format_, layout_.width);
  layout_.bytes_per_line = std::max(static_cast<int>(pix.bytesperline), min_bpl);
  if (pix.sizeimage != 0 && pix.sizeimage < min_bytes_for_gray(format_, layout_)) {
    return input_error("v4l2:" + device_ + ": driver image size " + std::to_string(pix.sizeimage) +
                       " bytes is too small for " + size_text(pix.width, pix.height) + " " +
                       std::string(pixel_format_name(format_)));
  }
  return Status::ok();
}

Status V4l2Camera::select_rate() {
  const double want = opts_.fps;
  v4l2_frmivalenum fi{};
  fi.index = 0;
  fi.pixel_format = fourcc_of(format_);
  fi.width = static_cast<std::uint32_t>(layout_.width);
  fi.height = static_cast<std::uint32_t>(layout_.height);
  if (xioctl(fd_, VIDIOC_ENUM_FRAMEINTERVALS, &fi) == 0) {
    bool ok = false;
    std::string rates;
    if (fi.type == V4L2_FRMIVAL_TYPE_DISCRETE) {
      for (std::uint32_t i = 0; i < kMaxEnumEntries; ++i) {
        fi.index = i;
        if (xioctl(fd_, VIDIOC_ENUM_FRAMEINTERVALS, &fi) != 0) break;
        const double r = fps_of(fi.discrete);
        rates += (rates.empty() ? "" : ", ") + fps_text(r);
        ok = ok || fps_matches(r, want);
      }
    } else {
      // Longest interval = lowest rate.
      const double lo = fps_of(fi.stepwise.max);
      const double hi = fps_of(fi.stepwise.min);
      ok = want >= lo * (1.0 - kFpsTolerance) && want <= hi * (1.0 + kFpsTolerance);
      rates = fps_text(lo) + " to " + fps_text(hi);
    }
    if (!ok) {
      return input_error("v4l2:" + device_ + ": " + fps_text(want) + " fps not offered at " +
                         size_text(fi.width, fi.height) + " " +
                         std::string(pixel_format_name(format_)) + " (offered: " + rates + " fps)");
    }
  }

  v4l2_streamparm parm{};
  parm.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
  if (xioctl(fd_, VIDIOC_G_PARM, &parm) != 0 ||
      (parm.parm.capture.capability & V4L2_CAP_TIMEPERFRAME) == 0) {
    fps_ = 0.0;
    MER_LOG_WARN("v4l2:%s: the driver cannot set the frame rate (no V4L2_CAP_TIMEPERFRAME)",
                 device_.c_str());
    return Status::ok();
  }
  parm = {};
  parm.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
  parm.parm.capture.timeperframe.numerator = kFpsScale;
  parm.parm.capture.timeperframe.denominator =
      static_cast<std::uint32_t>(std::lround(want * kFpsScale));
  if (xioctl(fd_, VIDIOC_S_PARM, &parm) != 0) return errno_error("VIDIOC_S_PARM", errno);
  fps_ = fps_of(parm.parm.capture.timeperframe);
  if (!fps_matches(fps_, want)) {
    return input_error("v4l2:" + device_ + ": VIDIOC_S_PARM set " + fps_text(fps_) +
                       " fps instead of " + fps_text(want));
  }
  return Status::ok();
}

Status V4l2Camera::map_buffers() {
  v4l2_requestbuffers req{};
  req.count = static_cast<std::uint32_t>(opts_.buffers);
  req.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
  req.memory = V4L2_MEMORY_MMAP;
  if (xioctl(fd_, VIDIOC_REQBUFS, &req) != 0) return errno_error("VIDIOC_REQBUFS", errno);
  if (req.count < static_cast<std::uint32_t>(kV4l2MinBuffers) ||
      req.count > static_cast<std::uint32_t>(kV4l2MaxBuffers)) {
    return input_error("v4l2:" + device_ + ": VIDIOC_REQBUFS granted " + std::to_string(req.count) +
                       " buffers (need " + std::to_string(kV4l2MinBuffers) + " to " +
                       std::to_string(kV4l2MaxBuffers) + ")");
  }
  const std::size_t need = min_bytes_for_gray(format_, layout_);
  for (std::uint32_t i = 0; i < req.count; ++i) {
    v4l2_buffer b{};
    b.index = i;
    b.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    b.memory = V4L2_MEMORY_MMAP;
    if (xioctl(fd_, VIDIOC_QUERYBUF, &b) != 0) return errno_error("VIDIOC_QUERYBUF", errno);
    if (b.length < need) {
      return input_error("v4l2:" + device_ + ": buffer " + std::to_string(i) + " holds " +
                         std::to_string(b.length) + " bytes, the format needs " +
                         std::to_string(need));
    }
    void* p = ::mmap(nullptr, b.length, PROT_READ | PROT_WRITE, MAP_SHARED, fd_, b.m.offset);
    if (p == MAP_FAILED) return errno_error("mmap", errno);
    buffers_[i] = MappedBuffer{p, b.length};
    buffer_count_ = i + 1;
  }
  return Status::ok();
}

Status V4l2Camera::start() {
  if (state_ == State::kStreaming) return Status::ok();
  if (fd_ < 0 || (state_ != State::kOpen && state_ != State::kStopped)) {
    return runtime_error(
        "v4l2:" + device_ + ": start() needs an opened, stopped camera" +
        (state_ == State::kFailed ? " (it failed: " + last_error_.message() + ")" : std::string()));
  }
  if (Status s = start_streaming(); !s.is_ok()) {
    // Take the buffers back so a later start() begins from a clean queue.
    int type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    static_cast<void>(xioctl(fd_, VIDIOC_STREAMOFF, &type));
    last_error_ = s;
    return s;
  }
  state_ = State::kStreaming;
  return Status::ok();
}

Status V4l2Camera::start_streaming() {
  for (std::uint32_t i = 0; i < buffer_count_; ++i) {
    v4l2_buffer b{};
    b.index = i;
    b.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    b.memory = V4L2_MEMORY_MMAP;
    if (xioctl(fd_, VIDIOC_QBUF, &b) != 0) return errno_error("VIDIOC_QBUF", errno);
  }
  int type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
  if (xioctl(fd_, VIDIOC_STREAMON, &type) != 0) return errno_error("VIDIOC_STREAMON", errno);
  // A new stream restarts the driver's sequence at its own origin (track_sequence()).
  have_seq_ = false;
  last_progress_ns_ = platform::monotonic_now_ns();
  return Status::ok();
}

void V4l2Camera::stop() {
  if (state_ == State::kStreaming) {
    int type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    if (xioctl(fd_, VIDIOC_STREAMOFF, &type) != 0) {
      MER_LOG_WARN("v4l2:%s: VIDIOC_STREAMOFF failed: %s", device_.c_str(),
                   errno_text(errno).c_str());
    }
    state_ = State::kStopped;
  } else if (state_ == State::kRecovering || state_ == State::kFailed) {
    state_ = State::kStopped;  // the device is already closed; last_error() keeps why
  }
}

void V4l2Camera::close_device() noexcept {
  if (fd_ >= 0) {
    int type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    static_cast<void>(xioctl(fd_, VIDIOC_STREAMOFF, &type));
  }
  for (std::uint32_t i = 0; i < buffer_count_; ++i) {
    if (buffers_[i].data != nullptr) ::munmap(buffers_[i].data, buffers_[i].length);
    buffers_[i] = {};
  }
  buffer_count_ = 0;
  if (fd_ >= 0) {
    // Free the driver's buffers (needs the mappings gone); harmless if the device is gone.
    v4l2_requestbuffers req{};
    req.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    req.memory = V4L2_MEMORY_MMAP;
    static_cast<void>(xioctl(fd_, VIDIOC_REQBUFS, &req));
    ::close(fd_);
    fd_ = -1;
  }
}

CameraCapabilities V4l2Camera::capabilities() const {
  return CameraCapabilities{true, false, false, fps_};
}

std::string V4l2Camera::describe() const {
  std::string d = "v4l2:" + device_;
  if (layout_.width > 0) {
    d += " (" + (card_.empty() ? std::string() : "'" + card_ + "', ") +
         size_text(static_cast<std::uint32_t>(layout_.width),
                   static_cast<std::uint32_t>(layout_.height)) +
         " " + std::string(pixel_format_name(format_)) + " @ " + fps_text(fps_) + " Hz, " +
         std::to_string(buffer_count_) + " buffers)";
  }
  return d;
}

std::uint64_t V4l2Camera::track_sequence(std::uint32_t driver_seq) noexcept {
  if (!have_seq_) {
    // First buffer of a stream: continue after the previous stream's last number.
    seq_ = (ever_seq_ ? seq_ + 1 : 0) + driver_seq;
    have_seq_ = true;
    ever_seq_ = true;
  } else {
    std::uint32_t delta = driver_seq - last_driver_seq_;  // modulo 2^32: survives wrap-around
    if (delta == 0 || delta >= kMaxSeqJump) delta = 1;    // repeated or backwards: no gap known
    stats_.sequence_gaps += delta - 1;
    seq_ += delta;
  }
  last_driver_seq_ = driver_seq;
  return seq_;
}

bool V4l2Camera::requeue(std::uint32_t index, Status& error) {
  v4l2_buffer b{};
  b.index = index;
  b.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
  b.memory = V4L2_MEMORY_MMAP;
  if (xioctl(fd_, VIDIOC_QBUF, &b) == 0) return true;
  error = errno_error("VIDIOC_QBUF", errno);
  return false;
}

AcquireStatus V4l2Camera::stream_error(Status error) {
  ++stats_.stream_errors;
  close_device();
  const bool retry = opts_.on_error == "retry" && opts_.max_retries > 0;
  MER_LOG_ERROR("%s%s", error.message().c_str(),
                retry ? " (on_error: retry: closing and reopening)" : " (on_error: stop)");
  last_error_ = runtime_error(error.message());
  if (retry) {
    first_stream_error_ = last_error_;
    recover_attempts_ = 0;
    next_attempt_ns_ = platform::monotonic_now_ns() + opts_.retry_delay_ms * kNsPerMs;
    state_ = State::kRecovering;
    return AcquireStatus::kTimeout;
  }
  state_ = State::kFailed;
  return AcquireStatus::kError;
}

AcquireStatus V4l2Camera::recover(std::int64_t timeout_ns) {
  const std::int64_t now = platform::monotonic_now_ns();
  if (now < next_attempt_ns_) {
    const std::int64_t wait =
        std::min(next_attempt_ns_ - now, std::max<std::int64_t>(timeout_ns, 0));
    std::this_thread::sleep_for(std::chrono::nanoseconds(wait));
    if (platform::monotonic_now_ns() < next_attempt_ns_) return AcquireStatus::kTimeout;
  }
  ++recover_attempts_;
  Status s = open_device();
  if (s.is_ok()) s = start_streaming();
  if (s.is_ok()) {
    ++stats_.restarts;
    state_ = State::kStreaming;
    MER_LOG_WARN("v4l2:%s: reopened and restarted after: %s", device_.c_str(),
                 first_stream_error_.message().c_str());
    return AcquireStatus::kFrame;  // streaming again: the caller goes on to dequeue
  }
  ++stats_.reopen_failures;
  close_device();
  MER_LOG_WARN("v4l2:%s: reopen attempt %d/%d failed: %s", device_.c_str(), recover_attempts_,
               opts_.max_retries, s.message().c_str());
  if (recover_attempts_ >= opts_.max_retries) {
    state_ = State::kFailed;
    last_error_ = runtime_error(first_stream_error_.message() + "; gave up after " +
                                std::to_string(recover_attempts_) +
                                " reopen attempts (on_error: retry), last: " + s.message());
    MER_LOG_ERROR("%s", last_error_.message().c_str());
    return AcquireStatus::kError;
  }
  next_attempt_ns_ = platform::monotonic_now_ns() + opts_.retry_delay_ms * kNsPerMs;
  return AcquireStatus::kTimeout;
}

AcquireStatus V4l2Camera::acquire(FrameHandle& out, std::int64_t timeout_ns) {
  switch (state_) {
    case State::kStreaming:
      break;
    case State::kRecovering:
      if (AcquireStatus st = recover(timeout_ns); st != AcquireStatus::kFrame) return st;
      break;
    case State::kFailed:
      return AcquireStatus::kError;
    case State::kClosed:
    case State::kOpen:
    case State::kStopped:
      return AcquireStatus::kEndOfStream;
  }
  FrameHandle h = pool_->acquire();
  if (!h) return AcquireStatus::kPoolEmpty;

  const std::int64_t deadline = platform::saturating_add_ns(platform::monotonic_now_ns(),
                                                            std::max<std::int64_t>(timeout_ns, 0));
  for (;;) {
    std::int64_t now = platform::monotonic_now_ns();
    const std::int64_t remaining = std::max<std::int64_t>(deadline - now, 0);
    pollfd pfd{fd_, POLLIN, 0};
    const timespec ts{static_cast<time_t>(remaining / kNsPerS),
                      static_cast<long>(remaining % kNsPerS)};
    const int r = ::ppoll(&pfd, 1, &ts, nullptr);
    if (r < 0) {
      if (errno == EINTR) continue;
      return stream_error(errno_error("poll", errno));
    }
    now = platform::monotonic_now_ns();
    if (r == 0) {
      if (now - last_progress_ns_ > opts_.dequeue_timeout_ms * kNsPerMs) {
        return stream_error(input_error(
            "v4l2:" + device_ + ": no frame for " +
            std::to_string((now - last_progress_ns_) / kNsPerMs) + " ms (dequeue_timeout_ms " +
            std::to_string(opts_.dequeue_timeout_ms) + "): the device stalled"));
      }
      return AcquireStatus::kTimeout;
    }
    // Dequeue even on POLLERR: DQBUF says why (EIO: queue error, ENODEV: disconnected).
    v4l2_buffer b{};
    b.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    b.memory = V4L2_MEMORY_MMAP;
    if (xioctl(fd_, VIDIOC_DQBUF, &b) != 0) {
      const int err = errno;
      if (err == EAGAIN) {
        if ((pfd.revents & (POLLERR | POLLHUP | POLLNVAL)) != 0) {
          return stream_error(input_error("v4l2:" + device_ +
                                          ": poll reported an error (POLLERR/POLLHUP): device "
                                          "failed or disconnected"));
        }
        if (now >= deadline) return AcquireStatus::kTimeout;
        continue;  // spurious wake-up
      }
      return stream_error(errno_error("VIDIOC_DQBUF", err));
    }
    const std::int64_t t_dq = platform::monotonic_now_ns();
    const std::int64_t cpu_dq = platform::thread_cpu_ns();
    last_progress_ns_ = t_dq;
    if (b.index >= buffer_count_) {
      return stream_error(input_error("v4l2:" + device_ + ": VIDIOC_DQBUF returned buffer index " +
                                      std::to_string(b.index) + " of " +
                                      std::to_string(buffer_count_)));
    }
    const std::uint64_t seq = track_sequence(b.sequence);
    Status qerr;
    if ((b.flags & V4L2_BUF_FLAG_ERROR) != 0) {
      ++stats_.error_frames;
      MER_LOG_WARN("v4l2:%s: buffer %u (sequence %u) flagged V4L2_BUF_FLAG_ERROR: dropped",
                   device_.c_str(), b.index, b.sequence);
      if (!requeue(b.index, qerr)) return stream_error(qerr);
      if (t_dq >= deadline) return AcquireStatus::kTimeout;
      continue;
    }
    const MappedBuffer& mb = buffers_[b.index];
    const std::size_t used = std::min<std::size_t>(b.bytesused, mb.length);
    Frame& f = *h;
    if (!convert_to_gray(
            format_, std::span<const std::uint8_t>(static_cast<const std::uint8_t*>(mb.data), used),
            layout_, f.gray)) {
      ++stats_.short_frames;
      MER_LOG_WARN("v4l2:%s: buffer %u (sequence %u) has %u bytes, the format needs %zu: dropped",
                   device_.c_str(), b.index, b.sequence, b.bytesused,
                   min_bytes_for_gray(format_, layout_));
      if (!requeue(b.index, qerr)) return stream_error(qerr);
      if (t_dq >= deadline) return AcquireStatus::kTimeout;
      continue;
    }
    if (!requeue(b.index, qerr)) return stream_error(qerr);

    if (!timestamp_checked_) {
      timestamp_checked_ = true;
      driver_timestamps_ =
          (b.flags & V4L2_BUF_FLAG_TIMESTAMP_MASK) == V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC;
      if (!driver_timestamps_) {
        MER_LOG_WARN(
            "v4l2:%s: driver timestamps are not on the monotonic clock; frames are "
            "stamped at dequeue",
            device_.c_str());
      }
    }
    const std::int64_t t_driver =
        static_cast<std::int64_t>(b.timestamp.tv_sec) * kNsPerS + b.timestamp.tv_usec * kNsPerUs;
    f.seq = seq;
    f.t_ns = driver_timestamps_ && t_driver > 0 ? t_driver : t_dq;
    f.has_ground_truth = false;
    f.t_ready_ns = platform::monotonic_now_ns();
    f.produce_ns = f.t_ready_ns - t_dq;
    f.produce_cpu_ns = platform::thread_cpu_ns() - cpu_dq;
    ++stats_.frames;
    recover_attempts_ = 0;
    out = std::move(h);
    return AcquireStatus::kFrame;
  }
}

Result<std::unique_ptr<CameraSource>> make_v4l2_camera(const std::string& device,
                                                       const V4l2Options& opts) {
  if (device.empty())
    return invalid_argument("v4l2: empty device path (expected v4l2:/dev/videoN)");
  V4l2Options o = opts;
  if (Status s = options::validate(o); !s.is_ok()) {
    return invalid_argument("v4l2:" + device + ": " + s.message());
  }
  return std::unique_ptr<CameraSource>(std::make_unique<V4l2Camera>(device, opts));
}

}  // namespace mer::hal
