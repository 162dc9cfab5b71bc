// Threaded mode (Pipeline::run_threaded): one pinned thread per stage, joined by lock-free
// rings and wake-ups. The stages and their priorities are described in pipeline.h.
#include <chrono>
#include <thread>

#include "pipeline/pipeline.h"
#include "platform/alloc_counter.h"
#include "platform/clock.h"
#include "platform/log_ring.h"
#include "platform/notifier.h"
#include "platform/overwrite_ring.h"
#include "platform/rt_thread.h"
#include "platform/spsc_ring.h"

namespace mer::pipeline {
namespace {

constexpr std::int64_t kIdleWaitNs = 20'000'000;     // consumer re-checks stop flags this often
constexpr std::int64_t kPoolRetryNs = 1'000'000;     // back-off when every buffer is in use
constexpr std::int64_t kBackendRetryNs = 1'000'000;  // depth thread: back-end queue full
constexpr double kNsToS = 1e-9;

/// What the depth thread hands to the back-end thread after each keyframe job.
struct BackendJob {
  map::KeyframeId kf = map::kNoId;                  ///< inserted keyframe, or the newest one
  map::Generation generation = map::kNoGeneration;  ///< kf's occupant when queued
  bool inserted = false;                            ///< kf was inserted by this job: run BA
  std::uint64_t seq = 0;                            ///< frame of the job (latency trace)
  geometry::Pinhole K;                              ///< intrinsics the frame was tracked with
};

/// Back-end work after draining its queue: local BA around the newest inserted keyframe,
/// culling around the newest keyframe of any job.
struct BackendBatch {
  BackendJob ba;    ///< newest job that inserted a keyframe (ba.inserted false: none)
  BackendJob cull;  ///< newest job
  int skipped = 0;  ///< inserted keyframes drained without their own BA run
};

/// Generic consumer loop of a threaded stage: pops inputs with `pop(In&)` and hands them to
/// `work(In&)`; sleeps on `wake` when idle; ends when `upstream_done` is set and the input
/// is drained.
template <typename In, typename PopFn, typename WorkFn>
void consume_loop(platform::Notifier& wake, const std::atomic<bool>& upstream_done, PopFn&& pop,
                  WorkFn&& work) {
  In item{};
  while (true) {
    const std::uint32_t epoch = wake.epoch();
    if (pop(item)) {
      work(item);
      continue;
    }
    if (upstream_done.load(std::memory_order_acquire)) {
      if (pop(item)) {  // a last item pushed before the flag
        work(item);
        continue;
      }
      return;
    }
    (void)wake.wait_for(epoch, kIdleWaitNs);
  }
}

}  // namespace

/// What the stage threads of one threaded run share: the rings between them, their wake-ups
/// and end-of-input flags, the relocalization mailbox. It lives on run_threaded's stack frame;
/// the threads are joined before it unwinds. One member function per thread.
struct Pipeline::Threaded {
  explicit Threaded(Pipeline& pipeline)
      : p(pipeline),
        timeout_ns(static_cast<std::int64_t>(pipeline.config_.pipeline.acquire_timeout_ms) *
                   1'000'000),
        warmup(static_cast<std::uint64_t>(pipeline.config_.telemetry.warmup_frames)),
        pool(pipeline.camera_.pool()),
        loop_enabled(pipeline.config_.loop.enabled) {
    for (std::uint32_t i = 0; i < kKeyframeJobs; ++i) (void)free_ring->try_push(i);
  }

  void capture();   ///< frames from the source into the capture ring (drop-oldest)
  void tracking();  ///< tracking, keyframe jobs and relocalization requests
  void depth();     ///< keyframe creation and relocalization (low priority)
  void backend();   ///< local BA and culling around the newest keyframe
  void loop();      ///< loop detection and correction (lowest priority)
  void output();    ///< the output files
  /// CPU each stage thread used, s (written by the thread as it ends; read after the joins).
  double cpu_capture_s = 0.0, cpu_tracking_s = 0.0, cpu_depth_s = 0.0, cpu_backend_s = 0.0,
         cpu_loop_s = 0.0, cpu_output_s = 0.0;

