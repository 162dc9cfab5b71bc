// mer_record: records any camera source to a native recording (hal/replay/recording.h).
//
// Two threads: the capture thread (the board's capture spec: highest priority) acquires
// frames and passes their pool slot indices through an SpscRing to the writer thread (the
// board's output spec: normal priority), which writes each frame as one chunk and returns
// the slot to the pool. Capture never waits for the disk: when the ring is full the frame
// is dropped and counted (for live sources; finite sources run unpaced with --fast simply
// wait, since nothing is lost by waiting). SIGINT/SIGTERM stop the capture; the writer
// finishes the queued frames, closes the file and a summary is printed.

#include <atomic>
#include <charconv>
#include <chrono>
#include <cmath>
#include <csignal>
#include <cstdio>
#include <iostream>
#include <optional>
#include <string>
#include <string_view>
#include <thread>

#include "app/cli.h"
#include "app/slam_config.h"
#include "app/stop_signal.h"
#include "core/config_io.h"
#include "hal/camera_factory.h"
#include "hal/replay/recording.h"
#include "platform/clock.h"
#include "platform/log_ring.h"
#include "platform/notifier.h"
#include "platform/rt_thread.h"
#include "platform/spsc_ring.h"
#include "platform/thread_table.h"

namespace {

using namespace mer;

/// Frames that may wait for the writer (a power of two, as SpscRing requires).
constexpr std::size_t kWriteQueueCapacity = 64;
/// Pool slots beyond the write queue: one being captured, one being written. With this
/// many, a slow disk fills the queue (a counted drop) before it empties the pool.
constexpr std::size_t kPoolSlack = 2;
/// How long one acquire() may wait, so stop requests and --duration are seen promptly.
constexpr std::int64_t kAcquireTimeoutNs = 100'000'000;
/// Back-off while the pool or (finite sources) the queue is full.
constexpr auto kBackoff = std::chrono::milliseconds(1);
constexpr double kNsPerS = 1e9;
constexpr double kBytesPerMiB = 1024.0 * 1024.0;

std::atomic<bool>& g_stop = app::stop_flag();

/// Parsed command line.
struct Args {
  std::string input;                 ///< --input URI
  std::string output;                ///< --output FILE
  std::string config_file;           ///< --config FILE
  std::optional<long> max_frames;    ///< --max-frames N
  std::optional<double> duration_s;  ///< --duration S
  bool fast = false;                 ///< --fast: finite sources unpaced
  bool no_depth = false;             ///< --no-depth
  bool quiet = false;                ///< --quiet
  bool help = false;                 ///< --help
  bool version = false;              ///< --version
};

std::string usage() {
  return "usage: mer_record --input URI --output FILE.merrec [--max-frames N] [--duration S]\n"
         "                  [--config FILE] [--fast] [--no-depth] [--quiet] [--help] "
         "[--version]\n"
         "\n"
         "Records a camera source to a native recording (replay it with --input rec:FILE).\n"
         "  --input URI       synthetic:NAME, tum:DIR, euroc:DIR, kitti:DIR, rec:FILE,\n"
         "                    v4l2:/dev/videoN, libcamera:ID (as mer_slam)\n"
         "  --output FILE     the recording to create (overwritten)\n"
         "  --max-frames N    stop after N captured frames\n"
         "  --duration S      stop after S seconds\n"
         "  --config FILE     YAML configuration as for mer_slam (its `camera` section is used)\n"
         "  --fast            do not pace finite sources (datasets, synthetic): record as fast\n"
         "                    as they produce, waiting for the disk instead of dropping\n"
         "  --no-depth        do not record the source's depth images\n"
         "  --quiet           no summary on stdout\n"
         "SIGINT/SIGTERM stop the recording cleanly. Exit codes: 0 ok, 2 usage or\n"
         "configuration, 3 input (source) error, 4 runtime (write) failure.\n";
}

Result<Args> parse_args(int argc, char** argv) {
  Args a;
  for (int i = 1; i < argc; ++i) {
    const std::string_view flag = argv[i];
    auto value = [&](std::string_view what) -> Result<std::string> {
      if (i + 1 >= argc)
        return invalid_argument(std::string(flag) + ": expected " + std::string(what));
      return std::string(argv[++i]);
    };
    if (flag == "--help" || flag == "-h") {
      a.help = true;
    } else if (flag == "--version") {
      a.version = true;
    } else if (flag == "--fast") {
      a.fast = true;
    } else if (flag == "--no-depth") {
      a.no_depth = true;
    } else if (flag == "--quiet") {
      a.quiet = true;
    } else if (flag == "--input" || flag == "--output" || flag == "--config") {
      auto v = value(flag == "--input" ? "a URI" : "a file name");
      if (!v.is_ok()) return v.status();
      (flag == "--input" ? a.input : flag == "--output" ? a.output : a.config_file) = v.value();
    } else if (flag == "--max-frames") {
      auto v = value("a positive integer");
      if (!v.is_ok()) return v.status();
      long n = 0;
      const std::string& s = v.value();
      const auto [end, ec] = std::from_chars(s.data(), s.data() + s.size(), n);
      if (ec != std::errc() || end != s.data() + s.size() || n <= 0) {
        return invalid_argument("--max-frames: expected a positive integer, found '" + s + "'");
      }
      a.max_frames = n;
    } else if (flag == "--duration") {
      auto v = value("a positive number of seconds");
      if (!v.is_ok()) return v.status();
      const std::string& s = v.value();
      std::size_t used = 0;
      double d = 0.0;
      try {
        d = std::stod(s, &used);
      } catch (const std::exception&) {
        used = 0;
      }
      if (used != s.size() || !std::isfinite(d) || d <= 0.0) {
        return invalid_argument("--duration: expected a positive number of seconds, found '" + s +
                                "'");
      }
      a.duration_s = d;
    } else {
      return invalid_argument("unknown argument '" + std::string(flag) + "'");
    }
  }
  if (a.help || a.version) return a;
  if (a.input.empty()) return invalid_argument("--input URI is required");
  if (a.output.empty()) return invalid_argument("--output FILE is required");
  return a;
}

int fail(const Status& s) {
  std::cerr << "mer_record: error: " << s.message() << "\n";
  return app::exit_code_for(s);
}

/// Why the capture loop ended.
enum class EndReason { kMaxFrames, kDuration, kSignal, kEndOfStream, kSourceError, kWriteError };

const char* end_reason_name(EndReason r) {
  switch (r) {
    case EndReason::kMaxFrames:
      return "max_frames";
    case EndReason::kDuration:
      return "duration";
    case EndReason::kSignal:
      return "signal";
    case EndReason::kEndOfStream:
      return "end_of_stream";
    case EndReason::kSourceError:
      return "source_error";
    case EndReason::kWriteError:
      return "write_error";
  }
  return "unknown";
}

/// Counters of one recording (written by the capture thread, read after it is joined).
struct CaptureStats {
  std::uint64_t captured = 0;     ///< frames acquired from the source
  std::uint64_t dropped = 0;      ///< frames dropped because the write queue was full
  std::uint64_t pool_waits = 0;   ///< acquire() calls that found the pool empty
  std::uint64_t source_gaps = 0;  ///< frames missing in the source's seq numbering
  EndReason end = EndReason::kEndOfStream;
  Status source_error;
};

/// The capture -> writer hand-off and the two thread bodies.
class Recorder {
 public:
  Recorder(hal::CameraSource& camera, hal::RecordingWriter& writer, const Args& args)
      : camera_(camera), writer_(writer), args_(args) {}

