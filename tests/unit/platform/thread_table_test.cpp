#include "platform/thread_table.h"

#include <string>

#include <gtest/gtest.h>

namespace mer::platform {
namespace {

// The tables are usable at compile time.
static_assert(kBoardRpi4.capture.priority > kBoardRpi4.tracking.priority);
static_assert(kBoardGenericX86.capture.core == -1 && kBoardGenericX86.tracking.core == -1);

TEST(ThreadTable, FindKnownBoards) {
  ASSERT_EQ(board_names().size(), 3u);
  for (const std::string_view name : board_names()) {
    EXPECT_TRUE(find_board(name).has_value()) << name;
  }
  const auto rpi = find_board("rpi4");
  ASSERT_TRUE(rpi.has_value());
  EXPECT_EQ(rpi->capture.name, "mer_capture");
  EXPECT_EQ(rpi->capture.priority, 80);
  EXPECT_EQ(rpi->tracking.priority, 70);
  EXPECT_EQ(rpi->backend.priority, 60);
  EXPECT_NE(rpi->capture.core, rpi->tracking.core);
  EXPECT_EQ(rpi->log.priority, 0);
  EXPECT_FALSE(find_board("pdp11").has_value());
}

TEST(ThreadTable, OrderingAndNameLengthOnEveryBoard) {
  for (const std::string_view name : board_names()) {
    const BoardThreads b = *find_board(name);
    EXPECT_GT(b.capture.priority, b.tracking.priority) << name;
    EXPECT_GT(b.tracking.priority, b.backend.priority) << name;
    // The back end (local BA, culling) is real-time, above the depth thread it shares the
    // map's writer lock with (priority inheritance lifts depth while the back end waits).
    EXPECT_GT(b.backend.priority, b.depth.priority) << name;
    EXPECT_EQ(b.backend.name, "mer_backend") << name;
    EXPECT_EQ(b.depth.priority, 0) << name;
    EXPECT_EQ(b.loop.priority, 0) << name;
    EXPECT_EQ(b.output.priority, 0) << name;
    for (const ThreadSpec& s :
         {b.capture, b.tracking, b.output, b.log, b.depth, b.backend, b.loop}) {
      EXPECT_LE(s.name.size(), 15u) << s.name;  // the kernel's limit, no truncation
      EXPECT_FALSE(s.name.empty());
    }
  }
}

TEST(ThreadTable, CopyIsModifiable) {
  BoardThreads b = kBoardGenericX86;  // the app applies YAML overrides to a copy
  b.tracking.core = 1;
  b.tracking.priority = 50;
  EXPECT_EQ(b.tracking.core, 1);
  EXPECT_EQ(kBoardGenericX86.tracking.core, -1);
}

}  // namespace
}  // namespace mer::platform
