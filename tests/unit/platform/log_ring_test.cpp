#include "platform/log_ring.h"

#include <cstdio>
#include <cstring>
#include <string>
#include <thread>
#include <vector>

#include <gtest/gtest.h>

#include "platform/alloc_counter.h"

namespace mer::platform {
namespace {

std::vector<LogRecord> drain_all(LogRing& ring) {
  std::vector<LogRecord> out;
  ring.drain([&](const LogRecord& r) { out.push_back(r); });
  return out;
}

TEST(LogRing, FormatsLevelThreadAndText) {
  LogRing ring(8);
  EXPECT_EQ(ring.capacity(), 8u);
  set_thread_log_name("unit_test_thread_long_name");
  EXPECT_STREQ(thread_log_name(), "unit_test_threa");  // 15 chars
  ASSERT_TRUE(ring.try_log(LogLevel::kWarn, "frame %d dropped: %s", 42, "ring full"));
  set_thread_log_name("main");
  const auto recs = drain_all(ring);
  ASSERT_EQ(recs.size(), 1u);
  EXPECT_EQ(recs[0].level, LogLevel::kWarn);
  EXPECT_STREQ(recs[0].text, "frame 42 dropped: ring full");
  EXPECT_STREQ(recs[0].thread, "unit_test_threa");
  EXPECT_GT(recs[0].t_ns, 0);

  char line[512];
  const std::size_t n = format_log_record(recs[0], line, sizeof(line));
  EXPECT_EQ(n, std::strlen(line));
  EXPECT_NE(std::string(line).find(" W [unit_test_threa] frame 42 dropped: ring full\n"),
            std::string::npos)
      << line;
}

TEST(LogRing, TruncatesLongText) {
  LogRing ring(2);
  const std::string big(500, 'x');
  ASSERT_TRUE(ring.try_log(LogLevel::kInfo, "%s", big.c_str()));
  const auto recs = drain_all(ring);
  ASSERT_EQ(recs.size(), 1u);
  EXPECT_EQ(std::strlen(recs[0].text), kLogTextSize - 1);
  EXPECT_EQ(recs[0].text[kLogTextSize - 2], 'x');
}

TEST(LogRing, FullRingDropsAndCounts) {
  LogRing ring(4);
  for (int i = 0; i < 4; ++i) {
    EXPECT_TRUE(ring.try_log(LogLevel::kInfo, "m%d", i));
  }
  EXPECT_FALSE(ring.try_log(LogLevel::kInfo, "lost"));
  EXPECT_FALSE(ring.try_log(LogLevel::kError, "lost too"));
  EXPECT_EQ(ring.dropped(), 2u);
  const auto recs = drain_all(ring);
  ASSERT_EQ(recs.size(), 4u);
  for (int i = 0; i < 4; ++i) {
    EXPECT_EQ(std::string(recs[static_cast<std::size_t>(i)].text), "m" + std::to_string(i));
  }
  // Space again after the drain, order continues across the wrap.
  EXPECT_TRUE(ring.try_log(LogLevel::kInfo, "after"));
  const auto more = drain_all(ring);
  ASSERT_EQ(more.size(), 1u);
  EXPECT_STREQ(more[0].text, "after");
}

TEST(LogRing, LoggingDoesNotAllocate) {
  LogRing ring(16);
  ASSERT_TRUE(ring.try_log(LogLevel::kInfo, "warm-up %d", 0));
  const std::uint64_t a0 = alloc::thread_allocations();
  for (int i = 0; i < 10; ++i) {
    ASSERT_TRUE(ring.try_log(LogLevel::kInfo, "seq=%d t=%.3f ms name=%s", i, 1.5 * i, "x"));
  }
  EXPECT_EQ(alloc::thread_allocations() - a0, 0u);
}

TEST(LogRing, RejectsNonPowerOfTwo) {
  EXPECT_THROW(LogRing(6), std::invalid_argument);
  EXPECT_THROW(LogRing(1), std::invalid_argument);
}

TEST(LogDrain, WritesFilteredRecordsAndDrainsOnStop) {
  LogRing ring(64);
  std::FILE* f = std::tmpfile();
  ASSERT_NE(f, nullptr);
  {
    LogDrain drain(ring, f, LogLevel::kInfo, 5);
    ASSERT_TRUE(drain.start(ThreadSpec{"mer_log_test", -1, 0}));
    ASSERT_TRUE(ring.try_log(LogLevel::kDebug, "hidden debug"));
    ASSERT_TRUE(ring.try_log(LogLevel::kInfo, "info one"));
    ASSERT_TRUE(ring.try_log(LogLevel::kError, "error two"));
    drain.stop();  // must write everything before returning
    EXPECT_EQ(drain.written(), 2u);
  }
  std::rewind(f);
  std::string content;
  char buf[256];
  while (std::fgets(buf, sizeof(buf), f) != nullptr) {
    content += buf;
  }
  std::fclose(f);
  EXPECT_EQ(content.find("hidden debug"), std::string::npos);
  EXPECT_NE(content.find(" I [main] info one\n"), std::string::npos) << content;
  EXPECT_NE(content.find(" E [main] error two\n"), std::string::npos) << content;
}

TEST(LogDrain, ReportsDrops) {
  LogRing ring(2);
  for (int i = 0; i < 5; ++i) {
    static_cast<void>(ring.try_log(LogLevel::kInfo, "m%d", i));
  }
  std::FILE* f = std::tmpfile();
  ASSERT_NE(f, nullptr);
  LogDrain drain(ring, f);
  drain.stop();
  std::rewind(f);
  std::string content;
  char buf[256];
  while (std::fgets(buf, sizeof(buf), f) != nullptr) {
    content += buf;
  }
  std::fclose(f);
  EXPECT_NE(content.find("log: 3 records dropped"), std::string::npos) << content;
}

TEST(LogRing, DefaultLogMacros) {
  LogRing& ring = default_log();
  EXPECT_EQ(&ring, &default_log());
  static_cast<void>(drain_all(ring));  // whatever earlier tests left
  MER_LOG_INFO("macro info %d", 1);
  MER_LOG_WARN("macro warn");
  MER_LOG_ERROR("macro error %s", "x");
  MER_LOG_DEBUG("macro debug");
  const auto recs = drain_all(ring);
  ASSERT_EQ(recs.size(), 4u);
  EXPECT_EQ(recs[0].level, LogLevel::kInfo);
  EXPECT_STREQ(recs[0].text, "macro info 1");
  EXPECT_EQ(recs[1].level, LogLevel::kWarn);
  EXPECT_EQ(recs[2].level, LogLevel::kError);
  EXPECT_EQ(recs[3].level, LogLevel::kDebug);
  MER_LOG_INFO("flushed at exit");
  flush_default_log_to_stderr();
  EXPECT_TRUE(drain_all(ring).empty());
}

}  // namespace
}  // namespace mer::platform