  /// Capture thread body: no allocation, no I/O, never blocks on the writer.
  void capture() {
    const bool live = camera_.capabilities().live;
    const std::int64_t t0 = platform::monotonic_now_ns();
    const auto max_duration_ns =
        args_.duration_s ? static_cast<std::int64_t>(*args_.duration_s * kNsPerS) : 0;
    std::optional<std::uint64_t> last_seq;
    CaptureStats& st = stats_;
    for (;;) {
      if (g_stop.load(std::memory_order_relaxed)) {
        st.end = EndReason::kSignal;
        break;
      }
      if (write_failed_.load(std::memory_order_acquire)) {
        st.end = EndReason::kWriteError;
        break;
      }
      if (args_.max_frames && st.captured >= static_cast<std::uint64_t>(*args_.max_frames)) {
        st.end = EndReason::kMaxFrames;
        break;
      }
      if (max_duration_ns > 0 && platform::monotonic_now_ns() - t0 >= max_duration_ns) {
        st.end = EndReason::kDuration;
        break;
      }
      hal::FrameHandle frame;
      const hal::AcquireStatus a = camera_.acquire(frame, kAcquireTimeoutNs);
      if (a == hal::AcquireStatus::kTimeout) continue;
      if (a == hal::AcquireStatus::kPoolEmpty) {
        ++st.pool_waits;
        std::this_thread::sleep_for(kBackoff);
        continue;
      }
      if (a == hal::AcquireStatus::kEndOfStream) {
        st.end = EndReason::kEndOfStream;
        break;
      }
      if (a == hal::AcquireStatus::kError) {
        st.end = EndReason::kSourceError;
        st.source_error = camera_.last_error();
        break;
      }
      ++st.captured;
      if (last_seq && frame->seq > *last_seq + 1) st.source_gaps += frame->seq - *last_seq - 1;
      last_seq = frame->seq;
      const std::uint32_t index = frame.release_raw();
      bool queued = queue_.try_push(index);
      // A finite source loses nothing by waiting for the disk; a live one would.
      while (!queued && !live && !g_stop.load(std::memory_order_relaxed) &&
             !write_failed_.load(std::memory_order_acquire)) {
        std::this_thread::sleep_for(kBackoff);
        queued = queue_.try_push(index);
      }
      if (queued) {
        wake_.notify();
      } else {
        camera_.pool().adopt(index).reset();  // drop: the buffer goes straight back
        ++st.dropped;
      }
    }
    camera_.stop();
    capture_done_.store(true, std::memory_order_release);
    wake_.notify();
  }

