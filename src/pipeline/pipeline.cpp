#include "pipeline/pipeline.h"

#include <algorithm>
#include <cerrno>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <thread>

#include "platform/alloc_counter.h"
#include "platform/clock.h"
#include "platform/log_ring.h"
#include "platform/memory.h"
#include "platform/notifier.h"
#include "platform/overwrite_ring.h"
#include "platform/rt_thread.h"
#include "platform/spsc_ring.h"

namespace mer::pipeline {
namespace {

constexpr double kMsToNs = 1e6;
constexpr double kNsToS = 1e-9;

std::int64_t ms_to_ns(double ms) {
  return static_cast<std::int64_t>(ms * kMsToNs);
}

StageLatency summarize(const platform::LatencyRecorder& r) {
  StageLatency s;
  s.name = std::string(r.name());
  s.count = r.count();
  if (s.count > 0) {
    s.p50_ms = r.percentile_ms(0.50);
    s.p90_ms = r.percentile_ms(0.90);
    s.p99_ms = r.percentile_ms(0.99);
    s.max_ms = r.max_ms();
    s.mean_ms = r.mean_ms();
  }
  s.budget_ms = static_cast<double>(r.budget_ns()) / kMsToNs;
  s.overruns = r.overruns();
  return s;
}

}  // namespace

Pipeline::Pipeline(const PipelineConfig& config, hal::CameraSource& camera,
                   const std::atomic<bool>& stop, depth::DepthMapSource* depth_maps)
    : config_(config), camera_(camera), stop_(stop), depth_maps_(depth_maps) {}

Pipeline::~Pipeline() {
  if (keyframes_csv_ != nullptr) (void)std::fclose(keyframes_csv_);
}

Status Pipeline::init(const std::string& output_dir) {
  const hal::CameraIntrinsics& K = camera_.intrinsics();
  if (K.width <= 0 || K.height <= 0) {
    return runtime_error("pipeline: camera '" + camera_.describe() + "' is not open");
  }
  if (config_.pipeline.mode == SensorMode::kRgbd && !camera_.capabilities().has_depth) {
    return input_error("--mode rgbd: input '" + camera_.describe() + "' provides no depth");
  }
  if (camera_.pool().capacity() < kCaptureRingSize + 2) {
    return invalid_argument("key 'camera.pool_size': expected at least " +
                            std::to_string(kCaptureRingSize + 2) +
                            " (capture ring + frames being captured and tracked), found " +
                            std::to_string(camera_.pool().capacity()));
  }
  if (Status v = map::validate(config_.map); !v.is_ok()) return v;  // e.g. table size
  if (const int kb = config_.board.malloc_mmap_threshold_kb; kb > 0) {
    std::string err;
    if (!platform::set_mmap_threshold(static_cast<std::size_t>(kb) * 1024U, &err)) {
      MER_LOG_WARN("board.malloc_mmap_threshold_kb: %s (continuing)", err.c_str());
    }
  }
  map_ = std::make_unique<map::Map>(config_.map);
  const hal::CameraIntrinsics& Kc = config_.intrinsics.fx > 0.0 ? config_.intrinsics : K;
  const geometry::Pinhole pinhole{Kc.fx, Kc.fy, Kc.cx, Kc.cy};
  tracker_ = std::make_unique<frontend::Tracker>(config_.tracking, *map_, pinhole, K.width,
                                                 K.height, config_.pipeline.mode,
                                                 config_.pipeline.focal == FocalMode::kAuto);
  if (Status t = tracker_->init(); !t.is_ok()) return t;
  builder_ = std::make_unique<depth::KeyframeBuilder>(
      config_.depth, config_.pipeline.mode, *map_, tracker_->level_sigma2(),
      config_.backend.depth_edges == backend::DepthEdgeSetting::kOff
          ? 0.0
          : config_.backend.depth_sigma_rel,
      depth_maps_);
  if (Status d = builder_->init(); !d.is_ok()) return d;
  ba_ = std::make_unique<backend::LocalBundleAdjuster>(
      config_.backend, *map_, tracker_->level_sigma2(), config_.pipeline.lockstep,
      builder_->metric_map_depth());
  culler_ =
      std::make_unique<backend::MapCuller>(config_.culling, *map_, builder_->metric_map_depth());
  if (!config_.pipeline.lockstep) {
    loop_ba_ = std::make_unique<backend::LocalBundleAdjuster>(
        config_.backend, *map_, tracker_->level_sigma2(), false, builder_->metric_map_depth());
  }
  loop_ = std::make_unique<loop::LoopCloser>(
      config_.loop, *map_, tracker_->level_sigma2(), builder_->metric_map_depth(),
      loop_ba_ ? loop_ba_.get() : ba_.get(), config_.relocalization);
  if (config_.relocalization.enabled) {
    int reader = -1;
    if (!config_.pipeline.lockstep) {
      // Threaded, it runs on the depth thread: a registered map reader. It shares the loop
      // closer's keyframe database (under the database's lock).
      Result<int> r = map_->register_reader();
      if (!r.is_ok()) return r.status();
      reader = r.value();
      reloc_reader_ = reader;
    }
    relocalizer_ = std::make_unique<loop::Relocalizer>(
        config_.relocalization, *map_, loop_->database(), reader, config_.pipeline.lockstep);
    tracker_->reserve_relocalization_request(reloc_request_);
    tracker_->enable_relocalization(true);
  }
  stats_.relocalization.enabled = relocalizer_ != nullptr;
  stats_.relocalization.events.reserve(kMaxRelocalizationEvents);
  segment_stats_.assign(static_cast<std::size_t>(config_.tracking.max_segments), SegmentStats{});
  jobs_.resize(kKeyframeJobs);
  const bool dense = builder_->backend() == depth::DepthBackend::kPlaneSweep;
  const int recent = dense ? config_.depth.plane_sweep.sources : 0;
  if (dense) tracker_->keep_recent_frames(recent + 1, config_.depth.plane_sweep.source_spacing_s);
  for (auto& j : jobs_) {
    j.reserve(tracker_->max_keypoints(), K.width, K.height);
    j.reserve_recent(recent, K.width, K.height);
  }
  const auto trace = static_cast<std::size_t>(config_.telemetry.trace_capacity);
  const BoardOptions& b = config_.board;
  lat_capture_ =
      std::make_unique<platform::LatencyRecorder>("capture", ms_to_ns(b.capture_budget_ms), trace);
  lat_tracking_ = std::make_unique<platform::LatencyRecorder>(
      "tracking", ms_to_ns(b.tracking_budget_ms), trace);
  lat_output_ =
      std::make_unique<platform::LatencyRecorder>("output", ms_to_ns(b.output_budget_ms), trace);
  lat_end_to_end_ = std::make_unique<platform::LatencyRecorder>(
      "end_to_end", ms_to_ns(b.end_to_end_budget_ms), trace);
  for (std::size_t i = 0; i < lat_steps_.size(); ++i) {
    lat_steps_[i] = std::make_unique<platform::LatencyRecorder>(
        frontend::to_string(static_cast<frontend::TrackStep>(i)), 0, trace);
  }
  lat_cpu_process_ = std::make_unique<platform::LatencyRecorder>("process", 0, trace);
  lat_cpu_slam_ = std::make_unique<platform::LatencyRecorder>("slam", 0, trace);
  lat_keyframe_ = std::make_unique<platform::LatencyRecorder>("keyframe", 0, trace);
  lat_relocalization_ = std::make_unique<platform::LatencyRecorder>(
      "relocalization", ms_to_ns(config_.relocalization.max_time_ms), trace);
  lat_local_ba_ = std::make_unique<platform::LatencyRecorder>(
      "local_ba", ms_to_ns(config_.backend.max_time_ms), trace);
  output_dir_ = output_dir;
  Status s = output_.open(output_dir, config_.output);
  if (s.is_ok()) s = open_keyframes_csv();
  if (!s.is_ok()) return s;
  if (b.lock_memory) {
    std::string err;
    if (!platform::lock_memory(&err)) MER_LOG_WARN("mlockall failed: %s (continuing)", err.c_str());
  }
  initialized_ = true;
  return Status::ok();
}

platform::BoardThreads Pipeline::resolve_threads() const {
  const BoardOptions& b = config_.board;
  platform::BoardThreads t = platform::find_board(b.profile).value_or(platform::kBoardGenericX86);
  auto apply = [](platform::ThreadSpec& spec, int core, int prio) {
    if (core != -2) spec.core = core;
    if (prio != -1) spec.priority = prio;
  };
  apply(t.capture, b.capture_core, b.capture_priority);
  apply(t.tracking, b.tracking_core, b.tracking_priority);
  apply(t.output, b.output_core, b.output_priority);
  apply(t.backend, b.backend_core, b.backend_priority);
  return t;
}

bool Pipeline::source_timed_out(std::int64_t last_frame_ns) const {
  return platform::monotonic_now_ns() - last_frame_ns >=
         static_cast<std::int64_t>(config_.pipeline.source_timeout_ms) * 1'000'000;
}

std::string Pipeline::source_timeout_message() const {
  std::string m = camera_.describe() + ": no frame for " +
                  std::to_string(config_.pipeline.source_timeout_ms) +
                  " ms (pipeline.source_timeout_ms)";
  if (!camera_.last_error().is_ok()) m += "; last source error: " + camera_.last_error().message();
  return m;
}

bool Pipeline::reached_max_frames() const {
  return config_.pipeline.max_frames > 0 &&
         stats_.frames_in >= static_cast<std::uint64_t>(config_.pipeline.max_frames);
}

Status Pipeline::run() {
  if (!initialized_) return runtime_error("pipeline: run() before init()");
  const std::int64_t t0 = platform::monotonic_now_ns();
  Status s = camera_.start();
  if (!s.is_ok()) return s;
  stats_.mode = config_.pipeline.lockstep ? "lockstep" : "threaded";
  cpu_start_ns_ = platform::process_cpu_ns();
  cpu_last_ns_ = cpu_start_ns_;
  s = config_.pipeline.lockstep ? run_lockstep() : run_threaded();
  stats_.cpu.process_s = static_cast<double>(platform::process_cpu_ns() - cpu_start_ns_) * kNsToS;
  stats_.cpu.source_s = static_cast<double>(source_cpu_ns_.load()) * kNsToS;
  camera_.stop();
  stats_.source = camera_.counters();
  Status c = output_.close();
  if (const Status k = close_keyframes_csv(); c.is_ok()) c = k;
  (void)culler_->remove_discarded_segments();  // every stage has stopped
  if (c.is_ok()) c = join_segments();
  if (config_.pipeline.final_ba && stats_.frames_processed > 0) run_final_ba();
  const Status k = write_final_keyframes();
  finish_stats(t0);
  if (!s.is_ok()) return s;
  return c.is_ok() ? k : c;
}

Status Pipeline::join_segments() {
  segment_outputs_.clear();
  for (std::size_t i = 0; i < segment_stats_.size(); ++i) {
    if (segment_stats_[i].frames == 0) continue;
    SegmentOutput g;
    g.id = static_cast<std::uint16_t>(i);
    g.frames = segment_stats_[i].frames;
    g.discarded = segment_stats_[i].discarded;
    segment_outputs_.push_back(g);
  }
  // Every stage has stopped: the map is read by nobody else.
  const FinalKeyframesOf finals = [this](std::uint16_t main) {
    return resolve_keyframe_poses(map_->live_keyframe_poses(main), culler_->lineage(),
                                  kept_segment_scales_into(main));
  };
  return join_segment_files(output_dir_, merge_records(), segment_outputs_, main_segment_, finals);
}

std::vector<SegmentMergeRecord> Pipeline::merge_records() const {
  std::vector<SegmentMergeRecord> merges;
  for (const loop::SegmentMergeEvent& e : loop_->totals().merges) {
    merges.push_back(SegmentMergeRecord{e.from, e.into, e.seq, e.sim_into_from});
  }
  return merges;
}

std::vector<double> Pipeline::segment_scales_into_main() const {
  return kept_segment_scales_into(main_segment_);
}

std::vector<double> Pipeline::kept_segment_scales_into(std::uint16_t main) const {
  std::vector<double> scales = segment_scales_into(merge_records(), main, segment_stats_.size());
  for (std::size_t i = 0; i < scales.size(); ++i) {
    if (segment_stats_[i].discarded) scales[i] = 0.0;  // its frames are lost
  }
  return scales;
}

Pipeline::FinishedMap Pipeline::finished_map() {
  return FinishedMap{*map_, *ba_, tracker_->intrinsics()};
}

std::vector<FinalKeyframePose> Pipeline::final_keyframe_poses() const {
  // The main segment's: trajectory.txt's world frame (the other segments have their own).
  if (map_->segment_discarded(main_segment_)) return {};  // no segment kept
  return resolve_keyframe_poses(map_->live_keyframe_poses(main_segment_), culler_->lineage(),
                                segment_scales_into_main());
}

Status Pipeline::write_final_keyframes() const {
  if (output_dir_.empty()) return Status::ok();
  // Every stage has stopped: reading the map here races with nobody.
  // The main segment's keyframes, in trajectory.txt's world frame.
  std::vector<StampedPose> poses;
  if (!map_->segment_discarded(main_segment_)) poses = map_->live_keyframe_poses(main_segment_);
  const std::string path = (std::filesystem::path(output_dir_) / "keyframes_final.txt").string();
  std::FILE* f = std::fopen(path.c_str(), "w");
  if (f == nullptr) return runtime_error("cannot write '" + path + "': " + std::strerror(errno));
  char line[256];
  bool ok = true;
  for (const StampedPose& p : poses) {
    const int len = format_tum_line(line, sizeof line, p.t_ns, p.T_w_c);
    ok = ok && len > 0 &&
         std::fwrite(line, 1, static_cast<std::size_t>(len), f) == static_cast<std::size_t>(len);
  }
  if (std::fclose(f) != 0 || !ok) return runtime_error("error writing '" + path + "'");
  return Status::ok();
}

void Pipeline::finish_stats(std::int64_t t_start_ns) {
  stats_.wall_time_s = static_cast<double>(platform::monotonic_now_ns() - t_start_ns) * kNsToS;
  stats_.pose_source = "tracking";
  stats_.latency = {summarize(*lat_capture_),       summarize(*lat_tracking_),
                    summarize(*lat_output_),        summarize(*lat_end_to_end_),
                    summarize(*lat_keyframe_),      summarize(*lat_local_ba_),
                    summarize(*lat_relocalization_)};
  stats_.tracking_steps.clear();
  for (const auto& l : lat_steps_) stats_.tracking_steps.push_back(summarize(*l));
  stats_.cpu.process = summarize(*lat_cpu_process_);
  stats_.cpu.slam = summarize(*lat_cpu_slam_);
  stats_.map = map_->counters();
  stats_.keyframes = stats_.map.live_keyframes;
  stats_.map_points = stats_.map.live_points;
  stats_.culling = culler_->totals();
  stats_.loop = loop_->totals();
  stats_.tracker = tracker_->counters();
  stats_.focal = tracker_->focal();
  stats_.mapping = builder_->totals();
  stats_.backend = ba_->totals();
  stats_.depth_backend = std::string(builder_->backend_name());
  stats_.backend_depth_edges = ba_->depth_edge_mode();
  stats_.allocs = {allocs_capture_, allocs_tracking_, allocs_output_};
  stats_.segments.clear();
  stats_.first_pose_seq = -1;
  for (std::size_t i = 0; i < segment_stats_.size(); ++i) {
    SegmentStats g = segment_stats_[i];
    if (g.frames == 0) continue;
    if (!g.discarded && (stats_.first_pose_seq < 0 ||
                         g.first_seq < static_cast<std::uint64_t>(stats_.first_pose_seq))) {
      stats_.first_pose_seq = static_cast<std::int64_t>(g.first_seq);
    }
    g.id = static_cast<std::uint16_t>(i);
    g.keyframes = map_->live_keyframe_poses(g.id).size();
    g.trajectory = segment_file_name(g.id, false);
    for (const SegmentOutput& o : segment_outputs_) {
      if (o.id != g.id) continue;
      g.trajectory = o.trajectory;
      g.merged_into = o.merged_into;
      g.merged_at_seq = o.merged_at_seq;
      g.fit_keyframes = o.fit_keyframes;
    }
    g.main = !g.discarded && g.id == main_segment_;
    stats_.segments.push_back(g);
  }
  stats_.tracking_allocs_by_state.clear();
  for (std::size_t i = 0; i < allocs_by_state_.size(); ++i) {
    ThreadAllocs a = allocs_by_state_[i];
    a.thread = frontend::to_string(static_cast<frontend::TrackerState>(i));
    stats_.tracking_allocs_by_state.push_back(a);
  }
}

void Pipeline::run_final_ba() {
  // Every stage has stopped: this thread is the map's only writer now.
  FinalBaStats& f = stats_.final_ba;
  const backend::LocalBaReport rep =
      ba_->optimize_full(tracker_->intrinsics(), config_.backend.full_max_iterations);
  f.ran = rep.ran;
  f.keyframes = rep.keyframes;
  f.points = rep.points;
  f.observations = rep.observations;
  f.iterations = rep.iterations;
  f.ms = rep.ms;
  MER_LOG_INFO("final BA: %d keyframes, %d points, %d observations, %d iterations, %.0f ms",
               rep.keyframes, rep.points, rep.observations, rep.iterations, rep.ms);
}

depth::KeyframeBuildReport Pipeline::build_keyframe(const map::KeyframeJob& job) {
  const std::int64_t t_kf = platform::monotonic_now_ns();
  const depth::KeyframeBuildReport rep = builder_->spin_once(job);
  // (A segment's start is an insertion only: not a keyframe's creation time.)
  if (!rep.segment_start) lat_keyframe_->record(job.seq, t_kf, platform::monotonic_now_ns() - t_kf);
  if (rep.ok && !rep.segment_start) write_keyframe_row(job, rep);
  return rep;
}

Status Pipeline::open_keyframes_csv() {
  if (output_dir_.empty()) return Status::ok();
  keyframes_csv_path_ = (std::filesystem::path(output_dir_) / "keyframes.csv").string();
  keyframes_csv_ = std::fopen(keyframes_csv_path_.c_str(), "w");
  if (keyframes_csv_ == nullptr) {
    return runtime_error("cannot write '" + keyframes_csv_path_ + "': " + std::strerror(errno));
  }
  std::fputs(
      "seq,t_s,segment,keypoints,tracked,free,no_match,low_parallax,few_views,rejected,depth,"
      "new_points,neighbours\n",
      keyframes_csv_);
  return Status::ok();
}

void Pipeline::write_keyframe_row(const map::KeyframeJob& job,
                                  const depth::KeyframeBuildReport& rep) {
  if (keyframes_csv_ == nullptr) return;
  const depth::KeypointFates& f = rep.fates;
  char t_s[32];
  format_seconds(t_s, sizeof t_s, job.t_ns);
  std::fprintf(keyframes_csv_, "%llu,%s,%u,%d,%d,%d,%d,%d,%d,%d,%d,%d,%d\n",
               static_cast<unsigned long long>(job.seq), t_s, unsigned{job.segment},
               job.num_keypoints, rep.tracked_observations, f.free, f.no_match, f.low_parallax,
               f.few_views, f.rejected, f.depth, rep.new_points, rep.neighbours);
}

Status Pipeline::close_keyframes_csv() {
  if (keyframes_csv_ == nullptr) return Status::ok();
  const bool bad = std::ferror(keyframes_csv_) != 0;
  const bool closed = std::fclose(keyframes_csv_) == 0;
  keyframes_csv_ = nullptr;
  if (bad || !closed) return runtime_error("error writing '" + keyframes_csv_path_ + "'");
  return Status::ok();
}

void Pipeline::optimize_and_cull(map::KeyframeId ba_kf, const geometry::Pinhole& K,
                                 std::uint64_t seq, map::KeyframeId cull_kf) {
  if (ba_kf != map::kNoId) {
    const std::int64_t t_ba = platform::monotonic_now_ns();
    const backend::LocalBaReport ba = ba_->spin_once(ba_kf, K);
    if (ba.ran) {
      lat_local_ba_->record(seq, t_ba, platform::monotonic_now_ns() - t_ba);
      MER_LOG_DEBUG(
          "local BA at frame %llu: %d + %d fixed keyframes, %d points, %d observations, "
          "%d outliers, %d points culled, %d iterations, cost %.4g -> %.4g, %.1f ms%s%s",
          static_cast<unsigned long long>(seq), ba.keyframes, ba.fixed_keyframes, ba.points,
          ba.observations, ba.outliers, ba.culled_points, ba.iterations, ba.initial_cost,
          ba.final_cost, ba.ms, ba.aborted ? ", aborted" : (ba.timed_out ? ", timed out" : ""),
          ba.resolved ? ", solved again" : (ba.resolve_skipped ? ", second solve skipped" : ""));
    }
  }
  (void)culler_->spin_once(cull_kf);
}

void Pipeline::create_keyframe(const map::KeyframeJob& job) {
  const depth::KeyframeBuildReport rep = build_keyframe(job);
  if (rep.segment_start) {  // a segment's start: nothing to optimize or cull yet,
    (void)culler_->remove_discarded_segments();  // but failed starts before it go
    return;
  }
  // Culling frees slots for the next keyframes; after a refused insertion (map full) it
  // still runs around the newest keyframe.
  optimize_and_cull(rep.ok ? rep.keyframe : map::kNoId, job.K, job.seq,
                    rep.ok ? rep.keyframe : map_->newest_keyframe());
  if (rep.ok && map_->keyframe_is_live(rep.keyframe)) (void)loop_->spin_once(rep.keyframe, job.K);
}

frontend::RelocalizationHint Pipeline::relocalize(const frontend::RelocalizationRequest& req) {
  loop::RelocQuery q;
  q.seq = req.seq;
  q.t_ns = req.t_ns;
  q.keypoints = std::span<const features::Keypoint>(req.keypoints.data(), req.count);
  q.descriptors = std::span<const features::Descriptor>(req.descriptors.data(), req.count);
  q.K = req.K;
  const std::int64_t t0 = platform::monotonic_now_ns();
  const loop::RelocResult res = relocalizer_->spin_once(q);
  lat_relocalization_->record(req.seq, t0, platform::monotonic_now_ns() - t0);
  RelocalizationStats& st = stats_.relocalization;
  ++st.attempts;
  st.candidates += static_cast<std::uint64_t>(res.candidates_tried);
  if (res.timed_out) ++st.timed_out;
  st.sum_ms += res.ms;
  st.max_ms = std::max(st.max_ms, res.ms);
  frontend::RelocalizationHint hint;
  if (res.success) {
    ++st.successes;
    st.last_success_seq = static_cast<std::int64_t>(req.seq);
    hint.valid = true;
    hint.seq = req.seq;
    hint.T_c_w = res.T_c_w;
    hint.keyframe = res.keyframe;
    hint.generation = res.generation;
    MER_LOG_DEBUG("relocalizer: frame %llu found against keyframe %u (%d inliers, %.1f ms)",
                  static_cast<unsigned long long>(req.seq), res.keyframe, res.inliers, res.ms);
  }
  return hint;
}

void Pipeline::count_state_allocs(const frontend::TrackingResult& r, std::uint64_t allocations) {
  // The frame that built the map is counted with initialization, the work it did.
  const frontend::TrackerState st = r.state == frontend::TrackState::kTracked && !r.steady
                                        ? frontend::TrackerState::kInitializing
                                        : r.tracker_state;
  ThreadAllocs& a = allocs_by_state_[static_cast<std::size_t>(st)];
  a.allocations += allocations;
  ++a.frames;
}

void Pipeline::count_result(const frontend::TrackingResult& r) {
  ++stats_.frames_processed;
  if (r.state != frontend::TrackState::kTracked) ++stats_.frames_lost;
  if (r.discarded_start && r.discarded_segment < segment_stats_.size()) {
    // A failed start: the frames it tracked count as lost (its file is dropped at the end).
    SegmentStats& g = segment_stats_[r.discarded_segment];
    if (!g.discarded) {
      g.discarded = true;
      stats_.frames_lost += g.frames;
      stats_.frames_discarded += g.frames;
    }
  }
  if (r.state == frontend::TrackState::kTracked && r.segment < segment_stats_.size()) {
    SegmentStats& g = segment_stats_[r.segment];
    if (g.frames++ == 0) g.first_seq = r.seq;
    g.last_seq = r.seq;
  }
  if (r.steady) ++stats_.steady_frames;
  if (r.relocalized && r.reloc_keyframe_t_ns != 0) {
    std::vector<RelocalizationEvent>& ev = stats_.relocalization.events;
    if (ev.size() < ev.capacity()) {
      ev.push_back(RelocalizationEvent{r.seq, r.t_ns, r.reloc_keyframe_t_ns, r.segment, r.T_rkf_c,
                                       r.reloc_confirmed, r.reloc_found_ratio});
    } else {
      ++stats_.relocalization.events_dropped;
    }
  }
  for (std::size_t i = 0; i < lat_steps_.size(); ++i) {
    if (r.steady) lat_steps_[i]->record(r.seq, r.t_ns, r.step_ns[i]);
  }
}

void Pipeline::record_cpu(std::uint64_t seq) {
  const std::int64_t now = platform::process_cpu_ns();
  const std::int64_t source = source_cpu_ns_.load(std::memory_order_relaxed);
  const std::int64_t d_process = now - cpu_last_ns_;
  const std::int64_t d_source = source - cpu_last_source_ns_;
  lat_cpu_process_->record(seq, now, d_process);
  lat_cpu_slam_->record(seq, now, std::max<std::int64_t>(0, d_process - d_source));
  cpu_last_ns_ = now;
  cpu_last_source_ns_ = source;
}

void Pipeline::add_source_cpu(std::int64_t cpu_ns) {
  // Single writer (the capture thread, or the lockstep loop): load + store.
  source_cpu_ns_.store(
      source_cpu_ns_.load(std::memory_order_relaxed) + std::max<std::int64_t>(0, cpu_ns),
      std::memory_order_relaxed);
}

// ---- Lockstep ------------------------------------------------------------------------

Status Pipeline::run_lockstep() {
  platform::LockstepClock clock;
  const auto timeout_ns =
      static_cast<std::int64_t>(config_.pipeline.acquire_timeout_ms) * 1'000'000;
  const auto warmup = static_cast<std::uint64_t>(config_.telemetry.warmup_frames);
  std::int64_t last_frame_ns = platform::monotonic_now_ns();
  while (true) {
    if (stop_.load(std::memory_order_relaxed)) {
      stats_.end_reason = "signal";
      break;
    }
    if (reached_max_frames()) {
      stats_.end_reason = "max_frames";
      break;
    }
    // capture
    hal::FrameHandle frame;
    platform::alloc::Scope cap_allocs;
    const hal::AcquireStatus st = camera_.acquire(frame, timeout_ns);
    const std::uint64_t cap_delta = cap_allocs.delta();
    if (st == hal::AcquireStatus::kEndOfStream) {
      stats_.end_reason = "end_of_stream";
      break;
    }
    if (st == hal::AcquireStatus::kTimeout) {
      ++stats_.acquire_timeouts;
      if (source_timed_out(last_frame_ns)) {
        stats_.end_reason = "source_error";
        return input_error(source_timeout_message());
      }
      continue;
    }
    if (st != hal::AcquireStatus::kFrame) {
      stats_.end_reason = "source_error";
      const Status& e = camera_.last_error();
      return input_error(e.is_ok() ? camera_.describe() + ": acquire failed" : e.message());
    }
    last_frame_ns = platform::monotonic_now_ns();
    ++stats_.frames_in;
    clock.set_ns(frame->t_ns);
    const bool steady = stats_.frames_in > warmup;
    lat_capture_->record(frame->seq, frame->t_ready_ns - frame->produce_ns, frame->produce_ns);
    add_source_cpu(frame->produce_cpu_ns);

    // tracking
    platform::alloc::Scope trk_allocs;
    const std::int64_t t_trk = platform::monotonic_now_ns();
    frontend::TrackingResult r = tracker_->spin_once(*frame);
    const std::int64_t t_done = platform::monotonic_now_ns();
    r.t_ready_ns = frame->t_ready_ns;
    r.stage_ns[static_cast<std::size_t>(frontend::StageId::kCapture)] = frame->produce_ns;
    r.stage_ns[static_cast<std::size_t>(frontend::StageId::kQueue)] = t_trk - frame->t_ready_ns;
    r.stage_ns[static_cast<std::size_t>(frontend::StageId::kTracking)] = t_done - t_trk;
    lat_tracking_->record(r.seq, t_trk, t_done - t_trk);
    lat_end_to_end_->record(r.seq, frame->t_ready_ns, t_done - frame->t_ready_ns);
    const std::uint64_t trk_delta = trk_allocs.delta();
    count_result(r);
    // relocalization (inline in lockstep: deterministic); its pose predicts the next frame
    if (r.relocalization_request && relocalizer_) {
      tracker_->fill_relocalization_request(*frame, reloc_request_);
      tracker_->set_relocalization_hint(relocalize(reloc_request_));
    }
    // keyframe creation (inline in lockstep: deterministic)
    if (r.keyframe_job) {
      map::KeyframeJob& job = jobs_[0];
      tracker_->fill_keyframe_job(*frame, job);
      create_keyframe(job);
    }
    frame.reset();

    // output
    platform::alloc::Scope out_allocs;
    const std::int64_t out_ns = output_.spin_once(r, t_done - r.t_ready_ns);
    lat_output_->record(r.seq, t_done, out_ns);
    record_cpu(r.seq);
    if (steady) {
      allocs_capture_.allocations += cap_delta;
      ++allocs_capture_.frames;
    }
    if (steady && r.steady) {
      allocs_tracking_.allocations += trk_delta;
      ++allocs_tracking_.frames;
    }
    if (steady) count_state_allocs(r, trk_delta);
    if (steady) {
      allocs_output_.allocations += out_allocs.delta();
      ++allocs_output_.frames;
    }
  }
  return Status::ok();
}

// ---- Threaded --------------------------------------------------------------------------

}  // namespace mer::pipeline
