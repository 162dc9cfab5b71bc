// mer_hw_v4l2_vivid: the V4L2 backend (hal/v4l2, the project's own V4l2Camera) against
// the kernel's vivid virtual camera. Runs inside a qemu VM booted from a stock Debian
// kernel (tools/hw/vivid_vm.sh, CTest label 'hw'); vivid is loaded with two instances
// that have only a video-capture node each (n_devs=2 node_types=0x1,0x1).
//
// Prints one line per check, "MER_HW_CHECK PASS|FAIL <name>: <detail>", and exits 1 when
// any check failed. Faults are injected with vivid's controls, found by name through
// VIDIOC_QUERY_EXT_CTRL (hal/v4l2/v4l2_controls.h).
#include <fcntl.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <functional>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include <opencv2/core.hpp>

#include "hal/v4l2/v4l2_camera.h"
#include "hal/v4l2/v4l2_controls.h"
#include "hw_check.h"
#include "platform/alloc_counter.h"
#include "platform/clock.h"
#include "platform/log_ring.h"

namespace {

using mer::Status;
using mer::hal::AcquireStatus;
using mer::hal::FrameHandle;
using mer::hal::V4l2Camera;
using mer::hal::V4l2Control;
using mer::hal::V4l2Options;

constexpr int kWidth = 640;
constexpr int kHeight = 480;
constexpr double kFps = 25.0;         // vivid's webcam input offers 25 fps at 640x480
constexpr int kFramesPerFormat = 30;  // frames captured per pixel format
constexpr int kWarmupFrames = 3;      // not counted in the allocation check
constexpr std::size_t kPoolSize = 4;  // frame pool of each camera
constexpr std::int64_t kAcquireTimeoutNs = 500'000'000;
constexpr std::int64_t kNsPerMs = 1'000'000;
constexpr double kNsPerS = 1e9;
constexpr std::int64_t kMaxClockSkewNs = 1'000'000'000;  // |driver stamp - frame ready|
constexpr std::size_t kMaxProblems = 5;                  // problems listed per check
constexpr double kPeriodTolerance = 0.15;                // relative, on the driver's frame period
constexpr double kMinStdDev = 10.0;                      // colour bars: far from a constant image
constexpr double kMaxMeanDiff = 8.0;  // gray of GREY vs YUYV vs NV12 of the same scene
constexpr std::int64_t kFaultDeadlineNs = 5'000'000'000;  // a fault must be reported by then
constexpr int kDropPercent = 50;                          // vivid "Percentage of Dropped Buffers"
constexpr int kDropFrames = 20;                           // frames captured while dropping
constexpr int kRetryDelayMs = 100;
constexpr int kRetries = 2;

using mer::hw::contains;
using mer::hw::fmt;
using mer::hw::report;

V4l2Options options_for(const std::string& pixel_format) {
  V4l2Options o;
  o.width = kWidth;
  o.height = kHeight;
  o.fps = kFps;
  o.pixel_format = pixel_format;
  return o;
}

// Capture nodes of the vivid instances, by their sysfs names (vivid-000-vid-cap, ...).
std::vector<std::string> find_vivid_capture_nodes() {
  std::vector<std::pair<std::string, std::string>> found;  // (name, /dev path)
  const std::filesystem::path cls = "/sys/class/video4linux";
  std::error_code ec;
  for (const auto& e : std::filesystem::directory_iterator(cls, ec)) {
    std::ifstream f(e.path() / "name");
    std::string name;
    std::getline(f, name);
    if (contains(name, "vivid") && contains(name, "vid-cap")) {
      found.emplace_back(name, "/dev/" + e.path().filename().string());
    }
  }
  std::sort(found.begin(), found.end());
  std::vector<std::string> nodes;
  for (const auto& [name, path] : found) nodes.push_back(path);
  return nodes;
}

// Acquires until a frame arrives or `deadline_ns` passes; returns the last status.
AcquireStatus acquire_until(V4l2Camera& cam, FrameHandle& h, std::int64_t deadline_ns,
                            int* timeouts = nullptr) {
  for (;;) {
    const AcquireStatus st = cam.acquire(h, kAcquireTimeoutNs);
    if (st != AcquireStatus::kTimeout) return st;
    if (timeouts != nullptr) ++*timeouts;
    if (mer::platform::monotonic_now_ns() > deadline_ns) return st;
  }
}

// Captures `n` frames, returning how many arrived (stops at the first non-frame status).
int capture(V4l2Camera& cam, int n, AcquireStatus* last = nullptr) {
  int got = 0;
  for (int i = 0; i < n; ++i) {
    FrameHandle h;
    const AcquireStatus st =
        acquire_until(cam, h, mer::platform::monotonic_now_ns() + kFaultDeadlineNs);
    if (last != nullptr) *last = st;
    if (st != AcquireStatus::kFrame) break;
    ++got;
  }
  return got;
}

// ---- checks ------------------------------------------------------------------------------

struct FormatResult {
  bool ok = false;
  double mean = 0.0;
};

FormatResult check_format(const std::string& dev, const std::string& format) {
  const std::string name = "capture_" + format;
  V4l2Camera cam(dev, options_for(format));
  if (Status s = cam.open(kPoolSize); !s.is_ok()) {
    report(false, name, s.message());
    return {};
  }
  if (Status s = cam.start(); !s.is_ok()) {
    report(false, name, s.message());
    return {};
  }
  std::vector<std::string> problems;
  std::uint64_t prev_seq = 0;
  std::int64_t prev_t = 0;
  std::uint64_t first_seq = 0;
  std::int64_t first_t = 0;
  std::uint64_t allocs = 0;
  double mean0 = 0.0;
  double min_std = 1e9;
  int frames = 0;
  const std::int64_t t0 = mer::platform::monotonic_now_ns();
  for (int i = 0; i < kFramesPerFormat; ++i) {
    FrameHandle h;
    const std::uint64_t a0 = mer::platform::alloc::thread_allocations();
    const AcquireStatus st =
        acquire_until(cam, h, mer::platform::monotonic_now_ns() + kFaultDeadlineNs);
    const std::uint64_t a1 = mer::platform::alloc::thread_allocations();
    if (st != AcquireStatus::kFrame) {
      problems.push_back("frame " + std::to_string(i) + ": acquire status " +
                         std::to_string(static_cast<int>(st)) + " " + cam.last_error().message());
      break;
    }
    if (i >= kWarmupFrames) allocs += a1 - a0;
    const auto& f = *h;
    if (i == 0) {
      first_seq = f.seq;
      first_t = f.t_ns;
    } else {
      if (f.seq <= prev_seq)
        problems.push_back("sequence not increasing at frame " + std::to_string(i));
      if (f.t_ns <= prev_t)
        problems.push_back("timestamp not increasing at frame " + std::to_string(i));
    }
    // Same clock as monotonic_now_ns(): vivid stamps the nominal end of frame, which may
    // lie a few ms after the dequeue, so only the distance is checked.
    if (std::abs(f.t_ready_ns - f.t_ns) > kMaxClockSkewNs && problems.size() < kMaxProblems) {
      problems.push_back("timestamp not on the monotonic clock: t_ns " + std::to_string(f.t_ns) +
                         " ready " + std::to_string(f.t_ready_ns));
    }
    cv::Scalar mean;
    cv::Scalar stddev;
    cv::meanStdDev(f.gray, mean, stddev);
    if (i == 0) mean0 = mean[0];
    min_std = std::min(min_std, stddev[0]);
    if (f.gray.rows != kHeight || f.gray.cols != kWidth || f.gray.type() != CV_8UC1) {
      problems.push_back("wrong image geometry");
    }
    prev_seq = f.seq;
    prev_t = f.t_ns;
    ++frames;
  }
  const double wall_s = static_cast<double>(mer::platform::monotonic_now_ns() - t0) / kNsPerS;
  if (min_std < kMinStdDev)
    problems.push_back("image (nearly) constant: stddev " + fmt("%.1f", min_std));
  if (!cam.driver_timestamps()) problems.push_back("driver timestamps not monotonic");
  if (allocs != 0) problems.push_back(std::to_string(allocs) + " heap allocations in acquire()");
  if (cam.error_frames() != 0) problems.push_back("unexpected error frames");
  // The driver's frame period, per sequence number (robust to frames it skipped).
  double period_ms = 0.0;
  if (frames > 1 && prev_seq > first_seq) {
    period_ms = static_cast<double>(prev_t - first_t) / static_cast<double>(prev_seq - first_seq) /
                static_cast<double>(kNsPerMs);
    const double want_ms = 1000.0 / kFps;
    if (std::abs(period_ms - want_ms) > kPeriodTolerance * want_ms) {
      problems.push_back("frame period " + fmt("%.1f", period_ms) + " ms, expected " +
                         fmt("%.1f", want_ms) + " (S_PARM)");
    }
  }
  cam.stop();
  std::string detail = cam.describe() + ": " + std::to_string(frames) + " frames in " +
                       fmt("%.2f", wall_s) + " s, period " + fmt("%.1f", period_ms) +
                       " ms, seq gaps " + std::to_string(cam.sequence_gaps()) + ", min stddev " +
                       fmt("%.1f", min_std) + ", mean " + fmt("%.1f", mean0) +
                       ", allocs in acquire " + std::to_string(allocs);
  for (const auto& p : problems) detail += "; " + p;
  const bool ok = problems.empty() && frames == kFramesPerFormat;
  report(ok, name, detail);
  return {ok, mean0};
}

void check_unsupported(const std::string& dev) {
  {
    V4l2Options o = options_for("YUYV");
    o.width = kWidth + 10;
    V4l2Camera cam(dev, o);
    const Status s = cam.open(kPoolSize);
    report(!s.is_ok() && contains(s.message(), dev) && contains(s.message(), "650x480") &&
               contains(s.message(), "640x480"),
           "size_not_offered", s.is_ok() ? "open() succeeded" : s.message());
  }
  {
    V4l2Options o = options_for("YUYV");
    o.fps = 7.0;
    V4l2Camera cam(dev, o);
    const Status s = cam.open(kPoolSize);
    report(!s.is_ok() && contains(s.message(), "fps") && contains(s.message(), "25"),
           "rate_not_offered", s.is_ok() ? "open() succeeded" : s.message());
  }
  {
    V4l2Camera cam("/dev/video99", options_for("auto"));
    const Status s = cam.open(kPoolSize);
    report(!s.is_ok() && contains(s.message(), "/dev/video99"), "missing_device",
           s.is_ok() ? "open() succeeded" : s.message());
  }
}

void check_busy(const std::string& dev) {
  V4l2Camera a(dev, options_for("GREY"));
  if (Status s = a.open(kPoolSize); !s.is_ok() || !a.start().is_ok()) {
    report(false, "busy", "first camera failed: " + a.last_error().message() + " " + s.message());
    return;
  }
  V4l2Camera b(dev, options_for("GREY"));
  const Status s = b.open(kPoolSize);
  const int after = capture(a, kWarmupFrames);
  report(!s.is_ok() && contains(s.message(), "EBUSY") && contains(s.message(), dev) &&
             after == kWarmupFrames,
         "busy",
         (s.is_ok() ? std::string("second open() succeeded") : s.message()) +
             "; first camera still streams: " + std::to_string(after) + " frames");
}

void check_streamon_error(const std::string& dev, const V4l2Control& inject) {
  V4l2Camera cam(dev, options_for("YUYV"));
  if (Status s = cam.open(kPoolSize); !s.is_ok()) {
    report(false, "streamon_error", s.message());
    return;
  }
  if (Status s = mer::hal::set_v4l2_control(dev, inject, 1); !s.is_ok()) {
    report(false, "streamon_error", s.message());
    return;
  }
  const Status s = cam.start();
  const bool reported =
      !s.is_ok() && contains(s.message(), "VIDIOC_STREAMON") && contains(s.message(), dev);
  FrameHandle h;
  const AcquireStatus idle = cam.acquire(h, kAcquireTimeoutNs);
  // The injection is one-shot: a second start() must work from the cleaned-up queue.
  const Status again = cam.start();
  const int frames = again.is_ok() ? capture(cam, kWarmupFrames) : 0;
  report(
      reported && idle == AcquireStatus::kEndOfStream && again.is_ok() && frames == kWarmupFrames,
      "streamon_error",
      (s.is_ok() ? std::string("start() succeeded") : s.message()) + "; restart: " +
          (again.is_ok() ? "ok, " + std::to_string(frames) + " frames" : again.message()));
}

void check_buffer_error(const std::string& dev, const V4l2Control& inject) {
  V4l2Camera cam(dev, options_for("GREY"));
  if (Status s = cam.open(kPoolSize); !s.is_ok() || !cam.start().is_ok()) {
    report(false, "buffer_error", "open/start failed: " + s.message());
    return;
  }
  const int before = capture(cam, kWarmupFrames);
  const Status s = mer::hal::set_v4l2_control(dev, inject, 1);
  AcquireStatus last = AcquireStatus::kFrame;
  const int after = capture(cam, kFramesPerFormat / 2, &last);
  report(s.is_ok() && cam.error_frames() == 1 && after == kFramesPerFormat / 2, "buffer_error",
         (s.is_ok() ? std::string() : s.message() + "; ") + "error frames dropped " +
             std::to_string(cam.error_frames()) + ", frames before/after " +
             std::to_string(before) + "/" + std::to_string(after) +
             ", stream continued: " + (last == AcquireStatus::kFrame ? "yes" : "no"));
}

void check_dropped_buffers(const std::string& dev, const V4l2Control& percent) {
  V4l2Camera cam(dev, options_for("GREY"));
  if (Status s = cam.open(kPoolSize); !s.is_ok() || !cam.start().is_ok()) {
    report(false, "sequence_gaps", "open/start failed: " + s.message());
    return;
  }
  capture(cam, kWarmupFrames);
  const std::uint64_t gaps0 = cam.sequence_gaps();
  const Status s = mer::hal::set_v4l2_control(dev, percent, kDropPercent);
  const int got = capture(cam, kDropFrames);
  const Status reset = mer::hal::set_v4l2_control(dev, percent, 0);
  report(s.is_ok() && reset.is_ok() && gaps0 == 0 && cam.sequence_gaps() > 0 && got == kDropFrames,
         "sequence_gaps",
         "driver dropped " + std::to_string(kDropPercent) +
             "%: " + std::to_string(cam.sequence_gaps()) + " gaps counted over " +
             std::to_string(got) + " frames (before: " + std::to_string(gaps0) + ")" +
             (s.is_ok() ? "" : "; " + s.message()));
}

// A fatal streaming error (vb2_queue_error: DQBUF -> EIO, POLLERR): with on_error: retry
// the camera reopens and streams on; with stop it reports and stops.
void check_fatal_error(const std::string& dev, const V4l2Control& inject, bool retry) {
  const std::string name = retry ? "fatal_error_retry" : "fatal_error_stop";
  V4l2Options o = options_for("NV12");
  o.on_error = retry ? "retry" : "stop";
  o.max_retries = kRetries;
  o.retry_delay_ms = kRetryDelayMs;
  V4l2Camera cam(dev, o);
  if (Status s = cam.open(kPoolSize); !s.is_ok() || !cam.start().is_ok()) {
    report(false, name, "open/start failed: " + s.message());
    return;
  }
  capture(cam, kWarmupFrames);
  std::uint64_t seq_before = 0;
  {
    FrameHandle h;
    if (acquire_until(cam, h, mer::platform::monotonic_now_ns() + kFaultDeadlineNs) ==
        AcquireStatus::kFrame) {
      seq_before = h->seq;
    }
  }
  const Status s = mer::hal::set_v4l2_control(dev, inject, 1);
  const std::int64_t t0 = mer::platform::monotonic_now_ns();
  FrameHandle h;
  int timeouts = 0;
  AcquireStatus st = AcquireStatus::kTimeout;
  // Frames already completed before the fault may still come out first.
  for (int i = 0; i < kFramesPerFormat; ++i) {
    st = acquire_until(cam, h, t0 + kFaultDeadlineNs, &timeouts);
    if (st != AcquireStatus::kFrame || cam.stats().stream_errors > 0) break;
  }
  const double react_ms =
      static_cast<double>(mer::platform::monotonic_now_ns() - t0) / static_cast<double>(kNsPerMs);
  const std::string err = cam.last_error().message();
  const bool named = contains(err, dev) && (contains(err, "VIDIOC_DQBUF") || contains(err, "poll"));
  bool ok = s.is_ok() && cam.stats().stream_errors == 1 && named;
  std::string detail = "error reported after " + fmt("%.0f", react_ms) + " ms: '" + err + "'";
  if (retry) {
    // Streaming again: the frame after the restart continues the sequence.
    if (st != AcquireStatus::kFrame) st = acquire_until(cam, h, t0 + kFaultDeadlineNs, &timeouts);
    const int more = st == AcquireStatus::kFrame ? 1 + capture(cam, kWarmupFrames) : 0;
    ok = ok && st == AcquireStatus::kFrame && cam.stats().restarts == 1 && h &&
         h->seq > seq_before && more == kWarmupFrames + 1;
    detail += "; restarts " + std::to_string(cam.stats().restarts) + ", frames after restart " +
              std::to_string(more) + ", seq " + std::to_string(seq_before) + " -> " +
              std::to_string(h ? h->seq : 0);
  } else {
    FrameHandle again;
    const AcquireStatus st2 = cam.acquire(again, kAcquireTimeoutNs);
    ok = ok && st == AcquireStatus::kError && st2 == AcquireStatus::kError;
    detail += "; acquire() -> kError, stays stopped";
  }
  report(ok, name, detail + (s.is_ok() ? "" : "; " + s.message()));
}

enum class DisconnectCase {
  kStop,            // on_error: stop -> kError naming ENODEV, clean close
  kRetryReconnect,  // on_error: retry; vivid re-registers on the last close (a replug)
  kRetryGone,       // on_error: retry while another fd pins the device: it stays gone
};

// vivid's "Disconnect" unregisters the node (ENODEV on every call, POLLERR) and
// re-registers it when its last user closes it, like a USB camera unplugged and plugged.
void check_disconnect(const std::string& dev, const V4l2Control& inject, DisconnectCase c) {
  const std::string name = c == DisconnectCase::kStop             ? "disconnect_stop"
                           : c == DisconnectCase::kRetryReconnect ? "disconnect_retry_replug"
                                                                  : "disconnect_retry_gone";
  V4l2Options o = options_for("YUYV");
  o.on_error = c == DisconnectCase::kStop ? "stop" : "retry";
  o.max_retries = kRetries;
  o.retry_delay_ms = kRetryDelayMs;
  std::optional<V4l2Camera> cam;
  cam.emplace(dev, o);
  if (Status s = cam->open(kPoolSize); !s.is_ok() || !cam->start().is_ok()) {
    report(false, name, "open/start failed: " + s.message());
    return;
  }
  capture(*cam, kWarmupFrames);
  // A second open file keeps vivid from re-registering the node after our close.
  const int pin = c == DisconnectCase::kRetryGone ? ::open(dev.c_str(), O_RDWR | O_CLOEXEC) : -1;
  const Status s = mer::hal::set_v4l2_control(dev, inject, 1);
  const std::int64_t t0 = mer::platform::monotonic_now_ns();
  FrameHandle h;
  AcquireStatus st = AcquireStatus::kFrame;
  int timeouts = 0;
  int frames_after = 0;
  // Until the error is seen (frames done before the disconnect may still come out).
  while (st == AcquireStatus::kFrame && cam->stats().stream_errors == 0 &&
         mer::platform::monotonic_now_ns() - t0 < kFaultDeadlineNs) {
    st = acquire_until(*cam, h, t0 + kFaultDeadlineNs, &timeouts);
  }
  const double react_ms =
      static_cast<double>(mer::platform::monotonic_now_ns() - t0) / static_cast<double>(kNsPerMs);
  const std::string err = cam->last_error().message();
  const bool named = cam->stats().stream_errors == 1 && contains(err, dev) &&
                     (contains(err, "ENODEV") || contains(err, "POLLERR"));
  bool ok = s.is_ok() && named;
  std::string detail = "outcome after " + fmt("%.0f", react_ms) + " ms: '" + err + "'";
  if (c == DisconnectCase::kStop) {
    ok = ok && st == AcquireStatus::kError;
  } else {
    // Retry: kTimeout while reopening, then frames again (replug) or kError (gone).
    const std::int64_t t1 = mer::platform::monotonic_now_ns();
    while ((st == AcquireStatus::kTimeout || st == AcquireStatus::kFrame) &&
           mer::platform::monotonic_now_ns() - t1 < kFaultDeadlineNs) {
      st = acquire_until(*cam, h, t1 + kFaultDeadlineNs, &timeouts);
      if (st == AcquireStatus::kFrame && ++frames_after >= kWarmupFrames) break;
    }
    const auto& stats = cam->stats();
    detail += "; then " + std::to_string(timeouts) + " timeouts, reopen failures " +
              std::to_string(stats.reopen_failures) + ", restarts " +
              std::to_string(stats.restarts) + ", frames after " + std::to_string(frames_after);
    if (c == DisconnectCase::kRetryReconnect) {
      ok =
          ok && st == AcquireStatus::kFrame && stats.restarts == 1 && frames_after == kWarmupFrames;
    } else {
      // last_error() was read after the give-up: it carries both errors.
      ok = ok && st == AcquireStatus::kError &&
           contains(err, "gave up after " + std::to_string(kRetries)) &&
           stats.reopen_failures == static_cast<std::uint64_t>(kRetries) && stats.restarts == 0;
    }
  }
  h.reset();
  const std::int64_t t_close = mer::platform::monotonic_now_ns();
  cam.reset();  // must not hang on a vanished device
  const double close_ms = static_cast<double>(mer::platform::monotonic_now_ns() - t_close) /
                          static_cast<double>(kNsPerMs);
  if (pin >= 0) ::close(pin);  // last user gone: vivid re-registers the node
  report(ok, name,
         detail + "; closed in " + fmt("%.0f", close_ms) + " ms" +
             (s.is_ok() ? "" : "; " + s.message()));
}

}  // namespace

