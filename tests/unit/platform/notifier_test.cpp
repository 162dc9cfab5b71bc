#include "platform/notifier.h"

#include <atomic>
#include <thread>

#include <gtest/gtest.h>

#include "platform/clock.h"

namespace mer::platform {
namespace {

TEST(Notifier, WaitReturnsAtOnceWhenEpochMoved) {
  Notifier n;
  const std::uint32_t seen = n.epoch();
  n.notify();
  EXPECT_EQ(n.epoch(), seen + 1);
  n.wait(seen);  // must not block
  n.notify_all();
  EXPECT_EQ(n.epoch(), seen + 2);
}

TEST(Notifier, WaitForTimesOutWithoutNotify) {
  Notifier n;
  const std::int64_t t0 = monotonic_now_ns();
  EXPECT_FALSE(n.wait_for(n.epoch(), 3'000'000));
  const std::int64_t dt = monotonic_now_ns() - t0;
  EXPECT_GE(dt, 3'000'000);
  EXPECT_LT(dt, 500'000'000);
}

TEST(Notifier, WakesSleepingThread) {
  Notifier n;
  std::atomic<bool> woke{false};
  const std::uint32_t seen = n.epoch();
  std::thread t([&] {
    n.wait(seen);
    woke.store(true);
  });
  std::this_thread::sleep_for(std::chrono::milliseconds(5));
  n.notify();
  t.join();
  EXPECT_TRUE(woke.load());
  EXPECT_TRUE(n.wait_for(seen, 0));
}

}  // namespace
}  // namespace mer::platform
