#include <cstdint>
#include <memory>
#include <thread>

#include <gtest/gtest.h>

#include "platform/spsc_ring.h"
#include "stress_config.h"

namespace mer::platform {
namespace {

/// Two words that must always match: a torn or stale slot read shows up as a mismatch.
struct Item {
  std::uint64_t seq;
  std::uint64_t check;
};

constexpr std::uint64_t kMix = 0x9E37'79B9'7F4A'7C15ULL;

TEST(SpscRingStress, EveryItemArrivesOnceInOrder) {
  const std::uint64_t n = stress::ring_items(5'000'000, 1'000'000);
  SpscRing<Item, 1024> ring;
  std::uint64_t producer_full_spins = 0;
  std::thread producer([&] {
    for (std::uint64_t i = 0; i < n; ++i) {
      while (!ring.try_push(Item{i, i * kMix})) {
        ++producer_full_spins;
        std::this_thread::yield();
      }
    }
  });
  std::uint64_t expected = 0;
  std::uint64_t bad = 0;
  Item it{};
  while (expected < n) {
    if (ring.try_pop(it)) {
      bad += (it.seq != expected || it.check != expected * kMix) ? 1 : 0;
      ++expected;
    } else {
      std::this_thread::yield();
    }
  }
  producer.join();
  EXPECT_EQ(bad, 0u);
  EXPECT_EQ(expected, n);
  EXPECT_FALSE(ring.try_pop(it));
  EXPECT_EQ(ring.size_approx(), 0u);
  RecordProperty("items", std::to_string(n));
  RecordProperty("producer_full_spins", std::to_string(producer_full_spins));
}

TEST(SpscRingStress, MoveOnlyPayloadSmallRing) {
  // A tiny ring maximizes full/empty transitions; unique_ptr checks ownership transfer.
  const std::uint64_t n = stress::ring_items(5'000'000, 1'000'000) / 10;
  SpscRing<std::unique_ptr<std::uint64_t>, 2> ring;
  std::thread producer([&] {
    for (std::uint64_t i = 0; i < n; ++i) {
      auto p = std::make_unique<std::uint64_t>(i);
      while (!ring.try_push(std::move(p))) {
        std::this_thread::yield();
      }
    }
  });
  std::uint64_t expected = 0;
  std::uint64_t bad = 0;
  std::unique_ptr<std::uint64_t> out;
  while (expected < n) {
    if (ring.try_pop(out)) {
      bad += (out == nullptr || *out != expected) ? 1 : 0;
      ++expected;
    } else {
      std::this_thread::yield();
    }
  }
  producer.join();
  EXPECT_EQ(bad, 0u);
  EXPECT_EQ(expected, n);
}

}  // namespace
}  // namespace mer::platform
