// The tracking stage per frame (extract + query + match + pose + decide) at 640x480 with
// 1000 features on one core, over a rendered room_orbit sequence. RGB-D mode so every frame
// is tracked from the first one (the steps and their cost are the same as monocular
// tracking). Keyframe creation and local BA run between frames, outside the timing, as they
// run on another thread in mer_slam. Counters: per-frame p50/p99 and per-step means (ms),
// heap allocations per tracked frame. bm_local_ba: the local BA per keyframe (see there);
// bm_local_ba_abort: the true latency of its abort request, from a second thread.
// bm_tracking_kidnap: the tracking stage on the frames of a kidnap (lost, relocalizing, and
// tracked again from the relocalizer's pose), per tracker state; the relocalizer itself runs
// on another thread in mer_slam and is timed apart.
#include <algorithm>
#include <array>
#include <atomic>
#include <chrono>
#include <memory>
#include <random>
#include <string>
#include <thread>
#include <vector>

#include <benchmark/benchmark.h>

#include "backend/local_ba.h"
#include "depth/keyframe_builder.h"
#include "frontend/tracker.h"
#include "hal/synthetic/synthetic_camera.h"
#include "loop/keyframe_database.h"
#include "loop/relocalizer.h"
#include "platform/alloc_counter.h"
#include "platform/clock.h"

