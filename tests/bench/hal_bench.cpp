// Camera HAL benchmarks: the synthetic camera's frame rate at 640x480 on one core.
#include <benchmark/benchmark.h>

#include "hal/synthetic/synthetic_camera.h"

namespace mer::hal {
namespace {

// One acquire = render one 640x480 frame (gray + depth) into a pool buffer.
void bm_synthetic_acquire(benchmark::State& state, const char* scenario, bool depth) {
  SyntheticOptions o;
  o.num_frames = 10000000;
  o.render_depth = depth;
  SyntheticCamera cam(scenario, o, /*paced=*/false);
  if (!cam.open(4).is_ok() || !cam.start().is_ok()) {
    state.SkipWithError("synthetic camera failed to open");
    return;
  }
  for (auto _ : state) {
    FrameHandle f;
    benchmark::DoNotOptimize(cam.acquire(f, 0));
  }
  state.SetItemsProcessed(state.iterations());  // frames; items_per_second = fps
}

BENCHMARK_CAPTURE(bm_synthetic_acquire, room_orbit_gray_depth, "room_orbit", true)
    ->Unit(benchmark::kMillisecond);
BENCHMARK_CAPTURE(bm_synthetic_acquire, room_orbit_gray, "room_orbit", false)
    ->Unit(benchmark::kMillisecond);
BENCHMARK_CAPTURE(bm_synthetic_acquire, room_loop_gray_depth, "room_loop", true)
    ->Unit(benchmark::kMillisecond);

}  // namespace
}  // namespace mer::hal

BENCHMARK_MAIN();
