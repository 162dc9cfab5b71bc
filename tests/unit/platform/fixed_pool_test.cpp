#include "platform/fixed_pool.h"

#include <cstdint>
#include <utility>
#include <vector>

#include <gtest/gtest.h>

#include "platform/overwrite_ring.h"

namespace mer::platform {
namespace {

struct Buffer {
  std::vector<std::uint8_t> bytes;
  std::size_t id = 0;
};

TEST(FixedPool, AcquireUntilExhaustedThenEmptyHandleCounted) {
  FixedPool<int> pool(3);
  EXPECT_EQ(pool.capacity(), 3u);
  EXPECT_EQ(pool.available_approx(), 3u);
  auto a = pool.acquire();
  auto b = pool.acquire();
  auto c = pool.acquire();
  ASSERT_TRUE(a && b && c);
  EXPECT_NE(a.index(), b.index());
  EXPECT_NE(b.index(), c.index());
  EXPECT_NE(a.index(), c.index());
  EXPECT_EQ(pool.available_approx(), 0u);
  EXPECT_EQ(pool.exhausted_count(), 0u);
  auto d = pool.acquire();
  EXPECT_FALSE(d);
  EXPECT_EQ(d.get(), nullptr);
  EXPECT_EQ(d.index(), kInvalidPoolIndex);
  auto e = pool.acquire();
  EXPECT_FALSE(e);
  EXPECT_EQ(pool.exhausted_count(), 2u);
}

TEST(FixedPool, HandleDestructionAndResetReturnTheSlot) {
  FixedPool<int> pool(2);
  {
    auto a = pool.acquire();
    *a = 11;
    EXPECT_EQ(pool.available_approx(), 1u);
  }
  EXPECT_EQ(pool.available_approx(), 2u);
  auto b = pool.acquire();
  const std::uint32_t idx = b.index();
  b.reset();
  EXPECT_FALSE(b);
  EXPECT_EQ(pool.available_approx(), 2u);
  // LIFO: the slot just released comes back first and keeps its contents.
  auto c = pool.acquire();
  EXPECT_EQ(c.index(), idx);
}

TEST(FixedPool, MoveTransfersOwnership) {
  FixedPool<int> pool(2);
  auto a = pool.acquire();
  const std::uint32_t idx = a.index();
  PoolHandle<int> b = std::move(a);
  EXPECT_FALSE(a);  // NOLINT(bugprone-use-after-move): moved-from is specified empty
  ASSERT_TRUE(b);
  EXPECT_EQ(b.index(), idx);
  EXPECT_EQ(pool.available_approx(), 1u);
  PoolHandle<int> c = pool.acquire();
  c = std::move(b);  // c's old slot is released, c now owns idx
  EXPECT_EQ(c.index(), idx);
  EXPECT_EQ(pool.available_approx(), 1u);
}

TEST(FixedPool, InitCallbackRunsOncePerSlot) {
  std::size_t calls = 0;
  FixedPool<Buffer> pool(4, [&](Buffer& b, std::size_t i) {
    b.bytes.resize(640 * 480);
    b.id = i;
    ++calls;
  });
  EXPECT_EQ(calls, 4u);
  for (std::uint32_t i = 0; i < 4; ++i) {
    EXPECT_EQ(pool.slot(i).id, i);
    EXPECT_EQ(pool.slot(i).bytes.size(), 640u * 480u);
  }
  auto h = pool.acquire();
  EXPECT_EQ(h->id, h.index());
  EXPECT_EQ(&*h, &pool.slot(h.index()));
}

TEST(FixedPool, ReleaseRawAdoptRoundTripThroughOverwriteRing) {
  FixedPool<int> pool(4);
  OverwriteRing<std::uint32_t, 2> ring;
  std::vector<std::uint32_t> pushed;
  for (int frame = 0; frame < 3; ++frame) {
    auto h = pool.acquire();
    ASSERT_TRUE(h);
    *h = 100 + frame;
    const std::uint32_t idx = h.release_raw();
    EXPECT_FALSE(h);
    EXPECT_EQ(h.release_raw(), kInvalidPoolIndex);
    pushed.push_back(idx);
    if (auto evicted = ring.push(idx)) {
      // Drop-oldest: the evicted raw slot goes back to the pool.
      EXPECT_EQ(*evicted, pushed[0]);
      pool.adopt(*evicted).reset();
    }
  }
  EXPECT_EQ(pool.available_approx(), 2u);  // 4 - 2 still in the ring
  std::uint32_t idx = 0;
  ASSERT_TRUE(ring.try_pop(idx));
  EXPECT_EQ(idx, pushed[1]);
  auto h = pool.adopt(idx);
  ASSERT_TRUE(h);
  EXPECT_EQ(*h, 101);
  EXPECT_EQ(h.index(), idx);
  h.reset();
  ASSERT_TRUE(ring.try_pop(idx));
  pool.adopt(idx).reset();
  EXPECT_EQ(pool.available_approx(), 4u);
  EXPECT_EQ(pool.misuse_count(), 0u);
}

TEST(FixedPool, ZeroCapacityIsAlwaysExhausted) {
  FixedPool<int> pool(0);
  EXPECT_FALSE(pool.acquire());
  EXPECT_EQ(pool.exhausted_count(), 1u);
}

#ifdef NDEBUG
TEST(FixedPool, InvalidAdoptIsRefusedAndCounted) {
  FixedPool<int> pool(2);
  auto h = pool.acquire();
  EXPECT_FALSE(pool.adopt(h.index()));  // owned by a handle, not released raw
  EXPECT_FALSE(pool.adopt(7));          // out of range
  const std::uint32_t raw = h.release_raw();
  auto first = pool.adopt(raw);
  EXPECT_TRUE(first);
  EXPECT_FALSE(pool.adopt(raw));  // adopted twice
  EXPECT_EQ(pool.misuse_count(), 3u);
  first.reset();
  EXPECT_EQ(pool.available_approx(), 2u);
}
#else
TEST(FixedPoolDeathTest, InvalidAdoptAsserts) {
  FixedPool<int> pool(2);
  EXPECT_DEATH(static_cast<void>(pool.adopt(7)), "adopt");
}
#endif

}  // namespace
}  // namespace mer::platform
