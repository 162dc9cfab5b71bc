#pragma once
/// @file pipeline.h
/// The one place that wires the stages:
///
///   capture (CameraSource) --OverwriteRing<slot>--> tracking --SpscRing<result>--> output
///                                                      |
///                                     SpscRing<keyframe job slot>
///                                                      v
///                 depth (keyframe builder) --SpscRing<keyframe id>--> back end (local BA,
///                                                                     map culling)
///
/// Threaded mode: each stage runs on its own RtThread (name, core and priority from the
/// board's thread table). Capture never blocks: when tracking falls behind, the ring drops
/// the oldest frame, hands its buffer back to the pool and counts it. Tracking never waits
/// on output: a full result ring is counted as an output overflow, and never on keyframe
/// creation: with every job slot busy the keyframe decision is deferred (counted).
/// The depth thread (low priority) runs the keyframe builder (depth inference, insertion)
/// and hands each new keyframe to the back-end thread (high priority, below tracking), which
/// runs the local BA around the newest keyframe queued (older ones queued behind it need no
/// run of their own) and culling. Both write the map, one at a time under its writer lock
/// (map.h), a priority-inheritance mutex; tracking never takes it. A keyframe inserted while
/// a local BA runs pre-empts it (LocalBundleAdjuster::request_abort). Shutdown: capture ends,
/// then tracking, depth and the back end each drain their input before they end.
///
/// Lockstep mode: the same stage objects run sequentially on the calling thread in a
/// fixed order (capture -> tracking -> keyframe builder -> local BA -> culling -> output),
/// with a lockstep clock set to each frame's timestamp: the same input gives bit-identical
/// trajectory/keyframes/frames files.

#include <array>
#include <atomic>
#include <cstdint>
#include <memory>
#include <span>
#include <string>
#include <vector>

#include "backend/local_ba.h"
#include "backend/map_culling.h"
#include "core/status.h"
#include "depth/depth_map_source.h"
#include "depth/depth_options.h"
#include "depth/keyframe_builder.h"
#include "frontend/tracker.h"
#include "hal/camera.h"
#include "loop/loop_closer.h"
#include "loop/relocalizer.h"
#include "map/keyframe_job.h"
#include "map/map.h"
#include "pipeline/final_trajectory.h"
#include "pipeline/output_stage.h"
#include "pipeline/pipeline_options.h"
#include "pipeline/segment_outputs.h"
#include "platform/latency_recorder.h"
#include "platform/thread_table.h"

