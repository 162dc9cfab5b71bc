#include "platform/spsc_ring.h"

#include <memory>
#include <string>

#include <gtest/gtest.h>

namespace mer::platform {
namespace {

TEST(SpscRing, CapacityIsNAndAllSlotsUsable) {
  SpscRing<int, 8> ring;
  EXPECT_EQ(ring.capacity(), 8u);
  for (int i = 0; i < 8; ++i) {
    ASSERT_TRUE(ring.try_push(i)) << i;
  }
  EXPECT_EQ(ring.size_approx(), 8u);
  EXPECT_FALSE(ring.try_push(99));  // full
  EXPECT_EQ(ring.size_approx(), 8u);
}

TEST(SpscRing, FifoOrderAcrossWrapAround) {
  SpscRing<int, 4> ring;
  int next_in = 0;
  int next_out = 0;
  // 10 rounds of push 3 / pop 3 wraps the 4-slot ring several times.
  for (int round = 0; round < 10; ++round) {
    for (int k = 0; k < 3; ++k) {
      ASSERT_TRUE(ring.try_push(next_in++));
    }
    for (int k = 0; k < 3; ++k) {
      int v = -1;
      ASSERT_TRUE(ring.try_pop(v));
      EXPECT_EQ(v, next_out++);
    }
  }
  EXPECT_EQ(next_out, 30);
}

TEST(SpscRing, EmptyPopFailsAndLeavesOutput) {
  SpscRing<int, 2> ring;
  EXPECT_TRUE(ring.empty_approx());
  int v = 42;
  EXPECT_FALSE(ring.try_pop(v));
  EXPECT_EQ(v, 42);
  ASSERT_TRUE(ring.try_push(7));
  EXPECT_FALSE(ring.empty_approx());
  ASSERT_TRUE(ring.try_pop(v));
  EXPECT_EQ(v, 7);
  EXPECT_FALSE(ring.try_pop(v));
  EXPECT_TRUE(ring.empty_approx());
}

TEST(SpscRing, MoveOnlyTypeAndFailedPushKeepsValue) {
  SpscRing<std::unique_ptr<int>, 2> ring;
  ASSERT_TRUE(ring.try_push(std::make_unique<int>(1)));
  ASSERT_TRUE(ring.try_push(std::make_unique<int>(2)));
  auto third = std::make_unique<int>(3);
  EXPECT_FALSE(ring.try_push(std::move(third)));
  // A failed push must not consume the value.
  ASSERT_NE(third, nullptr);  // NOLINT(bugprone-use-after-move)
  EXPECT_EQ(*third, 3);       // NOLINT(bugprone-use-after-move)
  std::unique_ptr<int> out;
  ASSERT_TRUE(ring.try_pop(out));
  ASSERT_NE(out, nullptr);
  EXPECT_EQ(*out, 1);
  ASSERT_TRUE(ring.try_pop(out));
  EXPECT_EQ(*out, 2);
}

TEST(SpscRing, DestroysRemainingElements) {
  auto counter = std::make_shared<int>(0);
  {
    SpscRing<std::shared_ptr<int>, 4> ring;
    ASSERT_TRUE(ring.try_push(counter));
    ASSERT_TRUE(ring.try_push(counter));
    EXPECT_EQ(counter.use_count(), 3);
    std::shared_ptr<int> out;
    ASSERT_TRUE(ring.try_pop(out));
    out.reset();
    EXPECT_EQ(counter.use_count(), 2);  // popped slot destroyed
  }
  EXPECT_EQ(counter.use_count(), 1);  // ring destructor destroyed the remaining one
}

TEST(SpscRing, CopyPushOfNonTrivialType) {
  SpscRing<std::string, 2> ring;
  const std::string s = "a string longer than the small-string buffer of libstdc++";
  ASSERT_TRUE(ring.try_push(s));
  std::string out;
  ASSERT_TRUE(ring.try_pop(out));
  EXPECT_EQ(out, s);
}

}  // namespace
}  // namespace mer::platform