  Pipeline& p;
  const std::int64_t timeout_ns;
  const std::uint64_t warmup;
  hal::FramePool& pool;
  const bool loop_enabled;
  std::unique_ptr<platform::OverwriteRing<std::uint32_t, kCaptureRingSize>> capture_ring =
      std::make_unique<platform::OverwriteRing<std::uint32_t, kCaptureRingSize>>();
  std::unique_ptr<platform::SpscRing<frontend::TrackingResult, kResultRingSize>> result_ring =
      std::make_unique<platform::SpscRing<frontend::TrackingResult, kResultRingSize>>();
  platform::Notifier capture_wake;
  platform::Notifier result_wake;
  std::unique_ptr<platform::SpscRing<std::uint32_t, 2 * kKeyframeJobs>> job_ring =
      std::make_unique<platform::SpscRing<std::uint32_t, 2 * kKeyframeJobs>>();
  std::unique_ptr<platform::SpscRing<std::uint32_t, 2 * kKeyframeJobs>> free_ring =
      std::make_unique<platform::SpscRing<std::uint32_t, 2 * kKeyframeJobs>>();
  platform::Notifier job_wake;
  std::unique_ptr<platform::SpscRing<BackendJob, kBackendQueue>> backend_ring =
      std::make_unique<platform::SpscRing<BackendJob, kBackendQueue>>();
  platform::Notifier backend_wake;
  std::unique_ptr<platform::SpscRing<BackendJob, kLoopQueue>> loop_ring =
      std::make_unique<platform::SpscRing<BackendJob, kLoopQueue>>();
  platform::Notifier loop_wake;
  std::atomic<bool> capture_done{false};
  std::atomic<bool> tracking_done{false};
  std::atomic<bool> depth_done{false};
  std::atomic<bool> backend_done{false};
  Status capture_status;
  // Relocalization mailbox: the tracking thread posts a lost frame's features (reloc_request_),
  // the depth thread answers with a pose hint, the tracking thread takes it before its next
  // frame. One request in flight; a lost frame that finds it busy is not posted.
  enum : int { kRelocIdle = 0, kRelocPosted = 1, kRelocAnswered = 2 };
  std::atomic<int> reloc_state{kRelocIdle};
  frontend::RelocalizationHint reloc_answer;
  static constexpr std::uint32_t kRelocWork = 0xFFFFFFFFU;  // depth-thread work item: relocalize
  std::uint64_t tracked_frames = 0;                         // tracking thread
  std::uint64_t written_frames = 0;                         // output thread
};

void Pipeline::Threaded::capture() {
  std::int64_t last_frame_ns = platform::monotonic_now_ns();
  while (true) {
    if (p.stop_.load(std::memory_order_relaxed)) {
      p.stats_.end_reason = "signal";
      break;
    }
    if (p.reached_max_frames()) {
      p.stats_.end_reason = "max_frames";
      break;
    }
    platform::alloc::Scope allocs;
    hal::FrameHandle frame;
    const hal::AcquireStatus st = p.camera_.acquire(frame, timeout_ns);
    if (st == hal::AcquireStatus::kEndOfStream) {
      p.stats_.end_reason = "end_of_stream";
      break;
    }
    if (st == hal::AcquireStatus::kTimeout) {
      ++p.stats_.acquire_timeouts;
      if (p.source_timed_out(last_frame_ns)) {
        p.stats_.end_reason = "source_error";
        capture_status = input_error(p.source_timeout_message());
        break;
      }
      continue;
    }
    if (st == hal::AcquireStatus::kPoolEmpty) {
      ++p.stats_.pool_exhausted;
      std::this_thread::sleep_for(std::chrono::nanoseconds(kPoolRetryNs));
      continue;
    }
    if (st != hal::AcquireStatus::kFrame) {
      p.stats_.end_reason = "source_error";
      const Status& e = p.camera_.last_error();
      capture_status =
          input_error(e.is_ok() ? p.camera_.describe() + ": acquire failed" : e.message());
      break;
    }
    last_frame_ns = platform::monotonic_now_ns();
    ++p.stats_.frames_in;
    p.lat_capture_->record(frame->seq, frame->t_ready_ns - frame->produce_ns, frame->produce_ns);
    p.add_source_cpu(frame->produce_cpu_ns);
    // Drop-oldest: a full ring hands back the oldest frame; its buffer returns to the pool.
    if (const auto evicted = capture_ring->push(frame.release_raw())) {
      hal::FrameHandle dropped = pool.adopt(*evicted);
      ++p.stats_.frames_dropped;
    }
    capture_wake.notify();
    if (p.stats_.frames_in > warmup) {
      p.allocs_capture_.allocations += allocs.delta();
      ++p.allocs_capture_.frames;
    }
  }
  capture_done.store(true, std::memory_order_release);
  capture_wake.notify_all();
}

void Pipeline::Threaded::tracking() {
  consume_loop<std::uint32_t>(
      capture_wake, capture_done, [&](std::uint32_t& idx) { return capture_ring->try_pop(idx); },
      [&](std::uint32_t& idx) {
        platform::alloc::Scope allocs;
        hal::FrameHandle frame = pool.adopt(idx);
        if (reloc_state.load(std::memory_order_acquire) == kRelocAnswered) {
          p.tracker_->set_relocalization_hint(reloc_answer);
          reloc_state.store(kRelocIdle, std::memory_order_release);
        }
        const std::int64_t t_trk = platform::monotonic_now_ns();
        frontend::TrackingResult r = p.tracker_->spin_once(*frame);
        const std::int64_t t_done = platform::monotonic_now_ns();
        r.t_ready_ns = frame->t_ready_ns;
        r.stage_ns[static_cast<std::size_t>(frontend::StageId::kCapture)] = frame->produce_ns;
        r.stage_ns[static_cast<std::size_t>(frontend::StageId::kQueue)] = t_trk - frame->t_ready_ns;
        r.stage_ns[static_cast<std::size_t>(frontend::StageId::kTracking)] = t_done - t_trk;
        p.lat_tracking_->record(r.seq, t_trk, t_done - t_trk);
        p.lat_end_to_end_->record(r.seq, frame->t_ready_ns, t_done - frame->t_ready_ns);
        const std::uint64_t trk_delta = allocs.delta();
        p.count_result(r);
        p.record_cpu(r.seq);
        if (r.relocalization_request && p.relocalizer_) {
          if (reloc_state.load(std::memory_order_acquire) == kRelocIdle) {
            p.tracker_->fill_relocalization_request(*frame, p.reloc_request_);
            reloc_state.store(kRelocPosted, std::memory_order_release);
            job_wake.notify();
          } else {
            ++p.stats_.relocalization.skipped_busy;
          }
        }
        if (r.keyframe_job) {
          std::uint32_t slot = 0;
          if (free_ring->try_pop(slot)) {
            p.tracker_->fill_keyframe_job(*frame, p.jobs_[slot]);
            (void)job_ring->try_push(slot);  // cannot be full: slots are fewer than its size
            job_wake.notify();
          } else {
            p.tracker_->keyframe_not_queued();
            ++p.stats_.keyframes_deferred;
          }
        }
        frame.reset();
        if (!result_ring->try_push(r)) {
          ++p.stats_.output_overflows;
          MER_LOG_WARN("output ring full: result of frame %llu not written",
                       static_cast<unsigned long long>(r.seq));
        }
        result_wake.notify();
        if (++tracked_frames > warmup) {
          if (r.steady) {
            p.allocs_tracking_.allocations += trk_delta;
            ++p.allocs_tracking_.frames;
          }
          p.count_state_allocs(r, trk_delta);
        }
      });
  p.tracker_->stop_reading();  // queued keyframes may reuse slots freed after its last frame
  tracking_done.store(true, std::memory_order_release);
  result_wake.notify_all();
  job_wake.notify_all();
}

// Depth thread (low priority): keyframe creation proper, then the back end is told.
void Pipeline::Threaded::depth() {
  consume_loop<std::uint32_t>(
      job_wake, tracking_done,
      [&](std::uint32_t& slot) {
        if (job_ring->try_pop(slot)) return true;
        if (reloc_state.load(std::memory_order_acquire) != kRelocPosted) return false;
        slot = kRelocWork;
        return true;
      },
      [&](std::uint32_t& slot) {
        // The relocalizer holds nothing of the map between its runs.
        if (p.reloc_reader_ >= 0) p.map_->reader_quiescent(p.reloc_reader_);
        if (slot == kRelocWork) {
          reloc_answer = p.relocalize(p.reloc_request_);
          if (p.reloc_reader_ >= 0) p.map_->reader_quiescent(p.reloc_reader_);
          reloc_state.store(kRelocAnswered, std::memory_order_release);
          return;
        }
        const map::KeyframeJob& job = p.jobs_[slot];
        const depth::KeyframeBuildReport rep = p.build_keyframe(job);
        if (rep.segment_start) {  // a segment's start: nothing to optimize or cull yet,
          (void)p.culler_->remove_discarded_segments();  // but failed starts before it go
          (void)free_ring->try_push(slot);
          return;
        }
        BackendJob b;
        b.inserted = rep.ok;
        // After a refused insertion (map full) culling still runs, around the newest.
        b.kf = rep.ok ? rep.keyframe : p.map_->newest_keyframe();
        b.generation = p.map_->keyframe_generation(b.kf);
        b.seq = job.seq;
        b.K = job.K;
        (void)free_ring->try_push(slot);
        // The back end drains its whole queue at each wake-up, so a full queue means it is
        // busy for a moment; this thread is not real-time and may wait (never while it
        // holds the map's writer lock, so the back end cannot be waiting for it).
        while (!backend_ring->try_push(b)) {
          std::this_thread::sleep_for(std::chrono::nanoseconds(kBackendRetryNs));
        }
        // A newer keyframe in the map pre-empts the local BA in progress: its window is
        // stale, and the run around the new keyframe can start now. (Not when the tracker
        // queues the job: the new keyframe is not in the map until depth inference is
        // done, so aborting then would only throw away optimization.)
        if (rep.ok) {
          p.ba_->request_abort();
          p.loop_ba_->request_abort();  // as documented: a new keyframe pre-empts the full BA
        }
        backend_wake.notify();
      });
  if (p.reloc_reader_ >= 0) p.map_->release_reader(p.reloc_reader_);
  depth_done.store(true, std::memory_order_release);
  backend_wake.notify_all();
}

// Back-end thread (high priority, below tracking): local BA around the newest keyframe
// inserted, then culling. Keyframes queued behind one another need one run only.
void Pipeline::Threaded::backend() {
  consume_loop<BackendBatch>(
      backend_wake, depth_done,
      [&](BackendBatch& batch) {
        BackendJob j;
        if (!backend_ring->try_pop(j)) return false;
        batch = BackendBatch{};
        do {
          if (j.inserted) {
            if (batch.ba.inserted) ++batch.skipped;
            batch.ba = j;
          }
          batch.cull = j;
        } while (backend_ring->try_pop(j));
        return true;
      },
      [&](BackendBatch& batch) {
        p.stats_.backend_coalesced += static_cast<std::uint64_t>(batch.skipped);
        // Ids are checked by generation: the culling of an earlier pass may have removed a
        // keyframe queued behind (not the newest: the map never removes that one).
        const bool ba_live =
            batch.ba.inserted && p.map_->keyframe_generation(batch.ba.kf) == batch.ba.generation;
        const bool cull_live = p.map_->keyframe_generation(batch.cull.kf) == batch.cull.generation;
        p.optimize_and_cull(ba_live ? batch.ba.kf : map::kNoId, batch.ba.K, batch.ba.seq,
                            cull_live ? batch.cull.kf : p.map_->newest_keyframe());
        // Loop detection and correction run on their own thread, after the local BA the
        // keyframe had; a full queue (the loop thread far behind) skips the keyframe.
        if (loop_enabled && ba_live &&
            p.map_->keyframe_generation(batch.ba.kf) == batch.ba.generation) {
          if (loop_ring->try_push(batch.ba)) {
            loop_wake.notify();
          } else {
            ++p.stats_.loop_queue_full;
          }
        }
      });
  backend_done.store(true, std::memory_order_release);
  loop_wake.notify_all();
}

// Loop-closure thread (lowest priority): detection, correction and the full BA after a
// loop, writing the map under its writer lock as every writer does.
void Pipeline::Threaded::loop() {
  consume_loop<BackendJob>(
      loop_wake, backend_done, [&](BackendJob& j) { return loop_ring->try_pop(j); },
      [&](BackendJob& j) {
        if (p.map_->keyframe_generation(j.kf) == j.generation) (void)p.loop_->spin_once(j.kf, j.K);
      });
}

void Pipeline::Threaded::output() {
  consume_loop<frontend::TrackingResult>(
      result_wake, tracking_done,
      [&](frontend::TrackingResult& r) { return result_ring->try_pop(r); },
      [&](frontend::TrackingResult& r) {
        platform::alloc::Scope allocs;
        const std::int64_t t0 = platform::monotonic_now_ns();
        const std::int64_t out_ns = p.output_.spin_once(
            r, r.stage_ns[static_cast<std::size_t>(frontend::StageId::kQueue)] +
                   r.stage_ns[static_cast<std::size_t>(frontend::StageId::kTracking)]);
        p.lat_output_->record(r.seq, t0, out_ns);
        if (++written_frames > warmup) {
          p.allocs_output_.allocations += allocs.delta();
          ++p.allocs_output_.frames;
        }
      });
}

Status Pipeline::run_threaded() {
  const platform::BoardThreads threads = resolve_threads();
  Threaded run(*this);
  platform::RtThread output_thread;
  platform::RtThread loop_thread;
  platform::RtThread backend_thread;
  platform::RtThread depth_thread;
  platform::RtThread tracking_thread;
  platform::RtThread capture_thread;
  // Start consumers first so the capture ring is drained from the first frame.
  // Each body ends by reading its thread's CPU clock (summary.json threads[].cpu_s).
  auto timed = [](auto body, double& cpu_s) {
    return [body, &cpu_s] {
      body();
      cpu_s = static_cast<double>(platform::thread_cpu_ns()) * kNsToS;
    };
  };
  const bool ok =
      output_thread.start(threads.output, timed([&run] { run.output(); }, run.cpu_output_s)) &&
      loop_thread.start(threads.loop, timed([&run] { run.loop(); }, run.cpu_loop_s)) &&
      backend_thread.start(threads.backend, timed([&run] { run.backend(); }, run.cpu_backend_s)) &&
      depth_thread.start(threads.depth, timed([&run] { run.depth(); }, run.cpu_depth_s)) &&
      tracking_thread.start(threads.tracking,
                            timed([&run] { run.tracking(); }, run.cpu_tracking_s)) &&
      capture_thread.start(threads.capture, timed([&run] { run.capture(); }, run.cpu_capture_s));
  if (!ok) {
    run.capture_done.store(true);
    run.capture_wake.notify_all();
    run.tracking_done.store(true);
    run.result_wake.notify_all();
    run.job_wake.notify_all();
    run.depth_done.store(true);
    run.backend_wake.notify_all();
    run.backend_done.store(true);
    run.loop_wake.notify_all();
  }
  // Shutdown order: capture ends -> tracking drains -> depth drains -> back end drains ->
  // loop closure drains.
  capture_thread.join();
  tracking_thread.join();
  depth_thread.join();
  backend_thread.join();
  loop_thread.join();
  output_thread.join();
  if (!ok) return runtime_error("pipeline: could not start the stage threads");

  struct Placed {
    const platform::ThreadSpec* spec;
    const platform::RtThread* thread;
    double cpu_s;
  };
  const Placed placed[] = {{&threads.capture, &capture_thread, run.cpu_capture_s},
                           {&threads.tracking, &tracking_thread, run.cpu_tracking_s},
                           {&threads.output, &output_thread, run.cpu_output_s},
                           {&threads.depth, &depth_thread, run.cpu_depth_s},
                           {&threads.backend, &backend_thread, run.cpu_backend_s},
                           {&threads.loop, &loop_thread, run.cpu_loop_s}};
  for (const Placed& t : placed) {
    stats_.threads.push_back(ThreadPlacement{std::string(t.spec->name), t.spec->core,
                                             t.spec->priority, t.thread->report().fully_applied(),
                                             t.thread->report().warning, t.cpu_s});
  }
  return run.capture_status;
}

}  // namespace mer::pipeline