namespace mer::pipeline {

/// Frames the capture ring holds (compile-time: rings are fixed-size). The camera pool
/// must hold at least this plus the frames being captured and tracked.
inline constexpr std::size_t kCaptureRingSize = 4;
/// Tracking results buffered for the output thread.
inline constexpr std::size_t kResultRingSize = 256;
/// Keyframe jobs in flight between tracking and keyframe creation.
inline constexpr std::size_t kKeyframeJobs = 8;
/// Keyframes queued from the depth thread to the back-end thread (drained at each wake-up).
inline constexpr std::size_t kBackendQueue = 2 * kKeyframeJobs;
/// Keyframes queued from the back-end thread to the loop-closure thread (threaded mode).
inline constexpr std::size_t kLoopQueue = 4 * kKeyframeJobs;

/// Everything the pipeline needs from the configuration.
struct PipelineConfig {
  PipelineOptions pipeline;
  BoardOptions board;
  TelemetryOptions telemetry;
  OutputOptions output;
  frontend::TrackingOptions tracking;
  map::MapOptions map;
  depth::DepthOptions depth;
  backend::LocalBaOptions backend;
  hal::CameraIntrinsics intrinsics;  ///< calibration in use (source's, or the override)
  backend::CullingOptions culling;
  mer::loop::LoopOptions loop;
  mer::loop::RelocalizerOptions relocalization;
};

/// Latency of one stage, summarized.
struct StageLatency {
  std::string name;  ///< capture, tracking, output, end_to_end
  double p50_ms = 0.0;
  double p90_ms = 0.0;
  double p99_ms = 0.0;
  double max_ms = 0.0;
  double mean_ms = 0.0;
  double budget_ms = 0.0;
  std::uint64_t count = 0;
  std::uint64_t overruns = 0;  ///< samples above budget
};

/// Steady-state heap allocations per frame of one thread.
struct ThreadAllocs {
  std::string thread;             ///< capture, tracking, output
  std::uint64_t allocations = 0;  ///< heap allocations in steady state
  std::uint64_t frames = 0;       ///< frames in steady state
  double per_frame() const { return frames ? static_cast<double>(allocations) / frames : 0.0; }
};

/// How a thread was actually placed (RT priority may be refused without privileges).
struct ThreadPlacement {
  std::string thread;
  int core = -1;
  int priority = 0;
  bool applied = false;  ///< affinity and priority were applied as asked
  std::string note;      ///< why not, when not
  double cpu_s = 0.0;    ///< CPU time the thread used over the run, s
};

/// CPU time of the run. Per frame: the CPU the whole process used between one frame's
/// tracking result and the next (every thread: in threaded mode the work of the keyframe,
/// back-end and loop threads lands in the frames during which it ran).
struct CpuStats {
  StageLatency process;    ///< per frame, ms (name "process")
  StageLatency slam;       ///< per frame without the source's work, ms (name "slam")
  double process_s = 0.0;  ///< whole process from the start to the end of the stream, s
  double source_s = 0.0;   ///< of which the source producing frames (converting, decoding or
                           ///< rendering them: hal::Frame::produce_cpu_ns), s
};

/// What the full-graph optimization after the stream did.
struct FinalBaStats {
  bool ran = false;
  int keyframes = 0;
  int points = 0;
  int observations = 0;
  int iterations = 0;
  double ms = 0.0;
};

/// One map segment of a run (summary.json `segments`; tracking.new_segments).
struct SegmentStats {
  std::uint16_t id = 0;
  std::uint64_t frames = 0;         ///< frames tracked in it
  std::uint64_t keyframes = 0;      ///< its keyframes alive in the map at the end
  std::uint64_t first_seq = 0;      ///< first frame tracked in it
  std::uint64_t last_seq = 0;       ///< last frame tracked in it
  std::string trajectory;           ///< file holding its frames after merging (segment_outputs.h):
                                    ///< trajectory.txt for the main segment
  int merged_into = -1;             ///< the segment it merged into (finally), -1: never merged
  std::uint64_t merged_at_seq = 0;  ///< frame of its merge
  int fit_keyframes = 0;   ///< merged: keyframes its frames' similarity into the main segment was
                           ///< fitted to (0: the merges' similarities; segment_outputs.h)
  bool main = false;       ///< the main segment (trajectory.txt)
  bool discarded = false;  ///< a failed start (tracking.init.discard_failed_starts):
                           ///< its `frames` count as lost, it has no trajectory file
};

/// What relocalization did over a run (summary.json `relocalization`).
/// An accepted relocalization: the frame, the keyframe it was matched to and its pose
/// relative to that keyframe as the map held it then (for ground-truth audits).
struct RelocalizationEvent {
  std::uint64_t seq = 0;           ///< the frame tracking resumed on
  std::int64_t t_ns = 0;           ///< its timestamp
  std::int64_t keyframe_t_ns = 0;  ///< the keyframe the relocalizer matched
  std::uint16_t segment = 0;       ///< the segment tracking resumed in
  SE3d T_kf_c = SE3d::Identity();  ///< frame pose relative to that keyframe, map units
  bool confirmed = false;          ///< confirmed on following frames, not trusted at once
  float found_ratio = 0.0F;        ///< found share / usual: lowest while confirming,
                                   ///< or the frame's when trusted at once
};

/// Accepted relocalizations kept per run, at most (later ones are only counted).
inline constexpr std::size_t kMaxRelocalizationEvents = 1024;

struct RelocalizationStats {
  bool enabled = false;
  std::uint64_t attempts = 0;          ///< lost frames the relocalizer ran on
  std::uint64_t successes = 0;         ///< of those, a pose with enough inliers was found
  std::uint64_t timed_out = 0;         ///< attempts that left candidates unchecked (max_time_ms)
  std::uint64_t candidates = 0;        ///< keyframes checked geometrically, all attempts
  std::uint64_t skipped_busy = 0;      ///< threaded: requests not posted, the last one in flight
  double max_ms = 0.0;                 ///< longest attempt
  double sum_ms = 0.0;                 ///< all attempts (mean = sum / attempts)
  std::int64_t last_success_seq = -1;  ///< frame of the last success
  std::vector<RelocalizationEvent> events;  ///< accepted ones (reserved: no allocation)
  std::uint64_t events_dropped = 0;         ///< accepted beyond kMaxRelocalizationEvents
};

/// Counters and summaries of one run.
struct PipelineStats {
  std::uint64_t frames_in = 0;               ///< frames delivered by the source
  std::uint64_t frames_processed = 0;        ///< frames tracking ran on
  std::uint64_t frames_dropped = 0;          ///< frames evicted from the capture ring (threaded)
  std::uint64_t frames_lost = 0;             ///< processed frames without a pose (those of
                                             ///< discarded segments included)
  std::uint64_t frames_discarded = 0;        ///< of these, tracked in a discarded segment
  std::int64_t first_pose_seq = -1;          ///< first frame tracked in a segment that was
                                             ///< not discarded (-1: none)
  std::uint64_t keyframes = 0;               ///< keyframes alive in the map at the end
  std::uint64_t keyframes_deferred = 0;      ///< keyframe decisions retried: every job slot busy
  std::uint64_t loop_queue_full = 0;         ///< threaded: keyframes not checked for a loop,
                                             ///< the loop thread's queue was full
  std::uint64_t backend_coalesced = 0;       ///< keyframes whose local BA was left to a newer
                                             ///< one queued behind it (threaded)
  std::uint64_t map_points = 0;              ///< map-points alive at the end
  std::uint64_t steady_frames = 0;           ///< frames tracked against an existing map
  frontend::TrackerCounters tracker;         ///< tracking counters
  frontend::FocalReport focal;               ///< focal length used / estimated
  depth::KeyframeBuildTotals mapping;        ///< keyframe creation totals
  backend::LocalBaTotals backend;            ///< local bundle adjustment totals
  backend::CullingTotals culling;            ///< map culling totals
  mer::loop::LoopTotals loop;                ///< loop closure totals
  RelocalizationStats relocalization;        ///< relocalization attempts and successes
  std::vector<SegmentStats> segments;        ///< map segments that tracked a frame, by id
  map::MapCounters map;                      ///< slots live / used / reused at the end
  std::string depth_backend;                 ///< depth inference backend in use
  std::string backend_depth_edges;           ///< 3D-3D edge mode of the back end in use
  std::vector<StageLatency> tracking_steps;  ///< tracking breakdown (extract, query, ...)
  std::uint64_t pool_exhausted = 0;          ///< acquire found every frame buffer in use
  std::uint64_t output_overflows = 0;        ///< results lost because the output ring was full
  std::uint64_t acquire_timeouts = 0;
  double wall_time_s = 0.0;
  std::string mode;            ///< "lockstep" or "threaded"
  std::string pose_source;     ///< where poses come from ("tracking")
  std::string end_reason;      ///< end_of_stream, max_frames, signal, source_error
  hal::SourceCounters source;  ///< what the source dropped or survived
  std::vector<StageLatency> latency;
  std::vector<ThreadAllocs> allocs;
  /// The tracking thread's heap allocations after the warm-up, per tracker state of the
  /// frame (every frame, not only steady ones; `thread` holds the state's name). The frame
  /// that initialized the map counts as initializing.
  std::vector<ThreadAllocs> tracking_allocs_by_state;
  std::vector<ThreadPlacement> threads;
  CpuStats cpu;           ///< CPU per frame and in total
  FinalBaStats final_ba;  ///< pipeline.final_ba
};

/// Owns the stages and runs them.
class Pipeline {
 public:
  /// `camera` must be opened; `stop` is polled (e.g. set from a SIGINT handler).
  /// `depth_maps`: the maps of `depth.backend: external` (must outlive the pipeline; null
  /// for the other backends).
  Pipeline(const PipelineConfig& config, hal::CameraSource& camera, const std::atomic<bool>& stop,
           depth::DepthMapSource* depth_maps = nullptr);
  ~Pipeline();

