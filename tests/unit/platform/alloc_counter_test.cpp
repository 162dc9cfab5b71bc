#include "platform/alloc_counter.h"

#include <thread>
#include <vector>

#include <gtest/gtest.h>

#include "platform/fixed_pool.h"
#include "platform/latency_recorder.h"
#include "platform/notifier.h"
#include "platform/overwrite_ring.h"
#include "platform/spsc_ring.h"

namespace mer::platform {
namespace {

// Keeps the compiler from eliding a new/delete pair.
template <typename T>
void escape(T* p) {
  asm volatile("" : : "g"(p) : "memory");
}

TEST(AllocCounter, IsLinkedIntoTests) {
  EXPECT_TRUE(alloc::counter_linked());
}

TEST(AllocCounter, CountsNewAndDeleteOnThisThread) {
  const std::uint64_t a0 = alloc::thread_allocations();
  const std::uint64_t d0 = alloc::thread_deallocations();
  int* p = new int(5);
  escape(p);
  EXPECT_EQ(alloc::thread_allocations() - a0, 1u);
  delete p;
  EXPECT_EQ(alloc::thread_deallocations() - d0, 1u);
  int* arr = new int[17];
  escape(arr);
  delete[] arr;
  EXPECT_EQ(alloc::thread_allocations() - a0, 2u);
  EXPECT_EQ(alloc::thread_deallocations() - d0, 2u);
}

TEST(AllocCounter, CountsAlignedAndNothrowVariants) {
  struct alignas(128) Big {
    char c[256];
  };
  const std::uint64_t a0 = alloc::thread_allocations();
  Big* b = new Big;
  escape(b);
  EXPECT_EQ(reinterpret_cast<std::uintptr_t>(b) % 128, 0u);
  delete b;
  int* n = new (std::nothrow) int;
  escape(n);
  delete n;
  EXPECT_EQ(alloc::thread_allocations() - a0, 2u);
}

TEST(AllocCounter, VectorReserveCountsOne) {
  const std::uint64_t a0 = alloc::thread_allocations();
  std::vector<int> v;
  v.reserve(1000);
  escape(v.data());
  EXPECT_EQ(alloc::thread_allocations() - a0, 1u);
  for (int i = 0; i < 1000; ++i) {
    v.push_back(i);  // within capacity: no allocation
  }
  EXPECT_EQ(alloc::thread_allocations() - a0, 1u);
}

TEST(AllocCounter, OtherThreadsDoNotChangeThisThreadsCount) {
  const std::uint64_t before = alloc::thread_allocations();
  std::uint64_t other_count = 0;
  std::thread t([&] {
    const std::uint64_t t0 = alloc::thread_allocations();
    for (int i = 0; i < 100; ++i) {
      int* p = new int(i);
      escape(p);
      delete p;
    }
    other_count = alloc::thread_allocations() - t0;
  });
  t.join();
  EXPECT_EQ(other_count, 100u);
  // std::thread's start-up state is allocated by *this* thread (the creator) - at most a
  // couple of blocks - but none of the other thread's 100 allocations may show up here.
  EXPECT_LE(alloc::thread_allocations() - before, 3u);
}

TEST(AllocCounter, TotalIncludesOtherThreadsInBatches) {
  const std::uint64_t total0 = alloc::total_allocations();
  std::thread t([] {
    for (int i = 0; i < 1000; ++i) {
      int* p = new int(i);
      escape(p);
      delete p;
    }
  });
  t.join();
  // The other thread published at least floor(1000 / 64) * 64 = 960 of its allocations.
  EXPECT_GE(alloc::total_allocations() - total0, 960u);
}

TEST(AllocCounter, HotPathPrimitivesDoNotAllocate) {
  // Everything allocated up front, as after start(); then one simulated frame loop.
  FixedPool<std::vector<std::uint8_t>> pool(
      4, [](std::vector<std::uint8_t>& b, std::size_t) { b.resize(1024); });
  OverwriteRing<std::uint32_t, 2> frames;
  SpscRing<PoolHandle<std::vector<std::uint8_t>>, 4> handoff;
  LatencyRecorder rec("stage", 1'000, 16);
  Notifier notifier;
  const std::uint64_t a0 = alloc::thread_allocations();
  for (std::uint64_t seq = 0; seq < 100; ++seq) {
    auto h = pool.acquire();
    ASSERT_TRUE(h);
    (*h)[0] = static_cast<std::uint8_t>(seq);
    if (auto evicted = frames.push(h.release_raw())) {
      pool.adopt(*evicted).reset();
    }
    std::uint32_t idx = 0;
    ASSERT_TRUE(frames.try_pop(idx));
    ASSERT_TRUE(handoff.try_push(pool.adopt(idx)));
    PoolHandle<std::vector<std::uint8_t>> out;
    ASSERT_TRUE(handoff.try_pop(out));
    notifier.notify();
    rec.record(seq, 0, static_cast<std::int64_t>(seq * 37));
  }
  EXPECT_EQ(alloc::thread_allocations() - a0, 0u);
  EXPECT_EQ(pool.available_approx(), 4u);
}

}  // namespace
}  // namespace mer::platform
