// Micro-benchmarks of the platform primitives. Run the release preset build:
//   build/release/tests/bench/mer_bench_platform --benchmark_repetitions=5
// Two-thread benchmarks use real time; on a 2-core machine they need both cores idle.
#include <atomic>
#include <cstdint>
#include <cstdlib>
#include <thread>

#include <benchmark/benchmark.h>

#include "platform/alloc_counter.h"
#include "platform/fixed_pool.h"
#include "platform/latency_recorder.h"
#include "platform/log_ring.h"
#include "platform/overwrite_ring.h"
#include "platform/spsc_ring.h"

namespace mer::platform {
namespace {

inline void cpu_relax() {
#if defined(__x86_64__) || defined(__i386__)
  __builtin_ia32_pause();
#elif defined(__aarch64__)
  asm volatile("yield" ::: "memory");
#endif
}

// One round trip: main pushes to `ping`, an echo thread pops it and pushes it back on
// `pong`, main pops it. Time per iteration = round-trip latency (two one-way hand-offs).
void bm_spsc_round_trip(benchmark::State& state) {
  SpscRing<std::uint64_t, 64> ping;
  SpscRing<std::uint64_t, 64> pong;
  std::atomic<bool> stop{false};
  std::thread echo([&] {
    std::uint64_t v = 0;
    while (!stop.load(std::memory_order_relaxed)) {
      if (ping.try_pop(v)) {
        while (!pong.try_push(v)) {
          cpu_relax();
        }
      } else {
        cpu_relax();
      }
    }
  });
  std::uint64_t i = 0;
  for (auto _ : state) {
    while (!ping.try_push(i)) {
      cpu_relax();
    }
    std::uint64_t v = 0;
    while (!pong.try_pop(v)) {
      cpu_relax();
    }
    benchmark::DoNotOptimize(v);
    ++i;
  }
  stop.store(true);
  echo.join();
  state.SetItemsProcessed(state.iterations());
}
BENCHMARK(bm_spsc_round_trip)->UseRealTime();

// Producer (benchmark thread) pushes as fast as it can, a consumer thread pops.
void bm_spsc_throughput(benchmark::State& state) {
  static SpscRing<std::uint64_t, 4096> ring;  // static: 32 KB, keep it off the stack
  std::atomic<bool> stop{false};
  std::atomic<std::uint64_t> consumed{0};
  std::thread consumer([&] {
    std::uint64_t v = 0;
    std::uint64_t n = 0;
    for (;;) {
      if (ring.try_pop(v)) {
        ++n;
      } else if (stop.load(std::memory_order_acquire)) {
        while (ring.try_pop(v)) {
          ++n;
        }
        break;
      } else {
        cpu_relax();
      }
    }
    consumed.store(n);
  });
  std::uint64_t i = 0;
  for (auto _ : state) {
    while (!ring.try_push(i)) {
      cpu_relax();
    }
    ++i;
  }
  stop.store(true, std::memory_order_release);
  consumer.join();
  if (consumed.load() != i) {
    state.SkipWithError("consumer lost items");
  }
  state.SetItemsProcessed(static_cast<std::int64_t>(i));
}
BENCHMARK(bm_spsc_throughput)->UseRealTime();

// Single-thread push + pop pair (uncontended cost of the two operations).
void bm_spsc_push_pop_same_thread(benchmark::State& state) {
  SpscRing<std::uint64_t, 64> ring;
  std::uint64_t v = 0;
  for (auto _ : state) {
    benchmark::DoNotOptimize(ring.try_push(v));
    benchmark::DoNotOptimize(ring.try_pop(v));
  }
}
BENCHMARK(bm_spsc_push_pop_same_thread);

// OverwriteRing push + pop, single thread (CAS cost, no contention).
void bm_overwrite_ring_push_pop(benchmark::State& state) {
  OverwriteRing<std::uint32_t, 8> ring;
  std::uint32_t v = 0;
  for (auto _ : state) {
    benchmark::DoNotOptimize(ring.push(v));
    benchmark::DoNotOptimize(ring.try_pop(v));
    ++v;
  }
}
BENCHMARK(bm_overwrite_ring_push_pop);

// OverwriteRing push into a full ring: every push evicts.
void bm_overwrite_ring_push_evict(benchmark::State& state) {
  OverwriteRing<std::uint32_t, 8> ring;
  std::uint32_t v = 0;
  for (std::uint32_t k = 0; k < 8; ++k) {
    benchmark::DoNotOptimize(ring.push(k));
  }
  for (auto _ : state) {
    benchmark::DoNotOptimize(ring.push(v++));
  }
  state.counters["dropped"] = static_cast<double>(ring.dropped());
}
BENCHMARK(bm_overwrite_ring_push_evict);

// OverwriteRing with a producer thread pushing and the benchmark thread popping.
void bm_overwrite_ring_two_threads(benchmark::State& state) {
  OverwriteRing<std::uint64_t, 16> ring;
  std::atomic<bool> stop{false};
  std::thread producer([&] {
    std::uint64_t i = 0;
    while (!stop.load(std::memory_order_relaxed)) {
      benchmark::DoNotOptimize(ring.push(i++));
    }
  });
  std::uint64_t v = 0;
  std::uint64_t popped = 0;
  for (auto _ : state) {
    while (!ring.try_pop(v)) {
      cpu_relax();
    }
    ++popped;
  }
  stop.store(true);
  producer.join();
  state.SetItemsProcessed(static_cast<std::int64_t>(popped));
  state.counters["dropped"] = static_cast<double>(ring.dropped());
}
BENCHMARK(bm_overwrite_ring_two_threads)->UseRealTime();

struct Frame {
  std::uint64_t seq = 0;
  std::int64_t t_ns = 0;
};

// FixedPool acquire + release (handle destruction), single thread.
void bm_fixed_pool_acquire_release(benchmark::State& state) {
  FixedPool<Frame> pool(16);
  for (auto _ : state) {
    PoolHandle<Frame> h = pool.acquire();
    benchmark::DoNotOptimize(h.get());
  }
}
BENCHMARK(bm_fixed_pool_acquire_release);

// Same, two threads hammering one pool (contended CAS on the free-list head).
void bm_fixed_pool_acquire_release_contended(benchmark::State& state) {
  static FixedPool<Frame> pool(64);
  for (auto _ : state) {
    PoolHandle<Frame> h = pool.acquire();
    benchmark::DoNotOptimize(h.get());
  }
}
BENCHMARK(bm_fixed_pool_acquire_release_contended)->Threads(2)->UseRealTime();

void bm_latency_recorder_record(benchmark::State& state) {
  LatencyRecorder rec("bench", 33'000'000, 1024);
  std::uint64_t seq = 0;
  std::int64_t d = 1'000;
  for (auto _ : state) {
    rec.record(seq++, 0, d);
    d = (d * 1103515245 + 12345) & 0x3FFFFFF;  // spread over ~26 octaves of bins
  }
  benchmark::DoNotOptimize(rec.count());
}
BENCHMARK(bm_latency_recorder_record);

void bm_log_ring_try_log_and_drain(benchmark::State& state) {
  LogRing ring(1024);
  std::uint64_t n = 0;
  for (auto _ : state) {
    benchmark::DoNotOptimize(ring.try_log(LogLevel::kInfo, "frame %llu took %.3f ms",
                                          static_cast<unsigned long long>(n), 1.25));
    if ((++n & 511) == 0) {
      ring.drain([](const LogRecord& r) { benchmark::DoNotOptimize(r.text[0]); });
    }
  }
}
BENCHMARK(bm_log_ring_try_log_and_drain);

// new/delete through the counting replacement (mer_alloc_counter is linked here) ...
void bm_alloc_counter_new_delete(benchmark::State& state) {
  if (!alloc::counter_linked()) {
    state.SkipWithError("mer_alloc_counter not linked");
  }
  const std::uint64_t a0 = alloc::thread_allocations();
  for (auto _ : state) {
    int* p = new int(1);
    benchmark::DoNotOptimize(p);
    delete p;
  }
  state.counters["counted"] = static_cast<double>(alloc::thread_allocations() - a0) /
                              static_cast<double>(state.iterations());
}
BENCHMARK(bm_alloc_counter_new_delete);

// ... versus the raw malloc/free pair it wraps (the counter's overhead is the difference).
void bm_malloc_free_baseline(benchmark::State& state) {
  for (auto _ : state) {
    void* p = std::malloc(sizeof(int));
    benchmark::DoNotOptimize(p);
    std::free(p);
  }
}
BENCHMARK(bm_malloc_free_baseline);

}  // namespace
}  // namespace mer::platform

BENCHMARK_MAIN();
