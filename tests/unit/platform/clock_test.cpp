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
