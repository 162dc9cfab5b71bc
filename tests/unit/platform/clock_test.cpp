#include "platform/clock.h"

#include <memory>
#include <thread>

#include <gtest/gtest.h>

namespace mer::platform {
namespace {

TEST(Clock, MonotonicAdvances) {
  const std::int64_t a = monotonic_now_ns();
  std::this_thread::sleep_for(std::chrono::milliseconds(2));
  const std::int64_t b = monotonic_now_ns();
  EXPECT_GE(b - a, 2'000'000);
  EXPECT_LT(b - a, 2'000'000'000);  // sanity: not seconds
  MonotonicClock clock;
  const std::int64_t c = clock.now_ns();
  EXPECT_GE(c, b);
}

TEST(Clock, CpuClocksCountWorkNotSleep) {
  const std::int64_t p0 = process_cpu_ns();
  const std::int64_t t0 = thread_cpu_ns();
  std::this_thread::sleep_for(std::chrono::milliseconds(20));
  const std::int64_t t1 = thread_cpu_ns();
  EXPECT_LT(t1 - t0, 10'000'000) << "sleeping uses no CPU";
  volatile double x = 1.0;
  const std::int64_t w0 = monotonic_now_ns();
  while (monotonic_now_ns() - w0 < 20'000'000) x = x * 1.0000001 + 1e-9;  // ~20 ms of work
  const std::int64_t t2 = thread_cpu_ns();
  const std::int64_t p2 = process_cpu_ns();
  EXPECT_GT(t2 - t1, 5'000'000) << "busy work is counted";
  EXPECT_GE(p2 - p0, t2 - t0) << "the process clock holds the thread's";
}

TEST(Clock, LockstepIsSetAndAdvancedExplicitly) {
  LockstepClock lockstep(1'000);
  const Clock& clock = lockstep;
  EXPECT_EQ(clock.now_ns(), 1'000);
  lockstep.set_ns(1'305'031'102'175'304'000);  // a TUM-style timestamp
  EXPECT_EQ(clock.now_ns(), 1'305'031'102'175'304'000);
  lockstep.advance_ns(33'333'333);
  EXPECT_EQ(clock.now_ns(), 1'305'031'102'208'637'333);
  std::this_thread::sleep_for(std::chrono::milliseconds(1));
  EXPECT_EQ(clock.now_ns(), 1'305'031'102'208'637'333);  // wall time does not move it
}

TEST(Clock, LockstepReadFromAnotherThread) {
  LockstepClock clock;
  std::thread reader([&] {
    while (clock.now_ns() != 42) {
      std::this_thread::yield();
    }
  });
  clock.set_ns(42);
  reader.join();
  EXPECT_EQ(clock.now_ns(), 42);
}

}  // namespace
}  // namespace mer::platform