  /// Writer thread body: writes every queued frame until the capture is done and the queue
  /// is empty. After a write error it keeps releasing frames without writing them.
  void write() {
    for (;;) {
      const std::uint32_t seen = wake_.epoch();
      const bool done = capture_done_.load(std::memory_order_acquire);
      std::uint32_t index = 0;
      while (queue_.try_pop(index)) {
        hal::FrameHandle frame = camera_.pool().adopt(index);
        if (!frame || !write_status_.is_ok()) continue;
        write_status_ = writer_.append(*frame);
        if (!write_status_.is_ok()) write_failed_.store(true, std::memory_order_release);
      }
      if (done) break;
      wake_.wait(seen);
    }
  }

  /// Capture counters (after the capture thread ended).
  const CaptureStats& stats() const { return stats_; }
  /// First write error (after the writer thread ended).
  const Status& write_status() const { return write_status_; }

 private:
  hal::CameraSource& camera_;
  hal::RecordingWriter& writer_;
  const Args& args_;
  platform::SpscRing<std::uint32_t, kWriteQueueCapacity> queue_;
  platform::Notifier wake_;
  std::atomic<bool> capture_done_{false};
  std::atomic<bool> write_failed_{false};
  CaptureStats stats_;
  Status write_status_;
};

void print_summary(std::ostream& os, const Args& args, const hal::CameraSource& camera,
                   const hal::RecordingWriter& writer, const CaptureStats& st, double wall_s) {
  char mib[32];
  std::snprintf(mib, sizeof(mib), "%.1f",
                static_cast<double>(writer.bytes_written()) / kBytesPerMiB);
  char dur[32];
  std::snprintf(dur, sizeof(dur), "%.3f", wall_s);
  os << "mer_record summary\n"
     << "  output:          " << args.output << "\n"
     << "  source:          " << camera.describe() << "\n"
     << "  end_reason:      " << end_reason_name(st.end) << "\n"
     << "  frames_captured: " << st.captured << "\n"
     << "  frames_recorded: " << writer.frames_written() << "\n"
     << "  frames_dropped:  " << st.dropped << "\n"
     << "  pool_waits:      " << st.pool_waits << "\n"
     << "  source_seq_gaps: " << st.source_gaps << "\n"
     << "  bytes:           " << writer.bytes_written() << " (" << mib << " MiB)\n"
     << "  duration_s:      " << dur << "\n";
}

}  // namespace

