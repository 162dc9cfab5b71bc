// Plane-sweep stereo (depth/plane_sweep.h) per keyframe: 640x480 room_orbit keyframes
// resampled to 320x240, 4 past source frames (t - 0.4 .. t - 0.1 s, as in the pipeline),
// one core. Argument: number of planes (24 is the default). Counters: min/p50/p99 of the
// compute() time (ms; min is the least disturbed by other processes on the machine), heap
// allocations per compute() (0 in steady state) and the fraction of pixels with a depth.
#include <algorithm>
#include <cstdint>
#include <vector>

#include <benchmark/benchmark.h>
#include <opencv2/core.hpp>

#include "depth/plane_sweep.h"
#include "hal/synthetic/synthetic_camera.h"
#include "platform/alloc_counter.h"
#include "platform/clock.h"

namespace mer::depth {
namespace {

constexpr double kNsToMs = 1e-6;
constexpr double kKeyframeTimesS[] = {4.0, 7.5, 11.0};  // keyframes cycled through
constexpr double kSourceOffsetsS[] = {-0.4, -0.3, -0.2, -0.1};
constexpr std::size_t kSources = std::size(kSourceOffsetsS);

struct Keyframe {
  cv::Mat gray;
  SE3d T_w_c;
  std::vector<cv::Mat> source_gray;
  std::vector<PlaneSweepView> sources;
  double min_depth = 0.0;
  double max_depth = 0.0;
};

struct Scene {
  geometry::Pinhole K;
  std::vector<Keyframe> keyframes;
};

const Scene& scene() {
  static const Scene kScene = [] {
    Scene s;
    hal::SyntheticOptions o;
    hal::SyntheticCamera cam("room_orbit", o, /*paced=*/false);
    if (!cam.open(2).is_ok()) return s;
    const auto& k = cam.intrinsics();
    s.K = {k.fx, k.fy, k.cx, k.cy};
    const auto render = [&](double t, cv::Mat& gray, cv::Mat* depth) {
      gray.create(k.height, k.width, CV_8UC1);
      if (depth != nullptr) depth->create(k.height, k.width, CV_32FC1);
      const SE3d T = cam.sample_at(t).T_w_c;
      cam.render(T, gray, depth, static_cast<std::uint64_t>(t * o.fps));
      return T;
    };
    for (const double t : kKeyframeTimesS) {
      Keyframe kf;
      cv::Mat depth;
      kf.T_w_c = render(t, kf.gray, &depth);
      kf.source_gray.resize(kSources);
      for (std::size_t i = 0; i < kSources; ++i) {
        kf.sources.push_back({nullptr, render(t + kSourceOffsetsS[i], kf.source_gray[i], nullptr)});
      }
      // Bounds as the sparse points would give them: the true depth range, widened.
      double lo = 0.0;
      double hi = 0.0;
      cv::minMaxLoc(depth, &lo, &hi);
      kf.min_depth = 0.8 * lo;
      kf.max_depth = 1.2 * hi;
      s.keyframes.push_back(std::move(kf));
    }
    // The views point into the keyframes' own images: set them once the vector is final.
    for (auto& kf : s.keyframes) {
      for (std::size_t i = 0; i < kSources; ++i) kf.sources[i].gray = &kf.source_gray[i];
    }
    return s;
  }();
  return kScene;
}

double percentile(std::vector<double> v, double q) {
  if (v.empty()) return 0.0;
  std::sort(v.begin(), v.end());
  return v[static_cast<std::size_t>(q * static_cast<double>(v.size() - 1))];
}

void bm_plane_sweep(benchmark::State& state) {
  const Scene& s = scene();
  if (s.keyframes.empty()) {
    state.SkipWithError("synthetic camera failed to open");
    return;
  }
  PlaneSweepOptions o;
  o.num_planes = static_cast<int>(state.range(0));
  PlaneSweepStereo ps(o);
  if (!ps.status().is_ok()) {
    state.SkipWithError(ps.status().message().c_str());
    return;
  }
  const auto input = [&](std::size_t i) {
    const Keyframe& kf = s.keyframes[i % s.keyframes.size()];
    PlaneSweepInput in;
    in.gray = &kf.gray;
    in.T_w_c = kf.T_w_c;
    in.K = s.K;
    in.sources = kf.sources;
    in.min_depth = kf.min_depth;
    in.max_depth = kf.max_depth;
    return in;
  };
  // Warm-up outside the timing: resampling tables are built on the first call.
  if (!ps.compute(input(0)).is_ok()) {
    state.SkipWithError("compute failed");
    return;
  }
  std::vector<double> ms;
  std::uint64_t allocs = 0;
  double covered = 0.0;
  std::size_t i = 0;
  for (auto _ : state) {
    const PlaneSweepInput in = input(i++);
    const std::uint64_t a0 = platform::alloc::thread_allocations();
    const std::int64_t t0 = platform::monotonic_now_ns();
    const Status st = ps.compute(in);
    const std::int64_t t1 = platform::monotonic_now_ns();
    allocs += platform::alloc::thread_allocations() - a0;
    benchmark::DoNotOptimize(st);
    ms.push_back(static_cast<double>(t1 - t0) * kNsToMs);
    covered +=
        static_cast<double>(cv::countNonZero(ps.depth())) / static_cast<double>(ps.depth().total());
  }
  const double n = std::max<double>(1.0, static_cast<double>(ms.size()));
  state.counters["min_ms"] = percentile(ms, 0.0);  // least disturbed by other processes
  state.counters["p50_ms"] = percentile(ms, 0.5);
  state.counters["p99_ms"] = percentile(ms, 0.99);
  state.counters["allocs_per_call"] = static_cast<double>(allocs) / n;
  state.counters["coverage"] = covered / n;
  state.SetItemsProcessed(state.iterations());  // keyframes
}

BENCHMARK(bm_plane_sweep)->Arg(24)->Arg(32)->Arg(64)->Unit(benchmark::kMillisecond);

}  // namespace
}  // namespace mer::depth

BENCHMARK_MAIN();