  /// Allocates every stage and opens the output files in `output_dir` (may be empty).
  Status init(const std::string& output_dir);

  /// Runs to the end of the input, max_frames, a source error or `stop`. Outputs are
  /// flushed and closed before returning, whatever the reason.
  Status run();

  /// Counters and latency summaries (complete after run()).
  const PipelineStats& stats() const { return stats_; }
  /// After run(): every keyframe's pose in the final map of the main segment (trajectory.txt's
  /// world frame, which merged segments joined), the removed ones through their lineage
  /// (final_trajectory.h), sorted by time.
  std::vector<FinalKeyframePose> final_keyframe_poses() const;
  /// After run(): per segment id, the scale from its units into trajectory.txt's (1 for the
  /// main segment, the merges' scales for segments joined into it, 0 for the others).
  std::vector<double> segment_scales_into_main() const;
  /// The finished map, for evaluation after run() (eval/groundtruth_check.h): every stage
  /// has stopped, so the caller is the map's only user.
  struct FinishedMap {
    map::Map& map;                     ///< the map as the run left it
    backend::LocalBundleAdjuster& ba;  ///< the bundle adjuster configured for it
    geometry::Pinhole K;               ///< the intrinsics tracking ended with
  };
  /// After run() (see FinishedMap).
  FinishedMap finished_map();

