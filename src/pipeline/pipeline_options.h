#pragma once
/// @file pipeline_options.h
/// Options of the pipeline, the board (threads, budgets), telemetry and outputs.

#include <array>
#include <cstdint>
#include <string>
#include <string_view>

#include "core/options.h"
#include "core/sensor_mode.h"
#include "platform/log_ring.h"

namespace mer::pipeline {

/// Focal length of the run (`pipeline.focal`).
enum class FocalMode : std::uint8_t {
  kFixed,  ///< the calibration's
  kAuto,   ///< estimated while tracking, the calibration's as a guess
};
/// Names of FocalMode in config, by value.
inline constexpr std::array<std::string_view, 2> kFocalModeNames{"fixed", "auto"};
inline constexpr std::array<std::string_view, 3> kBoardProfiles{"generic_x86", "rpi4",
                                                                "jetson_orin"};
/// Names of platform::LogLevel in config, by value.
inline constexpr std::array<std::string_view, 4> kLogLevelNames{"debug", "info", "warn", "error"};

/// How the pipeline runs (config section `pipeline`).
struct PipelineOptions {
  SensorMode mode = SensorMode::kMono;
  bool lockstep = false;
  int max_frames = 0;
  int acquire_timeout_ms = 1000;
  int source_timeout_ms = 10000;
  FocalMode focal = FocalMode::kFixed;
  bool final_ba = false;

  template <class V>
  void visit(V& v) {
    v.field("mode", mode, "sensor mode", options::Names<SensorMode>{kSensorModeNames});
    v.field("lockstep", lockstep,
            "sequential deterministic replay (no drops, as fast as possible)");
    v.field("max_frames", max_frames, "stop after N source frames (0: whole input)",
            options::Range<int>{0, 1 << 30});
    v.field("acquire_timeout_ms", acquire_timeout_ms, "wait for a frame this long, ms",
            options::Range<int>{1, 60000});
    v.field("source_timeout_ms", source_timeout_ms,
            "no frame for this long ends the run as a source error (covers device recovery), ms",
            options::Range<int>{1, 3600000});
    v.field("focal", focal, "focal length: fixed (calibrated) or auto (estimated)",
            options::Names<FocalMode>{kFocalModeNames});
    v.field("final_ba", final_ba,
            "after the stream ends, optimize the whole graph (all keyframes and points); "
            "keyframes_final.txt and trajectory_final.txt then carry its result");
  }
};

/// Thread placement and latency budgets of the board (config section `board`; a file from
/// configs/boards/ passed with --board holds the same keys at its top level).
struct BoardOptions {
  std::string profile = "generic_x86";
  int capture_core = -2;
  int capture_priority = -1;
  int tracking_core = -2;
  int tracking_priority = -1;
  int output_core = -2;
  int output_priority = -1;
  int backend_core = -2;
  int backend_priority = -1;
  bool lock_memory = false;
  int malloc_mmap_threshold_kb = 128;
  double capture_budget_ms = 15.0;
  double tracking_budget_ms = 30.0;
  double output_budget_ms = 5.0;
  double end_to_end_budget_ms = 50.0;

  template <class V>
  void visit(V& v) {
    v.field("profile", profile, "built-in thread table", options::OneOf{kBoardProfiles});
    v.field("capture_core", capture_core, "capture thread CPU (-1 any, -2 profile)",
            options::Range<int>{-2, 1023});
    v.field("capture_priority", capture_priority,
            "capture SCHED_FIFO priority (0 normal, -1 profile)", options::Range<int>{-1, 99});
    v.field("tracking_core", tracking_core, "tracking thread CPU (-1 any, -2 profile)",
            options::Range<int>{-2, 1023});
    v.field("tracking_priority", tracking_priority,
            "tracking SCHED_FIFO priority (0 normal, -1 profile)", options::Range<int>{-1, 99});
    v.field("output_core", output_core, "output thread CPU (-1 any, -2 profile)",
            options::Range<int>{-2, 1023});
    v.field("output_priority", output_priority, "output thread priority (0 normal, -1 profile)",
            options::Range<int>{-1, 99});
    v.field("backend_core", backend_core,
            "back-end thread CPU (local BA, culling; -1 any, -2 profile)",
            options::Range<int>{-2, 1023});
    v.field("backend_priority", backend_priority,
            "back-end SCHED_FIFO priority, keep it below tracking (0 normal, -1 profile)",
            options::Range<int>{-1, 99});
    v.field("lock_memory", lock_memory, "mlockall() at start");
    v.field("malloc_mmap_threshold_kb", malloc_mmap_threshold_kb,
            "heap blocks of at least this many KiB get their own mapping, returned to the "
            "system when freed, so resident memory levels off on long runs (0: the "
            "allocator's adaptive threshold)",
            options::Range<int>{0, 32768});
    v.field("capture_budget_ms", capture_budget_ms, "capture budget per frame, ms",
            options::Range<double>{0.0, 10000.0});
    v.field("tracking_budget_ms", tracking_budget_ms, "tracking budget per frame, ms",
            options::Range<double>{0.0, 10000.0});
    v.field("output_budget_ms", output_budget_ms, "output budget per frame, ms",
            options::Range<double>{0.0, 10000.0});
    v.field("end_to_end_budget_ms", end_to_end_budget_ms,
            "frame ready to tracking result budget, ms", options::Range<double>{0.0, 10000.0});
  }
};

/// Latency and allocation accounting (config section `telemetry`).
struct TelemetryOptions {
  int warmup_frames = 10;
  int trace_capacity = 4096;
  platform::LogLevel log_level = platform::LogLevel::kInfo;

  template <class V>
  void visit(V& v) {
    v.field("warmup_frames", warmup_frames, "frames before steady state (allocation counts)",
            options::Range<int>{0, 1000000});
    v.field("trace_capacity", trace_capacity, "latency trace samples kept per stage",
            options::Range<int>{16, 1 << 22});
    v.field("log_level", log_level, "least severe log level printed",
            options::Names<platform::LogLevel>{kLogLevelNames});
  }
};

/// Output files (config section `output`).
struct OutputOptions {
  int flush_every = 30;

  template <class V>
  void visit(V& v) {
    v.field("flush_every", flush_every, "flush output files every N frames",
            options::Range<int>{1, 1000000});
  }
};

}  // namespace mer::pipeline
