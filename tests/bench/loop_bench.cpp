// Image retrieval (loop/keyframe_database.h): a query by a frame's 1000 descriptors against
// 500 keyframes of 1000 descriptors each, one core. Keyframes see overlapping windows of a
// pool of world descriptors (each point in ~5 keyframes, 10 bits of view noise), so posting
// lists hold what a revisited place gives them. Counters: per-query p50/p99 (ms), the rank
// of the keyframe the query views, allocations per query (0 after init).
#include <algorithm>
#include <array>
#include <chrono>
#include <cstdint>
#include <ctime>
#include <random>
#include <vector>

#include <benchmark/benchmark.h>

#include "loop/keyframe_database.h"
#include "map/map.h"
#include "platform/alloc_counter.h"

namespace mer::loop {
namespace {

constexpr int kKeyframes = 500;
constexpr int kDescriptors = 1000;
constexpr int kStride = 200;  // window shift per keyframe: each point in 5 keyframes
constexpr int kPool = kKeyframes * kStride + kDescriptors;
constexpr int kBitFlips = 10;

features::Descriptor noisy(const features::Descriptor& d, std::mt19937_64& rng) {
  std::uniform_int_distribution<int> bit(0, 255);
  features::Descriptor out = d;
  for (int b = 0; b < kBitFlips; ++b) {
    const int k = bit(rng);
    out[static_cast<std::size_t>(k / 64)] ^= 1ULL << static_cast<unsigned>(k % 64);
  }
  return out;
}

// Thread CPU time, ms: the query's own cost, without the time the scheduler gave others on a
// loaded machine (wall-clock percentiles are reported too).
double thread_cpu_ms() {
  timespec ts{};
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
  return static_cast<double>(ts.tv_sec) * 1e3 + static_cast<double>(ts.tv_nsec) * 1e-6;
}

double percentile(std::vector<double> v, double q) {
  if (v.empty()) return 0.0;
  std::sort(v.begin(), v.end());
  return v[static_cast<std::size_t>(q * static_cast<double>(v.size() - 1))];
}

void bm_retrieval_query(benchmark::State& state) {
  map::MapOptions mo;
  mo.max_keyframes = kKeyframes;
  mo.max_keypoints_per_keyframe = kDescriptors;
  mo.max_points = 1024;
  mo.cell_table_size = 1024;
  map::Map map(mo);
  std::mt19937_64 rng(1);
  std::vector<features::Descriptor> pool(kPool);
  for (auto& d : pool) d = {rng(), rng(), rng(), rng()};
  std::vector<features::Keypoint> kps(kDescriptors);
  std::vector<features::Descriptor> desc(kDescriptors);
  for (int k = 0; k < kKeyframes; ++k) {
    for (int i = 0; i < kDescriptors; ++i) {
      desc[static_cast<std::size_t>(i)] =
          noisy(pool[static_cast<std::size_t>(k * kStride + i)], rng);
    }
    map::KeyframeInput in;
    in.seq = static_cast<std::uint64_t>(k);
    in.keypoints = kps;
    in.descriptors = desc;
    if (!map.add_keyframe(in).is_ok()) {
      state.SkipWithError("add_keyframe failed");
      return;
    }
  }
  KeyframeDatabase db(map);
  db.refresh_live();
  // Queries: new views of every 10th keyframe's place.
  std::vector<std::vector<features::Descriptor>> queries;
  for (int k = 0; k < kKeyframes; k += 10) {
    std::vector<features::Descriptor> q(kDescriptors);
    for (int i = 0; i < kDescriptors; ++i) {
      q[static_cast<std::size_t>(i)] = noisy(pool[static_cast<std::size_t>(k * kStride + i)], rng);
    }
    queries.push_back(std::move(q));
  }
  std::array<RetrievalHit, 5> top{};
  std::vector<double> ms;
  std::vector<double> cpu_ms;
  ms.reserve(1 << 20);
  cpu_ms.reserve(1 << 20);
  std::uint64_t allocs = 0;
  std::uint64_t calls = 0;
  std::uint64_t first = 0;
  std::size_t qi = 0;
  for (auto _ : state) {
    const auto& q = queries[qi];
    const std::uint64_t a0 = platform::alloc::thread_allocations();
    const double c0 = thread_cpu_ms();
    const auto t0 = std::chrono::steady_clock::now();
    const std::size_t n = db.query(q, top);
    const auto t1 = std::chrono::steady_clock::now();
    const double c1 = thread_cpu_ms();
    allocs += platform::alloc::thread_allocations() - a0;
    benchmark::DoNotOptimize(n);
    if (cpu_ms.size() < cpu_ms.capacity()) cpu_ms.push_back(c1 - c0);
    if (ms.size() < ms.capacity())
      ms.push_back(std::chrono::duration<double, std::milli>(t1 - t0).count());
    first += (n > 0 && top[0].id == static_cast<map::KeyframeId>(qi * 10)) ? 1 : 0;
    ++calls;
    qi = (qi + 1) % queries.size();
  }
  state.counters["keyframes"] = static_cast<double>(db.size());
  state.counters["p50_ms"] = percentile(ms, 0.5);
  state.counters["p99_ms"] = percentile(ms, 0.99);
  state.counters["cpu_p50_ms"] = percentile(cpu_ms, 0.5);
  state.counters["cpu_p99_ms"] = percentile(cpu_ms, 0.99);
  state.counters["top1_fraction"] = calls > 0 ? static_cast<double>(first) / calls : 0.0;
  state.counters["allocs_per_query"] = calls > 0 ? static_cast<double>(allocs) / calls : 0.0;
}
BENCHMARK(bm_retrieval_query)->Unit(benchmark::kMillisecond);

}  // namespace
}  // namespace mer::loop

BENCHMARK_MAIN();