 private:
  struct Threaded;  // the stage threads of run_threaded (pipeline_threaded.cpp)
  Status run_lockstep();
  Status run_threaded();
  void finish_stats(std::int64_t t_start_ns);
  void run_final_ba();
  /// Joins the segment trajectory files along the merges of the run (segment_outputs.h).
  Status join_segments();
  /// Writes `output_dir`/keyframes_final.txt: the main segment's live keyframes' poses in the
  /// final map (after local BA and the final BA), in time order.
  Status write_final_keyframes() const;
  std::vector<SegmentMergeRecord> merge_records() const;
  /// Per segment id, the scale from its units into segment `main`'s along the merges (0 for a
  /// segment that did not join it and for a discarded one).
  std::vector<double> kept_segment_scales_into(std::uint16_t main) const;
  /// keyframes.csv: one line per keyframe created (keyframe thread only; closed by run()).
  Status open_keyframes_csv();
  void write_keyframe_row(const map::KeyframeJob& job, const depth::KeyframeBuildReport& rep);
  Status close_keyframes_csv();
  std::FILE* keyframes_csv_ = nullptr;
  std::string keyframes_csv_path_;
  std::string output_dir_;
  platform::BoardThreads resolve_threads() const;
  bool reached_max_frames() const;
  bool source_timed_out(std::int64_t last_frame_ns) const;
  std::string source_timeout_message() const;

  PipelineConfig config_;
  hal::CameraSource& camera_;
  const std::atomic<bool>& stop_;
  depth::DepthMapSource* depth_maps_;
  void queue_or_build_keyframe(const hal::Frame& frame, const frontend::TrackingResult& r);
  void count_result(const frontend::TrackingResult& r);

