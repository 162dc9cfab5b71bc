#include <array>
#include <atomic>
#include <cstdint>
#include <thread>
#include <vector>

#include <gtest/gtest.h>

#include "platform/fixed_pool.h"
#include "platform/overwrite_ring.h"
#include "platform/spsc_ring.h"
#include "stress_config.h"

namespace mer::platform {
namespace {

/// Plain (non-atomic) fields on purpose: two threads owning one slot at once is a data race
/// that TSan reports, and a value check that fails in every build.
struct Slot {
  std::uint64_t owner = 0;
  std::uint64_t stamp = 0;
};

TEST(FixedPoolStress, ExclusiveOwnershipManyThreads) {
  constexpr std::size_t kCapacity = 8;
  constexpr unsigned kThreads = 4;  // more threads than cores on CI: preemption mid-CAS
  const std::uint64_t iters = stress::iterations(400'000, 2);
  FixedPool<Slot> pool(kCapacity);
  std::atomic<std::uint64_t> violations{0};
  std::atomic<std::uint64_t> successes{0};
  std::atomic<unsigned> ready{0};

  auto worker = [&](std::uint64_t tid) {
    ready.fetch_add(1);
    while (ready.load() < kThreads) {
    }
    std::array<PoolHandle<Slot>, 2> held;  // hold up to 2 slots to drive exhaustion
    std::uint64_t ok = 0;
    std::uint64_t bad = 0;
    for (std::uint64_t i = 0; i < iters; ++i) {
      PoolHandle<Slot> h = pool.acquire();
      if (!h) {
        held[i % 2].reset();
        continue;
      }
      h->owner = tid;
      h->stamp = i;
      for (int s = 0; s < 16; ++s) {
        stress::cpu_relax();
      }
      bad += (h->owner != tid || h->stamp != i) ? 1 : 0;
      ++ok;
      if (i % 3 == 0) {
        held[i % 2] = std::move(h);  // releases the previously held one
      }
    }
    for (auto& h : held) {
      if (h) {
        bad += h->owner != tid ? 1 : 0;
      }
    }
    violations.fetch_add(bad);
    successes.fetch_add(ok);
  };
  std::vector<std::thread> threads;
  for (unsigned t = 0; t < kThreads; ++t) {
    threads.emplace_back(worker, std::uint64_t{t} + 1);
  }
  for (auto& t : threads) {
    t.join();
  }
  EXPECT_EQ(violations.load(), 0u);
  EXPECT_EQ(pool.available_approx(), kCapacity);  // no slot lost
  EXPECT_EQ(pool.misuse_count(), 0u);
  EXPECT_GT(successes.load(), iters);     // most acquires succeed
  EXPECT_GT(pool.exhausted_count(), 0u);  // 4 threads x up to 3 slots > 8: exhaustion hit
  // Every slot can still be acquired exactly once.
  std::vector<PoolHandle<Slot>> all;
  for (std::size_t i = 0; i < kCapacity; ++i) {
    all.push_back(pool.acquire());
    ASSERT_TRUE(all.back());
  }
  EXPECT_FALSE(pool.acquire());
}

TEST(FixedPoolStress, AcquireOnOneThreadReleaseOnAnother) {
  // Capture-like: producer acquires and fills, hands the handle over a ring, the consumer
  // checks the contents and releases on its own thread.
  constexpr std::size_t kCapacity = 6;
  const std::uint64_t n = stress::iterations(1'000'000, 4);
  FixedPool<Slot> pool(kCapacity);
  SpscRing<PoolHandle<Slot>, 4> ring;
  std::uint64_t producer_exhausted = 0;
  std::thread producer([&] {
    for (std::uint64_t i = 0; i < n;) {
      PoolHandle<Slot> h = pool.acquire();
      if (!h) {
        ++producer_exhausted;
        std::this_thread::yield();
        continue;
      }
      h->owner = 1;
      h->stamp = i;
      // try_push moves from `h` only when it succeeds, so retrying with it is fine.
      while (!ring.try_push(std::move(h))) {  // NOLINT(bugprone-use-after-move)
        std::this_thread::yield();
      }
      ++i;
    }
  });
  std::uint64_t expected = 0;
  std::uint64_t bad = 0;
  PoolHandle<Slot> h;
  while (expected < n) {
    if (ring.try_pop(h)) {
      bad += (h->owner != 1 || h->stamp != expected) ? 1 : 0;
      h->owner = 2;  // consumer writes too: must not race with a later producer write
      h.reset();
      ++expected;
    } else {
      std::this_thread::yield();
    }
  }
  producer.join();
  EXPECT_EQ(bad, 0u);
  EXPECT_EQ(pool.available_approx(), kCapacity);
  EXPECT_EQ(pool.exhausted_count(), producer_exhausted);
}

TEST(FixedPoolStress, RawIndicesThroughOverwriteRing) {
  // The frame path: capture releases raw indices into a drop-oldest ring, evicted indices
  // go straight back to the pool, tracking adopts what it pops.
  constexpr std::size_t kCapacity = 8;  // ring 4 + producer 1 + consumer 1 + slack
  const std::uint64_t n = stress::iterations(1'000'000, 4);
  FixedPool<Slot> pool(kCapacity);
  OverwriteRing<std::uint32_t, 4> ring;
  std::atomic<bool> done{false};
  std::uint64_t exhausted_spins = 0;
  std::thread producer([&] {
    for (std::uint64_t i = 0; i < n;) {
      PoolHandle<Slot> h = pool.acquire();
      if (!h) {
        ++exhausted_spins;
        std::this_thread::yield();
        continue;
      }
      h->owner = 1;
      h->stamp = i++;
      if (const auto evicted = ring.push(h.release_raw())) {
        pool.adopt(*evicted).reset();
      }
    }
    done.store(true, std::memory_order_release);
  });
  std::uint64_t popped = 0;
  std::uint64_t bad = 0;
  std::uint64_t last = 0;
  for (;;) {
    const bool finished = done.load(std::memory_order_acquire);
    std::uint32_t idx = 0;
    if (ring.try_pop(idx)) {
      PoolHandle<Slot> h = pool.adopt(idx);
      bad += (!h || h->owner != 1 || (popped > 0 && h->stamp <= last)) ? 1 : 0;
      if (h) {
        last = h->stamp;
        h->owner = 2;
      }
      ++popped;
    } else if (finished) {
      break;
    } else {
      std::this_thread::yield();
    }
  }
  producer.join();
  EXPECT_EQ(bad, 0u);
  EXPECT_EQ(popped + ring.dropped(), n);
  EXPECT_EQ(pool.available_approx(), kCapacity);
  EXPECT_EQ(pool.misuse_count(), 0u);
}

}  // namespace
}  // namespace mer::platform
