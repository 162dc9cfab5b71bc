#include "platform/memory.h"

#include <cstdlib>
#include <string>

#if defined(__GLIBC__)
#include <malloc.h>
#endif

#include <gtest/gtest.h>

namespace mer::platform {
namespace {

TEST(Memory, LockMemoryReportsOutcome) {
  std::string error;
  const bool ok = lock_memory(&error);
  if (ok) {
    EXPECT_TRUE(error.empty());
    EXPECT_TRUE(unlock_memory(&error)) << error;
  } else {
    // Not permitted here (no CAP_IPC_LOCK / small RLIMIT_MEMLOCK): the message says why.
    EXPECT_NE(error.find("mlockall"), std::string::npos) << error;
    EXPECT_NE(error.find("errno"), std::string::npos) << error;
  }
}

TEST(Memory, NullErrorPointerIsAccepted) {
  if (lock_memory(nullptr)) {
    EXPECT_TRUE(unlock_memory(nullptr));
  } else {
    SUCCEED() << "mlockall not permitted here; the call returned false without crashing";
  }
}

// A fixed threshold sends a block above it to a mapping of its own (glibc counts those in
// mallinfo2().hblks) and one below it to the heap, the same size either way round.
TEST(Memory, MmapThresholdDecidesWhereABlockLives) {
#if defined(__SANITIZE_ADDRESS__) || defined(__SANITIZE_THREAD__)
  GTEST_SKIP() << "a sanitizer's allocator replaces glibc's: nothing to observe";
#elif defined(__GLIBC__)
  // Large enough that no free chunk of the heap can serve it, which glibc would use first.
  constexpr std::size_t kBlock = std::size_t{8} << 20U;
  auto own_mapping = [](std::size_t bytes) {
    const std::size_t before = mallinfo2().hblks;
    char* volatile p = static_cast<char*>(std::malloc(bytes));
    p[0] = 1;  // used, so the allocation stays
    const std::size_t after = mallinfo2().hblks;
    std::free(p);
    return after > before;
  };
  std::string error;
  ASSERT_TRUE(set_mmap_threshold(kBlock / 2, &error)) << error;
  EXPECT_TRUE(own_mapping(kBlock));
  ASSERT_TRUE(set_mmap_threshold(2 * kBlock, &error)) << error;
  EXPECT_FALSE(own_mapping(kBlock));
  ASSERT_TRUE(set_mmap_threshold(128U << 10U, &error)) << error;  // the pipeline's default
#else
  GTEST_SKIP() << "mmap threshold: glibc only";
#endif
}

TEST(Memory, MmapThresholdOutOfRangeIsRefusedWithItsValue) {
  std::string error;
  EXPECT_FALSE(set_mmap_threshold(0, &error));
  EXPECT_NE(error.find("mmap threshold 0 bytes"), std::string::npos) << error;
  EXPECT_FALSE(set_mmap_threshold(kMaxMmapThresholdBytes + 1, &error));
  EXPECT_NE(error.find(std::to_string(kMaxMmapThresholdBytes + 1)), std::string::npos) << error;
  EXPECT_FALSE(set_mmap_threshold(kMaxMmapThresholdBytes + 1, nullptr));
}

}  // namespace
}  // namespace mer::platform