  std::unique_ptr<map::Map> map_;
  std::unique_ptr<frontend::Tracker> tracker_;
  std::unique_ptr<depth::KeyframeBuilder> builder_;
  std::unique_ptr<backend::LocalBundleAdjuster> ba_;
  /// Threaded: the loop thread's full BA after a loop, its own problem and workspace so that
  /// it never holds up the back end's local BA (lockstep: the loop closer uses ba_).
  std::unique_ptr<backend::LocalBundleAdjuster> loop_ba_;
  std::unique_ptr<backend::MapCuller> culler_;
  std::unique_ptr<loop::LoopCloser> loop_;
  std::unique_ptr<loop::Relocalizer> relocalizer_;  ///< null when relocalization.enabled is off
  frontend::RelocalizationRequest reloc_request_;
  int reloc_reader_ = -1;  ///< threaded: the relocalizer's map-reader handle (depth thread)
  /// Runs the relocalizer on `req` (the calling thread: lockstep, or the depth thread) and
  /// counts it; the hint is valid when it succeeded.
  frontend::RelocalizationHint relocalize(const frontend::RelocalizationRequest& req);
  /// Lockstep keyframe creation: build_keyframe, then optimize_and_cull.
  void create_keyframe(const map::KeyframeJob& job);
  /// The keyframe builder (depth inference + insertion; latency `keyframe`).
  depth::KeyframeBuildReport build_keyframe(const map::KeyframeJob& job);
  /// Local BA around ba_kf (kNoId: none; latency `local_ba`), then culling around cull_kf.
  void optimize_and_cull(map::KeyframeId ba_kf, const geometry::Pinhole& K, std::uint64_t seq,
                         map::KeyframeId cull_kf);
  std::vector<map::KeyframeJob> jobs_;
  std::array<std::unique_ptr<platform::LatencyRecorder>,
             static_cast<std::size_t>(frontend::TrackStep::kCount)>
      lat_steps_;
  std::unique_ptr<platform::LatencyRecorder> lat_keyframe_;        ///< builder only (depth thread)
  std::unique_ptr<platform::LatencyRecorder> lat_local_ba_;        ///< one local BA run (back end)
  std::unique_ptr<platform::LatencyRecorder> lat_relocalization_;  ///< one relocalizer attempt
  OutputStage output_;
  std::unique_ptr<platform::LatencyRecorder> lat_capture_;
  std::unique_ptr<platform::LatencyRecorder> lat_tracking_;
  std::unique_ptr<platform::LatencyRecorder> lat_output_;
  std::unique_ptr<platform::LatencyRecorder> lat_end_to_end_;
  std::unique_ptr<platform::LatencyRecorder> lat_cpu_process_;  ///< CPU per frame (tracking thread)
  std::unique_ptr<platform::LatencyRecorder> lat_cpu_slam_;     ///< the same without the source
  std::int64_t cpu_start_ns_ = 0;        ///< process CPU when the stream started
  std::int64_t cpu_last_ns_ = 0;         ///< process CPU at the last frame's result
  std::int64_t cpu_last_source_ns_ = 0;  ///< source_cpu_ns_ then
  /// CPU the source spent producing the frames so far (hal::Frame::produce_cpu_ns; written by
  /// the capture thread, read by the tracking thread).
  std::atomic<std::int64_t> source_cpu_ns_{0};
  /// Records the CPU used since the previous frame's result (the tracking thread, once per
  /// frame).
  void record_cpu(std::uint64_t seq);
  /// Adds a frame's produce_cpu_ns (capture thread).
  void add_source_cpu(std::int64_t cpu_ns);
  ThreadAllocs allocs_capture_{"capture"};
  ThreadAllocs allocs_tracking_{"tracking"};
  std::array<ThreadAllocs, frontend::kTrackerStateCount>
      allocs_by_state_{};                       ///< per frontend::TrackerState
  std::vector<SegmentStats> segment_stats_;     ///< per segment id (sized at init)
  std::vector<SegmentOutput> segment_outputs_;  ///< join_segment_files' result
  std::uint16_t main_segment_ = 0;              ///< trajectory.txt's segment
  void count_state_allocs(const frontend::TrackingResult& r, std::uint64_t allocations);
  ThreadAllocs allocs_output_{"output"};
  PipelineStats stats_;
  bool initialized_ = false;
};

}  // namespace mer::pipeline