int main() {
  mer::platform::default_log();  // construct the log ring before any capture
  const std::int64_t t_start = mer::platform::monotonic_now_ns();
  const std::vector<std::string> nodes = find_vivid_capture_nodes();
  if (nodes.size() < 2) {
    report(false, "discover",
           "expected 2 vivid capture nodes, found " + std::to_string(nodes.size()));
    return 1;
  }
  const std::string& dev = nodes[0];
  const std::string& dev2 = nodes[1];
  auto controls = mer::hal::list_v4l2_controls(dev);
  if (!controls.is_ok()) {
    report(false, "discover", controls.status().message());
    return 1;
  }
  struct Needed {
    const char* needle;
    V4l2Control control;
  };
  std::vector<Needed> needed{{"STREAMON Error", {}},
                             {"BUF_FLAG_ERROR", {}},
                             {"Dropped Buffers", {}},
                             {"Fatal Streaming Error", {}},
                             {"Disconnect", {}}};
  std::string found;
  for (auto& n : needed) {
    auto c = mer::hal::find_v4l2_control(controls.value(), n.needle);
    if (!c.is_ok()) {
      report(false, "discover", c.status().message());
      return 1;
    }
    n.control = c.value();
    char id[16];
    std::snprintf(id, sizeof id, "0x%08x", n.control.id);
    found += (found.empty() ? "" : ", ") + std::string("'") + n.control.name + "' " + id;
  }
  report(true, "discover",
         dev + ", " + dev2 + "; " + std::to_string(controls.value().size()) +
             " controls; fault injection: " + found);

  std::vector<double> means;
  for (const char* f : {"GREY", "YUYV", "NV12"}) {
    const FormatResult r = check_format(dev, f);
    if (r.ok) means.push_back(r.mean);
  }
  if (means.size() == 3) {
    const double spread = *std::max_element(means.begin(), means.end()) -
                          *std::min_element(means.begin(), means.end());
    report(spread <= kMaxMeanDiff, "formats_agree",
           "mean gray GREY/YUYV/NV12 " + fmt("%.1f", means[0]) + "/" + fmt("%.1f", means[1]) + "/" +
               fmt("%.1f", means[2]) + " (spread " + fmt("%.1f", spread) + ")");
  }
  check_unsupported(dev);
  check_busy(dev);
  check_streamon_error(dev, needed[0].control);
  check_buffer_error(dev, needed[1].control);
  check_dropped_buffers(dev, needed[2].control);
  check_fatal_error(dev, needed[3].control, /*retry=*/true);
  check_fatal_error(dev, needed[3].control, /*retry=*/false);
  check_disconnect(dev, needed[4].control, DisconnectCase::kStop);
  check_disconnect(dev2, needed[4].control, DisconnectCase::kRetryReconnect);
  check_disconnect(dev, needed[4].control, DisconnectCase::kRetryGone);

  const double total_s = static_cast<double>(mer::platform::monotonic_now_ns() - t_start) / kNsPerS;
  std::printf("MER_HW_SUMMARY %d failed checks, %.1f s in the guest\n", mer::hw::failures(),
              total_s);
  mer::platform::flush_default_log_to_stderr(mer::platform::LogLevel::kInfo);
  return mer::hw::failures() == 0 ? 0 : 1;
}
