// mer_hw_libcamera_vimc: the libcamera backend (hal/libcamera, the project's LibcameraCamera
// behind make_libcamera_camera, i.e. what `--input libcamera:ID` opens) against the kernel's
// vimc virtual media pipeline (sensor -> debayer -> scaler -> capture) driven by libcamera's
// own vimc pipeline handler and IPA module. Runs inside a qemu VM booted from a stock
// Debian kernel with an out-of-tree vimc.ko (tools/hw/libcamera_vimc_vm.sh, CTest label 'hw').
//
//   mer_hw_libcamera_vimc [ID]     ID: camera to capture from (default "auto")
//
// Prints one line per check, "MER_HW_CHECK PASS|FAIL <name>: <detail>", and exits 1 when
// any check failed. libcamera allows one CameraManager per process, so the checks open
// their cameras one after the other.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <memory>
#include <string>
#include <vector>

#include <opencv2/core.hpp>

#include "hal/libcamera/libcamera_camera.h"
#include "hw_check.h"
#include "platform/alloc_counter.h"
#include "platform/clock.h"
#include "platform/log_ring.h"

namespace {

using mer::Status;
using mer::hal::AcquireStatus;
using mer::hal::CameraSource;
using mer::hal::FrameHandle;
using mer::hal::LibcameraOptions;

constexpr int kWidth = 640;
constexpr int kHeight = 480;
constexpr double kFps = 30.0;
constexpr int kFrames = 30;           // frames checked in steady state
constexpr int kWarmupFrames = 3;      // captured first, not counted in the allocation check
constexpr std::size_t kPoolSize = 4;  // frame pool of the camera
constexpr int kMaxSizeAdjustPx = 16;  // the pipeline may align the size (vimc: 636x480)
constexpr std::int64_t kAcquireTimeoutNs = 500'000'000;
constexpr std::int64_t kFrameDeadlineNs = 10'000'000'000;  // TCG: a few frames per second
constexpr std::int64_t kMaxClockSkewNs = 1'000'000'000;    // |driver stamp - frame ready|
constexpr double kNsPerS = 1e9;
constexpr double kMinStdDev = 10.0;  // vimc's test pattern: far from a constant image
constexpr std::size_t kMaxProblems = 5;
constexpr std::string_view kUriPrefix = "libcamera:";

using mer::hw::contains;
using mer::hw::fmt;
using mer::hw::report;

LibcameraOptions default_options() {
  LibcameraOptions o;
  o.width = kWidth;
  o.height = kHeight;
  o.fps = kFps;
  o.pixel_format = "auto";
  return o;
}

std::unique_ptr<CameraSource> make(const std::string& id) {
  auto cam = mer::hal::make_libcamera_camera(id, default_options());
  if (!cam.is_ok()) return nullptr;
  return std::move(cam).value();
}

/// The camera id inside describe() ("libcamera:<id> (<stream configuration>)").
std::string camera_id(const CameraSource& cam) {
  const std::string d = cam.describe();
  const auto end = d.rfind(" (");
  if (d.rfind(kUriPrefix, 0) != 0 || end == std::string::npos) return {};
  return d.substr(kUriPrefix.size(), end - kUriPrefix.size());
}

// Acquires until a frame arrives or `deadline_ns` passes; returns the last status.
AcquireStatus acquire_until(CameraSource& cam, FrameHandle& h, std::int64_t deadline_ns) {
  for (;;) {
    const AcquireStatus st = cam.acquire(h, kAcquireTimeoutNs);
    if (st != AcquireStatus::kTimeout) return st;
    if (mer::platform::monotonic_now_ns() > deadline_ns) return st;
  }
}

// Captures up to `n` frames, returning how many arrived.
int capture(CameraSource& cam, int n) {
  int got = 0;
  for (int i = 0; i < n; ++i) {
    FrameHandle h;
    if (acquire_until(cam, h, mer::platform::monotonic_now_ns() + kFrameDeadlineNs) !=
        AcquireStatus::kFrame) {
      break;
    }
    ++got;
  }
  return got;
}

// ---- checks ------------------------------------------------------------------------------

// An unknown id fails open() with an input error naming the id and the cameras there are.
void check_unknown_camera() {
  const std::string bad = "no-such-camera";
  auto cam = make(bad);
  if (!cam) {
    report(false, "unknown_camera", "make_libcamera_camera failed");
    return;
  }
  const Status s = cam->open(kPoolSize);
  // vimc's camera ids name the sensor entity ("... Sensor B").
  report(!s.is_ok() && s.code() == mer::StatusCode::kInputError && contains(s.message(), bad) &&
             contains(s.message(), "available: ") && contains(s.message(), "Sensor"),
         "unknown_camera", s.is_ok() ? "open() succeeded" : s.message());
}

// An index past the last camera is the same clear error.
void check_bad_index() {
  auto cam = make("7");
  const Status s = cam ? cam->open(kPoolSize) : Status::ok();
  report(!s.is_ok() && contains(s.message(), "libcamera:7") && contains(s.message(), "available"),
         "bad_index", s.is_ok() ? "open() succeeded" : s.message());
}

// Steady-state capture: sequence and timestamps increase, the image has content, the size
// is the configured (possibly adjusted) one, and acquire() does not allocate.
// Returns the camera id on success (empty on failure).
std::string check_capture(const std::string& id) {
  const std::string name = "capture_" + id;
  auto cam = make(id);
  if (!cam) {
    report(false, name, "make_libcamera_camera failed");
    return {};
  }
  const std::int64_t t_open = mer::platform::monotonic_now_ns();
  if (Status s = cam->open(kPoolSize); !s.is_ok()) {
    report(false, name, "open: " + s.message());
    return {};
  }
  const double open_s = static_cast<double>(mer::platform::monotonic_now_ns() - t_open) / kNsPerS;
  if (Status s = cam->start(); !s.is_ok()) {
    report(false, name, "start: " + s.message());
    return {};
  }
  const auto& k = cam->intrinsics();
  std::vector<std::string> problems;
  if (std::abs(k.width - kWidth) > kMaxSizeAdjustPx ||
      std::abs(k.height - kHeight) > kMaxSizeAdjustPx) {
    problems.push_back("size " + std::to_string(k.width) + "x" + std::to_string(k.height) +
                       " too far from the requested " + std::to_string(kWidth) + "x" +
                       std::to_string(kHeight));
  }
  if (!cam->capabilities().live) problems.push_back("capabilities().live is false");
  const int warm = capture(*cam, kWarmupFrames);
  if (warm != kWarmupFrames) problems.push_back("warm-up: " + std::to_string(warm) + " frames");

  std::uint64_t prev_seq = 0;
  std::int64_t prev_t = 0;
  std::uint64_t first_seq = 0;
  std::uint64_t last_seq = 0;
  std::uint64_t allocs = 0;
  std::uint64_t allocs_max = 0;
  double min_std = 1e9;
  double mean0 = 0.0;
  int frames = 0;
  const std::int64_t t0 = mer::platform::monotonic_now_ns();
  const std::uint64_t all_threads0 = mer::platform::alloc::total_allocations();
  for (int i = 0; i < kFrames && problems.size() < kMaxProblems; ++i) {
    FrameHandle h;
    const std::int64_t deadline = mer::platform::monotonic_now_ns() + kFrameDeadlineNs;
    std::uint64_t frame_allocs = 0;
    AcquireStatus st = AcquireStatus::kTimeout;
    // Count only the call that returns the frame (the others only waited).
    while (st == AcquireStatus::kTimeout && mer::platform::monotonic_now_ns() < deadline) {
      const std::uint64_t a0 = mer::platform::alloc::thread_allocations();
      st = cam->acquire(h, kAcquireTimeoutNs);
      frame_allocs = mer::platform::alloc::thread_allocations() - a0;
    }
    if (st != AcquireStatus::kFrame) {
      problems.push_back("frame " + std::to_string(i) + ": acquire status " +
                         std::to_string(static_cast<int>(st)) + " " + cam->last_error().message());
      break;
    }
    allocs += frame_allocs;
    allocs_max = std::max(allocs_max, frame_allocs);
    const auto& f = *h;
    if (i == 0) {
      first_seq = f.seq;
    } else {
      if (f.seq <= prev_seq) {
        problems.push_back("sequence not increasing at frame " + std::to_string(i) + ": " +
                           std::to_string(prev_seq) + " -> " + std::to_string(f.seq));
      }
      if (f.t_ns <= prev_t) {
        problems.push_back("timestamp not increasing at frame " + std::to_string(i));
      }
    }
    if (std::abs(f.t_ready_ns - f.t_ns) > kMaxClockSkewNs) {
      problems.push_back("timestamp not on the monotonic clock: t_ns " + std::to_string(f.t_ns) +
                         " ready " + std::to_string(f.t_ready_ns));
    }
    if (f.gray.cols != k.width || f.gray.rows != k.height || f.gray.type() != CV_8UC1) {
      problems.push_back("frame " + std::to_string(f.gray.cols) + "x" +
                         std::to_string(f.gray.rows) + " does not match the configured " +
                         std::to_string(k.width) + "x" + std::to_string(k.height));
    }
    cv::Scalar mean;
    cv::Scalar stddev;
    cv::meanStdDev(f.gray, mean, stddev);
    if (i == 0) mean0 = mean[0];
    min_std = std::min(min_std, stddev[0]);
    prev_seq = f.seq;
    prev_t = f.t_ns;
    last_seq = f.seq;
    ++frames;
  }
  const double wall_s = static_cast<double>(mer::platform::monotonic_now_ns() - t0) / kNsPerS;
  // libcamera's own threads (and the backend's requeue thread) allocate per request; shown
  // for the record (approximate: other threads publish their counts in batches).
  const double all_threads_per_frame =
      static_cast<double>(mer::platform::alloc::total_allocations() - all_threads0) /
      std::max(frames, 1);
  if (min_std < kMinStdDev) {
    problems.push_back("image (nearly) constant: stddev " + fmt("%.1f", min_std));
  }
  if (allocs != 0) {
    problems.push_back(std::to_string(allocs) + " heap allocations in acquire() over " +
                       std::to_string(frames) + " frames (max " + std::to_string(allocs_max) +
                       " in one call)");
  }
  // stop(): acquire() reports the end of the stream.
  cam->stop();
  FrameHandle after;
  const AcquireStatus st_stopped = cam->acquire(after, kAcquireTimeoutNs);
  if (st_stopped != AcquireStatus::kEndOfStream) {
    problems.push_back("acquire() after stop() returned " +
                       std::to_string(static_cast<int>(st_stopped)));
  }
  std::string detail = cam->describe() + ": open " + fmt("%.2f", open_s) + " s, " +
                       std::to_string(frames) + " frames in " + fmt("%.2f", wall_s) + " s (" +
                       fmt("%.1f", frames / std::max(wall_s, 1e-9)) + " fps), seq " +
                       std::to_string(first_seq) + ".." + std::to_string(last_seq) +
                       ", min stddev " + fmt("%.1f", min_std) + ", mean " + fmt("%.1f", mean0) +
                       ", nominal fps " + fmt("%.0f", cam->capabilities().nominal_fps) +
                       ", allocs in acquire " + std::to_string(allocs) +
                       ", allocs per frame on all threads ~" + fmt("%.0f", all_threads_per_frame);
  for (const auto& p : problems) detail += "; " + p;
  const bool ok = problems.empty() && frames == kFrames;
  report(ok, name, detail);

  // Restart on the same camera: stop() left the requests reusable.
  std::string id_found = camera_id(*cam);
  if (Status s = cam->start(); !s.is_ok()) {
    report(false, "restart", "start() after stop(): " + s.message());
  } else {
    const int got = capture(*cam, kWarmupFrames);
    report(got == kWarmupFrames, "restart", std::to_string(got) + " frames after stop() + start()");
  }
  return ok ? id_found : std::string();
}

// The camera id found by "auto" opens by name too, and its index "0" too.
void check_open_by(const std::string& id, const std::string& check) {
  auto cam = make(id);
  if (!cam) {
    report(false, check, "make_libcamera_camera failed");
    return;
  }
  Status s = cam->open(kPoolSize);
  if (s.is_ok()) s = cam->start();
  const int got = s.is_ok() ? capture(*cam, kWarmupFrames) : 0;
  report(s.is_ok() && got == kWarmupFrames, check,
         "libcamera:" + id + ": " + (s.is_ok() ? cam->describe() : s.message()) + ", " +
             std::to_string(got) + " frames");
}

}  // namespace

int main(int argc, char** argv) {
  const std::string id = argc > 1 ? argv[1] : "auto";
  if (!mer::hal::libcamera_backend_built()) {
    report(false, "backend", "this build has no libcamera backend (libcamera-dev not found)");
    return 1;
  }
  if (!mer::platform::alloc::counter_linked()) {
    report(false, "alloc_counter", "the counting operator new is not linked");
    return 1;
  }
  check_unknown_camera();
  check_bad_index();
  const std::string found = check_capture(id);
  if (!found.empty()) {
    check_open_by(found, "open_by_id");
    check_open_by("0", "open_by_index");
  }
  std::printf("MER_HW_SUMMARY %s (%d failed)\n", mer::hw::failures() == 0 ? "PASS" : "FAIL",
              mer::hw::failures());
  mer::platform::flush_default_log_to_stderr(mer::platform::LogLevel::kInfo);
  return mer::hw::failures() == 0 ? 0 : 1;
}