int main(int argc, char** argv) {
  app::install_stop_signal_handlers();
  (void)platform::default_log();  // construct before any hot thread logs

  auto parsed = parse_args(argc, argv);
  if (!parsed.is_ok()) {
    std::cerr << usage();
    return fail(parsed.status());
  }
  const Args& args = parsed.value();
  if (args.help) {
    std::cout << usage();
    return 0;
  }
  if (args.version) {
    std::cout << "mer_record " << MER_VERSION << "\n";
    return 0;
  }
  app::SlamConfig config;
  if (!args.config_file.empty()) {
    if (Status s = options::load_yaml_file(args.config_file, config); !s.is_ok()) return fail(s);
  }

  platform::LogDrain drain(platform::default_log(), stderr, platform::LogLevel::kInfo);
  const platform::BoardThreads board =
      platform::find_board(config.board.profile).value_or(platform::kBoardGenericX86);
  (void)drain.start(board.log);
  auto stop_fail = [&drain](const Status& s) {
    drain.stop();
    return fail(s);
  };

  auto uri = hal::parse_input_uri(args.input);
  if (!uri.is_ok()) return stop_fail(uri.status());
  auto cam = hal::make_camera(uri.value(), config.camera, !args.fast);
  if (!cam.is_ok()) return stop_fail(cam.status());
  hal::CameraSource& camera = *cam.value();
  const std::size_t pool_size =
      std::max(static_cast<std::size_t>(config.camera.pool_size), kWriteQueueCapacity + kPoolSlack);
  if (Status s = camera.open(pool_size); !s.is_ok()) return stop_fail(s);

  hal::RecordingHeader header;
  header.description = camera.describe();
  header.intrinsics = hal::effective_intrinsics(camera.intrinsics(), config.camera.calibration);
  const hal::CameraCapabilities caps = camera.capabilities();
  header.nominal_fps = caps.nominal_fps;
  header.has_depth = caps.has_depth && !args.no_depth;
  header.has_ground_truth = caps.has_ground_truth;
  hal::RecordingWriter writer;
  if (Status s = writer.open(args.output, header); !s.is_ok()) return stop_fail(s);
  if (Status s = camera.start(); !s.is_ok()) return stop_fail(s);

  const std::int64_t t0 = platform::monotonic_now_ns();
  Recorder recorder(camera, writer, args);
  {
    platform::RtThread writer_thread;
    if (!writer_thread.start(board.output, [&recorder] { recorder.write(); })) {
      return stop_fail(runtime_error("cannot start the writer thread"));
    }
    platform::RtThread capture_thread;
    if (!capture_thread.start(board.capture, [&recorder] { recorder.capture(); })) {
      recorder.capture();  // fall back to this thread; it ends by telling the writer
    }
    capture_thread.join();
    writer_thread.join();
  }
  const double wall_s = static_cast<double>(platform::monotonic_now_ns() - t0) / kNsPerS;
  Status close_status = writer.close();
  drain.stop();  // pending warnings before the summary

  const CaptureStats& st = recorder.stats();
  if (!args.quiet) print_summary(std::cout, args, camera, writer, st, wall_s);
  if (!recorder.write_status().is_ok()) {
    return fail(runtime_error(recorder.write_status().message()));  // exit 4, whatever the cause
  }
  if (!close_status.is_ok()) return fail(close_status);
  if (st.end == EndReason::kSourceError) {
    return fail(st.source_error.is_ok() ? runtime_error("the source reported an error")
                                        : st.source_error);
  }
  return 0;
}
