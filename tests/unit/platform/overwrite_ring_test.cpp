#include "platform/overwrite_ring.h"

#include <cstdint>

#include <gtest/gtest.h>

namespace mer::platform {
namespace {

TEST(OverwriteRing, CapacityIsN) {
  OverwriteRing<std::uint32_t, 3> ring;
  EXPECT_EQ(ring.capacity(), 3u);
  for (std::uint32_t i = 0; i < 3; ++i) {
    EXPECT_FALSE(ring.push(i).has_value()) << i;
  }
  EXPECT_EQ(ring.size_approx(), 3u);
  EXPECT_EQ(ring.dropped(), 0u);
}

TEST(OverwriteRing, FullPushEvictsOldestAndCounts) {
  OverwriteRing<std::uint32_t, 4> ring;
  for (std::uint32_t i = 0; i < 4; ++i) {
    ASSERT_FALSE(ring.push(i).has_value());
  }
  // Pushing 4..9 evicts 0..5 in order.
  for (std::uint32_t i = 4; i < 10; ++i) {
    const auto evicted = ring.push(i);
    ASSERT_TRUE(evicted.has_value()) << i;
    EXPECT_EQ(*evicted, i - 4);
  }
  EXPECT_EQ(ring.dropped(), 6u);
  EXPECT_EQ(ring.size_approx(), 4u);
  // The four newest remain, oldest first.
  std::uint32_t v = 0;
  for (std::uint32_t expect = 6; expect < 10; ++expect) {
    ASSERT_TRUE(ring.try_pop(v));
    EXPECT_EQ(v, expect);
  }
  EXPECT_FALSE(ring.try_pop(v));
  EXPECT_EQ(ring.size_approx(), 0u);
}

TEST(OverwriteRing, PopMakesRoomSoNoEviction) {
  OverwriteRing<std::uint32_t, 2> ring;
  ASSERT_FALSE(ring.push(1).has_value());
  ASSERT_FALSE(ring.push(2).has_value());
  std::uint32_t v = 0;
  ASSERT_TRUE(ring.try_pop(v));
  EXPECT_EQ(v, 1u);
  EXPECT_FALSE(ring.push(3).has_value());
  EXPECT_EQ(ring.dropped(), 0u);
  ASSERT_TRUE(ring.try_pop(v));
  EXPECT_EQ(v, 2u);
  ASSERT_TRUE(ring.try_pop(v));
  EXPECT_EQ(v, 3u);
}

struct Wide {
  std::uint64_t a;
  std::uint32_t b;
  std::uint16_t c;
};

TEST(OverwriteRing, MultiWordTriviallyCopyableType) {
  OverwriteRing<Wide, 1> ring;
  ASSERT_FALSE(ring.push(Wide{1, 2, 3}).has_value());
  const auto evicted = ring.push(Wide{4, 5, 6});
  ASSERT_TRUE(evicted.has_value());
  EXPECT_EQ(evicted->a, 1u);
  EXPECT_EQ(evicted->b, 2u);
  EXPECT_EQ(evicted->c, 3u);
  Wide out{};
  ASSERT_TRUE(ring.try_pop(out));
  EXPECT_EQ(out.a, 4u);
  EXPECT_EQ(out.b, 5u);
  EXPECT_EQ(out.c, 6u);
}

}  // namespace
}  // namespace mer::platform