namespace {

using namespace mer;  // NOLINT(google-build-using-namespace): benchmark file

constexpr int kFrames = 240;  // 8 s of room_orbit at 30 Hz
constexpr double kFps = 30.0;
constexpr double kNsToMs = 1e-6;

struct Sequence {
  std::vector<hal::Frame> frames;
  geometry::Pinhole K;
  int width = 0;
  int height = 0;
};

Sequence render_sequence(const char* scenario) {
  Sequence s;
  hal::SyntheticOptions o;
  o.num_frames = kFrames;
  hal::SyntheticCamera cam(scenario, o, false);
  (void)cam.open(4);
  const auto& k = cam.intrinsics();
  s.K = {k.fx, k.fy, k.cx, k.cy};
  s.width = k.width;
  s.height = k.height;
  for (int i = 0; i < kFrames; ++i) {
    hal::Frame f;
    f.seq = static_cast<std::uint64_t>(i);
    f.t_ns = static_cast<std::int64_t>(i / kFps * 1e9);
    f.gray.create(k.height, k.width, CV_8UC1);
    f.depth.create(k.height, k.width, CV_32FC1);
    f.T_w_c_gt = cam.sample_at(i / kFps).T_w_c;
    f.has_ground_truth = true;
    cam.render(f.T_w_c_gt, f.gray, &f.depth, static_cast<std::uint64_t>(i));
    s.frames.push_back(f);
  }
  return s;
}

// room_orbit (tracking, RGB-D local BA). Monocular local BA runs on room_loop: monocular
// initialization on room_orbit waits for a confident two-view pair (frame 165-279 with the
// default seeds), past the end of this short sequence; room_loop initializes at frame ~20.
const Sequence& sequence(bool mono = false) {
  static const Sequence kOrbit = render_sequence("room_orbit");
  static const Sequence kLoop = render_sequence("room_loop");
  return mono ? kLoop : kOrbit;
}

double percentile(std::vector<double> v, double q) {
  if (v.empty()) return 0.0;
  std::sort(v.begin(), v.end());
  return v[static_cast<std::size_t>(q * static_cast<double>(v.size() - 1))];
}

void bm_tracking(benchmark::State& state) {
  const Sequence& seq = sequence();
  std::vector<double> frame_ms;
  std::array<double, static_cast<std::size_t>(frontend::TrackStep::kCount)> step_sum{};
  std::uint64_t allocs = 0;
  std::uint64_t tracked = 0;
  for (auto _ : state) {
    state.PauseTiming();
    map::MapOptions mo;
    mo.max_keyframes = 128;
    mo.max_points = 50000;
    auto map = std::make_unique<map::Map>(mo);
    frontend::Tracker tracker(frontend::TrackingOptions{}, *map, seq.K, seq.width, seq.height,
                              SensorMode::kRgbd, false);
    (void)tracker.init();
    const backend::LocalBaOptions ba_opts;
    depth::KeyframeBuilder builder(depth::DepthOptions{}, SensorMode::kRgbd, *map,
                                   tracker.level_sigma2(), ba_opts.depth_sigma_rel);
    (void)builder.init();
    backend::LocalBundleAdjuster ba(ba_opts, *map, tracker.level_sigma2(), true, true);
    map::KeyframeJob job;
    job.reserve(tracker.max_keypoints(), seq.width, seq.height);
    for (const hal::Frame& f : seq.frames) {
      state.ResumeTiming();
      const std::uint64_t a0 = platform::alloc::thread_allocations();
      const std::int64_t t0 = platform::monotonic_now_ns();
      const frontend::TrackingResult r = tracker.spin_once(f);
      const std::int64_t t1 = platform::monotonic_now_ns();
      const std::uint64_t a1 = platform::alloc::thread_allocations();
      state.PauseTiming();
      if (r.steady) {
        frame_ms.push_back(static_cast<double>(t1 - t0) * kNsToMs);
        for (std::size_t s = 0; s < step_sum.size(); ++s) step_sum[s] += r.step_ns[s] * kNsToMs;
        allocs += a1 - a0;
        ++tracked;
      }
      if (r.keyframe_job) {
        tracker.fill_keyframe_job(f, job);
        const depth::KeyframeBuildReport rep = builder.spin_once(job);
        if (rep.ok) (void)ba.spin_once(rep.keyframe, job.K);
      }
    }
    state.ResumeTiming();
  }
  state.counters["frames"] = static_cast<double>(tracked);
  state.counters["p50_ms"] = percentile(frame_ms, 0.5);
  state.counters["p99_ms"] = percentile(frame_ms, 0.99);
  const double n = tracked > 0 ? static_cast<double>(tracked) : 1.0;
  for (std::size_t s = 0; s < step_sum.size(); ++s) {
    state.counters[std::string(frontend::to_string(static_cast<frontend::TrackStep>(s))) + "_ms"] =
        step_sum[s] / n;
  }
  state.counters["allocs_per_frame"] = static_cast<double>(allocs) / n;
}

// A kidnap in RGB-D on room_orbit: frames 0-179 tracked, 30 black frames, then frames 60-119
// again (the camera is back where it was 4 s before the blackout). Per frame the tracking
// stage is timed as the tracking thread runs it (spin_once, and the copy of a lost frame's
// features for the relocalizer); the relocalizer runs untimed between frames (in mer_slam:
// on the depth thread) and its pose is handed back before the next frame. Counters per tracker
// state (tracking / lost / relocalizing): frames, p50/p99 (ms), heap allocations per frame;
// relocalize_p50/p99_ms: one relocalizer attempt; relocalized_after: lost frames before
// tracking came back.
void bm_tracking_kidnap(benchmark::State& state) {
  const Sequence& seq = sequence();
  constexpr int kBefore = 180;
  constexpr int kBlack = 30;
  constexpr int kBackFrom = 60;
  constexpr int kBackTo = 120;
  std::vector<hal::Frame> frames;
  for (int i = 0; i < kBefore; ++i) frames.push_back(seq.frames[static_cast<std::size_t>(i)]);
  for (int i = 0; i < kBlack; ++i) {
    hal::Frame f;
    f.gray = cv::Mat::zeros(seq.height, seq.width, CV_8UC1);
    f.depth = cv::Mat::zeros(seq.height, seq.width, CV_32FC1);
    frames.push_back(f);
  }
  for (int i = kBackFrom; i < kBackTo; ++i) {
    hal::Frame f = seq.frames[static_cast<std::size_t>(i)];
    f.gray = f.gray.clone();
    f.depth = f.depth.clone();
    frames.push_back(f);
  }
  for (std::size_t i = 0; i < frames.size(); ++i) {
    frames[i].seq = i;
    frames[i].t_ns = static_cast<std::int64_t>(static_cast<double>(i) / kFps * 1e9);
  }
  constexpr std::size_t kStates = 5;
  std::array<std::vector<double>, kStates> ms;
  std::array<std::uint64_t, kStates> allocs{};
  std::vector<double> reloc_ms;
  double relocalized_after = -1.0;
  for (auto _ : state) {
    state.PauseTiming();
    map::MapOptions mo;
    mo.max_keyframes = 128;
    mo.max_points = 50000;
    auto map = std::make_unique<map::Map>(mo);
    frontend::Tracker tracker(frontend::TrackingOptions{}, *map, seq.K, seq.width, seq.height,
                              SensorMode::kRgbd, false);
    (void)tracker.init();
    tracker.enable_relocalization(true);
    frontend::RelocalizationRequest req;
    tracker.reserve_relocalization_request(req);
    const backend::LocalBaOptions ba_opts;
    depth::KeyframeBuilder builder(depth::DepthOptions{}, SensorMode::kRgbd, *map,
                                   tracker.level_sigma2(), ba_opts.depth_sigma_rel);
    (void)builder.init();
    backend::LocalBundleAdjuster ba(ba_opts, *map, tracker.level_sigma2(), true, true);
    loop::KeyframeDatabase db(*map);
    loop::Relocalizer relocalizer(loop::RelocalizerOptions{}, *map, db);
    map::KeyframeJob job;
    job.reserve(tracker.max_keypoints(), seq.width, seq.height);
    std::uint64_t lost = 0;
    for (const hal::Frame& f : frames) {
      state.ResumeTiming();
      const std::uint64_t a0 = platform::alloc::thread_allocations();
      const std::int64_t t0 = platform::monotonic_now_ns();
      const frontend::TrackingResult r = tracker.spin_once(f);
      if (r.relocalization_request) tracker.fill_relocalization_request(f, req);
      const std::int64_t t1 = platform::monotonic_now_ns();
      const std::uint64_t a1 = platform::alloc::thread_allocations();
      state.PauseTiming();
      if (r.steady || r.state != frontend::TrackState::kTracked) {
        const auto si = static_cast<std::size_t>(r.tracker_state);
        ms[si].push_back(static_cast<double>(t1 - t0) * kNsToMs);
        allocs[si] += a1 - a0;
      }
      if (r.state != frontend::TrackState::kTracked) ++lost;
      if (r.relocalized && relocalized_after < 0.0) relocalized_after = static_cast<double>(lost);
      if (r.relocalization_request) {
        loop::RelocQuery q;
        q.seq = req.seq;
        q.t_ns = req.t_ns;
        q.keypoints = std::span<const features::Keypoint>(req.keypoints.data(), req.count);
        q.descriptors = std::span<const features::Descriptor>(req.descriptors.data(), req.count);
        q.K = req.K;
        const loop::RelocResult res = relocalizer.spin_once(q);
        reloc_ms.push_back(res.ms);
        frontend::RelocalizationHint hint;
        hint.valid = res.success;
        hint.seq = req.seq;
        hint.T_c_w = res.T_c_w;
        hint.keyframe = res.keyframe;
        hint.generation = res.generation;
        tracker.set_relocalization_hint(hint);
      }
      if (r.keyframe_job) {
        tracker.fill_keyframe_job(f, job);
        const depth::KeyframeBuildReport rep = builder.spin_once(job);
        if (rep.ok) (void)ba.spin_once(rep.keyframe, job.K);
      }
    }
    state.ResumeTiming();
  }
  for (std::size_t si = 0; si < kStates; ++si) {
    const auto st = static_cast<frontend::TrackerState>(si);
    if (st == frontend::TrackerState::kInitializing || st == frontend::TrackerState::kNewSegment) {
      continue;
    }
    const std::string name = frontend::to_string(st);
    const double n = ms[si].empty() ? 1.0 : static_cast<double>(ms[si].size());
    state.counters[name + "_frames"] = static_cast<double>(ms[si].size());
    state.counters[name + "_p50_ms"] = percentile(ms[si], 0.5);
    state.counters[name + "_p99_ms"] = percentile(ms[si], 0.99);
    state.counters[name + "_allocs_per_frame"] = static_cast<double>(allocs[si]) / n;
  }
  state.counters["relocalize_p50_ms"] = percentile(reloc_ms, 0.5);
  state.counters["relocalize_p99_ms"] = percentile(reloc_ms, 0.99);
  state.counters["relocalized_after"] = relocalized_after;
}

// Tracks `seq` in `mode` from an empty map with default options, builds every keyframe the
// tracker asks for and calls on_keyframe(ba, keyframe, K) after each insertion: the local BA
// benchmarks' common set-up, run with the timing paused (on_keyframe resumes it as needed).
template <class OnKeyframe>
void for_each_keyframe(const Sequence& seq, SensorMode mode, OnKeyframe&& on_keyframe) {
  map::MapOptions mo;
  mo.max_keyframes = 128;
  mo.max_points = 50000;
  auto map = std::make_unique<map::Map>(mo);
  frontend::Tracker tracker(frontend::TrackingOptions{}, *map, seq.K, seq.width, seq.height, mode,
                            false);
  (void)tracker.init();
  const backend::LocalBaOptions ba_opts;
  depth::KeyframeBuilder builder(depth::DepthOptions{}, mode, *map, tracker.level_sigma2(),
                                 ba_opts.depth_sigma_rel);
  (void)builder.init();
  backend::LocalBundleAdjuster ba(ba_opts, *map, tracker.level_sigma2(), false,
                                  builder.metric_map_depth());
  map::KeyframeJob job;
  job.reserve(tracker.max_keypoints(), seq.width, seq.height);
  for (const hal::Frame& f : seq.frames) {
    const frontend::TrackingResult r = tracker.spin_once(f);
    if (!r.keyframe_job) continue;
    tracker.fill_keyframe_job(f, job);
    const depth::KeyframeBuildReport rep = builder.spin_once(job);
    if (rep.ok) on_keyframe(ba, rep.keyframe, job.K);
  }
}

// Local BA per keyframe as mer_slam runs it outside lockstep (default options: 50 ms budget
// per run, polled between solver iterations). Arg 0: RGB-D (metric 3D-3D edges), 1: mono.
// Counters: run time p50/p99 (ms), runs over the budget, solver iterations per run, and the
// abort latency: the longest stretch of a run without a poll of the abort flag (p50/p99, ms).
void bm_local_ba(benchmark::State& state) {
  const Sequence& seq = sequence(state.range(0) != 0);
  const SensorMode mode = state.range(0) == 0 ? SensorMode::kRgbd : SensorMode::kMono;
  std::vector<double> run_ms;
  std::vector<double> gap_ms;
  double iterations = 0.0;
  int overruns = 0;
  for (auto _ : state) {
    state.PauseTiming();
    const double budget_ms = backend::LocalBaOptions{}.max_time_ms;
    for_each_keyframe(
        seq, mode,
        [&](backend::LocalBundleAdjuster& ba, map::KeyframeId kf, const geometry::Pinhole& K) {
          state.ResumeTiming();
          const backend::LocalBaReport b = ba.spin_once(kf, K);
          state.PauseTiming();
          if (!b.ran) return;
          run_ms.push_back(b.ms);
          gap_ms.push_back(b.max_poll_gap_ms);
          iterations += b.iterations;
          overruns += b.ms > budget_ms ? 1 : 0;
        });
    state.ResumeTiming();
  }
  const double n = run_ms.empty() ? 1.0 : static_cast<double>(run_ms.size());
  state.counters["runs"] = static_cast<double>(run_ms.size());
  state.counters["run_p50_ms"] = percentile(run_ms, 0.5);
  state.counters["run_p99_ms"] = percentile(run_ms, 0.99);
  state.counters["overruns"] = overruns;
  state.counters["iterations"] = iterations / n;
  state.counters["abort_p50_ms"] = percentile(gap_ms, 0.5);
  state.counters["abort_p99_ms"] = percentile(gap_ms, 0.99);
}

// The abort latency as the pipeline sees it: for every keyframe, kAbortTrials runs of local BA
// are each pre-empted by request_abort from a second thread after a random delay (uniform in
// 0..kMaxAbortDelayMs, about a run), and the time from the request to spin_once's return is
// recorded (requests made after the run returned are not); then a full run, so that the map
// evolves as in bm_local_ba. Arg 0: RGB-D, 1: mono. Counters: latency p50/p99/max (ms), the
// number of measured requests, and the worst poll gap of the aborted runs.
constexpr int kAbortTrials = 12;
constexpr double kMaxAbortDelayMs = 40.0;

void bm_local_ba_abort(benchmark::State& state) {
  const Sequence& seq = sequence(state.range(0) != 0);
  const SensorMode mode = state.range(0) == 0 ? SensorMode::kRgbd : SensorMode::kMono;
  std::vector<double> latency_ms;
  double max_gap_ms = 0.0;
  std::mt19937 rng(11);
  std::uniform_real_distribution<double> delay_ms(0.0, kMaxAbortDelayMs);
  for (auto _ : state) {
    state.PauseTiming();
    for_each_keyframe(
        seq, mode,
        [&](backend::LocalBundleAdjuster& ba, map::KeyframeId kf, const geometry::Pinhole& K) {
          for (int t = 0; t < kAbortTrials; ++t) {
            const auto delay = std::chrono::duration<double, std::milli>(delay_ms(rng));
            std::atomic<std::int64_t> t_request{0};
            std::atomic<bool> returned{false};
            std::thread aborter([&] {
              std::this_thread::sleep_for(delay);
              if (returned.load()) return;
              t_request.store(platform::monotonic_now_ns());
              ba.request_abort();
            });
            const backend::LocalBaReport b = ba.spin_once(kf, K);
            const std::int64_t t_return = platform::monotonic_now_ns();
            returned.store(true);
            aborter.join();
            const std::int64_t t_req = t_request.load();
            if (t_req != 0 && t_req <= t_return) {
              latency_ms.push_back(static_cast<double>(t_return - t_req) * kNsToMs);
              if (b.aborted) max_gap_ms = std::max(max_gap_ms, b.max_poll_gap_ms);
            }
          }
          (void)ba.spin_once(kf, K);
        });
    state.ResumeTiming();
  }
  state.counters["requests"] = static_cast<double>(latency_ms.size());
  state.counters["latency_p50_ms"] = percentile(latency_ms, 0.5);
  state.counters["latency_p99_ms"] = percentile(latency_ms, 0.99);
  state.counters["latency_max_ms"] = percentile(latency_ms, 1.0);
  state.counters["aborted_max_gap_ms"] = max_gap_ms;
}

}  // namespace

BENCHMARK(bm_tracking)->Unit(benchmark::kMillisecond)->Iterations(1);
BENCHMARK(bm_tracking_kidnap)->Unit(benchmark::kMillisecond)->Iterations(1);
BENCHMARK(bm_local_ba)->Arg(0)->Arg(1)->Unit(benchmark::kMillisecond)->Iterations(1);
BENCHMARK(bm_local_ba_abort)->Arg(0)->Arg(1)->Unit(benchmark::kMillisecond)->Iterations(1);

BENCHMARK_MAIN();
