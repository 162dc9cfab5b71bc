#include <cstdint>
#include <thread>
#include <vector>

#include <gtest/gtest.h>

#include "platform/overwrite_ring.h"
#include "stress_config.h"

namespace mer::platform {
namespace {

struct Item {
  std::uint64_t id;
  std::uint64_t check;  // id * kMix: a torn speculative copy that won the CAS would mismatch
};

constexpr std::uint64_t kMix = 0x9E37'79B9'7F4A'7C15ULL;

template <std::size_t N>
void run_exactly_once(std::uint64_t n, unsigned consumer_pause_every) {
  OverwriteRing<Item, N> ring;
  std::vector<std::uint8_t> evicted(n, 0);  // written by the producer only
  std::vector<std::uint8_t> popped(n, 0);   // written by the consumer only
  std::uint64_t evicted_count = 0;
  std::uint64_t evicted_bad = 0;
  std::atomic<bool> done{false};

  std::thread producer([&] {
    for (std::uint64_t i = 0; i < n; ++i) {
      if (const auto old = ring.push(Item{i, i * kMix})) {
        evicted_bad += (old->id >= n || old->check != old->id * kMix) ? 1 : 0;
        if (old->id < n) {
          ++evicted[old->id];
        }
        ++evicted_count;
      }
    }
    done.store(true, std::memory_order_release);
  });

  std::uint64_t popped_count = 0;
  std::uint64_t order_violations = 0;
  std::uint64_t popped_bad = 0;
  std::uint64_t last = 0;
  bool any = false;
  Item it{};
  unsigned k = 0;
  for (;;) {
    const bool finished = done.load(std::memory_order_acquire);
    if (ring.try_pop(it)) {
      if (it.id >= n || it.check != it.id * kMix) {
        ++popped_bad;
        continue;
      }
      order_violations += (any && it.id <= last) ? 1 : 0;
      last = it.id;
      any = true;
      ++popped[it.id];
      ++popped_count;
      // Fall behind now and then so that the producer has to evict.
      if (consumer_pause_every != 0 && ++k % consumer_pause_every == 0) {
        for (int s = 0; s < 200; ++s) {
          stress::cpu_relax();
        }
      }
    } else if (finished) {
      break;  // producer done and ring empty
    } else {
      std::this_thread::yield();  // be polite when CTest runs other tests alongside
    }
  }
  producer.join();

  EXPECT_EQ(popped_bad, 0u);
  EXPECT_EQ(evicted_bad, 0u);
  EXPECT_EQ(order_violations, 0u);
  EXPECT_EQ(popped_count + evicted_count, n);
  EXPECT_EQ(ring.dropped(), evicted_count);
  std::uint64_t lost = 0;
  std::uint64_t twice = 0;
  for (std::uint64_t i = 0; i < n; ++i) {
    const int seen = popped[i] + evicted[i];
    lost += seen == 0 ? 1 : 0;
    twice += seen > 1 ? 1 : 0;
  }
  EXPECT_EQ(lost, 0u);
  EXPECT_EQ(twice, 0u);
  // Both paths must actually have been exercised for the test to mean anything.
  EXPECT_GT(popped_count, 0u);
  EXPECT_GT(evicted_count, 0u);
  ::testing::Test::RecordProperty("popped", std::to_string(popped_count));
  ::testing::Test::RecordProperty("evicted", std::to_string(evicted_count));
}

TEST(OverwriteRingStress, ExactlyOnceSmallRing) {
  run_exactly_once<4>(stress::ring_items(4'000'000, 1'000'000), 16);
}

TEST(OverwriteRingStress, ExactlyOnceCapacityOne) {
  // Capacity 1: every push while an element is present races eviction against pop.
  run_exactly_once<1>(stress::ring_items(4'000'000, 1'000'000) / 2, 0);
}

TEST(OverwriteRingStress, ExactlyOnceLargerRing) {
  run_exactly_once<64>(stress::ring_items(4'000'000, 1'000'000) / 2, 0);
}

}  // namespace
}  // namespace mer::platform
