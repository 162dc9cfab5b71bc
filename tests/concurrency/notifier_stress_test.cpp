#include <atomic>
#include <cstdint>
#include <thread>

#include <gtest/gtest.h>

#include "platform/notifier.h"
#include "platform/spsc_ring.h"
#include "stress_config.h"

namespace mer::platform {
namespace {

TEST(NotifierStress, PingPongNoLostWakeups) {
  // Each side blocks in wait() until the other answers: one lost wake-up hangs the test
  // (caught by the CTest timeout).
  const std::uint32_t rounds = static_cast<std::uint32_t>(stress::iterations(100'000, 2));
  Notifier ping;
  Notifier pong;
  std::atomic<std::uint32_t> ball{0};
  std::thread partner([&] {
    for (std::uint32_t i = 0; i < rounds; ++i) {
      std::uint32_t seen = ping.epoch();
      while (ball.load(std::memory_order_acquire) != 2 * i + 1) {
        ping.wait(seen);
        seen = ping.epoch();
      }
      ball.store(2 * i + 2, std::memory_order_release);
      pong.notify();
    }
  });
  for (std::uint32_t i = 0; i < rounds; ++i) {
    ball.store(2 * i + 1, std::memory_order_release);
    ping.notify();
    std::uint32_t seen = pong.epoch();
    while (ball.load(std::memory_order_acquire) != 2 * i + 2) {
      pong.wait(seen);
      seen = pong.epoch();
    }
  }
  partner.join();
  EXPECT_EQ(ball.load(), 2 * rounds);
}

TEST(NotifierStress, SleepingConsumerGetsEveryItem) {
  // The documented pattern: read epoch, drain the ring, wait(epoch).
  const std::uint64_t n = stress::iterations(1'000'000, 2);
  SpscRing<std::uint64_t, 64> ring;
  Notifier notifier;
  std::thread producer([&] {
    for (std::uint64_t i = 0; i < n; ++i) {
      while (!ring.try_push(i)) {
        std::this_thread::yield();
      }
      if (i % 7 == 0) {  // bursty notification: also exercises spurious/merged wake-ups
        notifier.notify();
      }
    }
    notifier.notify();
  });
  std::uint64_t expected = 0;
  std::uint64_t bad = 0;
  std::uint64_t waits = 0;
  while (expected < n) {
    const std::uint32_t seen = notifier.epoch();
    std::uint64_t v = 0;
    bool got = false;
    while (ring.try_pop(v)) {
      bad += v != expected ? 1 : 0;
      ++expected;
      got = true;
    }
    if (!got && expected < n) {
      notifier.wait(seen);
      ++waits;
    }
  }
  producer.join();
  EXPECT_EQ(bad, 0u);
  EXPECT_EQ(expected, n);
  RecordProperty("waits", std::to_string(waits));
}

}  // namespace
}  // namespace mer::platform
