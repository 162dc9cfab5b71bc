// Feature extractor benchmarks: one 640x480 synthetic room frame, 1000 features, both
// backends (extractor.h). Counters: keypoints found and heap allocations per extract()
// (the `orb` backend must show 0).
#include <benchmark/benchmark.h>
#include <opencv2/core.hpp>

#include "features/extractor.h"
#include "hal/synthetic/synthetic_camera.h"
#include "platform/alloc_counter.h"

namespace mer::features {
namespace {

constexpr double kFrameTimeS = 1.0;  // where on the room_orbit trajectory the frame is taken

cv::Mat room_frame() {
  hal::SyntheticOptions o;
  o.render_depth = false;
  hal::SyntheticCamera cam("room_orbit", o, /*paced=*/false);
  cv::Mat gray(o.height, o.width, CV_8UC1);
  if (!cam.open(2).is_ok()) return {};
  cam.render(cam.sample_at(kFrameTimeS).T_w_c, gray, nullptr, 0);
  return gray;
}

// `opencv_threads` < 0: leave OpenCV's thread setting alone; otherwise set it for this
// benchmark only (restored afterwards) - cv::ORB may use OpenCV's thread pool, ours never.
void bm_extract(benchmark::State& state, const char* backend, int opencv_threads) {
  const cv::Mat gray = room_frame();
  if (gray.empty()) {
    state.SkipWithError("synthetic camera failed to open");
    return;
  }
  ExtractorOptions o;
  (void)options::parse_name(backend, kExtractorBackendNames, o.backend);
  o.num_features = 1000;
  auto made = make_extractor(o, gray.cols, gray.rows);
  if (!made.is_ok()) {
    state.SkipWithError(made.status().message().c_str());
    return;
  }
  auto ex = std::move(made).value();
  const int saved_threads = cv::getNumThreads();
  if (opencv_threads >= 0) cv::setNumThreads(opencv_threads);
  ex->extract(gray);  // first call outside the timing (warm caches)
  const auto allocs_before = platform::alloc::thread_allocations();
  int keypoints = 0;
  for (auto _ : state) {
    keypoints = ex->extract(gray);
    benchmark::DoNotOptimize(keypoints);
  }
  const auto allocs = platform::alloc::thread_allocations() - allocs_before;
  if (opencv_threads >= 0) cv::setNumThreads(saved_threads);
  state.counters["keypoints"] = keypoints;
  state.counters["allocs_per_call"] =
      static_cast<double>(allocs) /
      static_cast<double>(std::max<std::int64_t>(1, state.iterations()));
  state.SetItemsProcessed(state.iterations());  // frames
}

BENCHMARK_CAPTURE(bm_extract, orb, "orb", -1)->Unit(benchmark::kMillisecond);
BENCHMARK_CAPTURE(bm_extract, opencv_orb, "opencv_orb", -1)->Unit(benchmark::kMillisecond);
BENCHMARK_CAPTURE(bm_extract, opencv_orb_1thread, "opencv_orb", 1)->Unit(benchmark::kMillisecond);

}  // namespace
}  // namespace mer::features

BENCHMARK_MAIN();
