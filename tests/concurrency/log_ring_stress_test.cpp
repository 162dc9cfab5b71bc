#include <atomic>
#include <cstdio>
#include <cstring>
#include <thread>
#include <vector>

#include <gtest/gtest.h>

#include "platform/log_ring.h"
#include "stress_config.h"

namespace mer::platform {
namespace {

TEST(LogRingStress, ManyProducersOneConsumerNothingLostOrReordered) {
  constexpr int kProducers = 4;
  const std::uint64_t per_producer = stress::iterations(200'000, 4);
  LogRing ring(256);
  std::atomic<int> producers_done{0};
  std::atomic<std::uint64_t> full_retries{0};

  std::vector<std::thread> producers;
  for (int p = 0; p < kProducers; ++p) {
    producers.emplace_back([&, p] {
      char name[16];
      std::snprintf(name, sizeof(name), "prod%d", p);
      set_thread_log_name(name);
      std::uint64_t retries = 0;
      for (std::uint64_t i = 0; i < per_producer; ++i) {
        while (
            !ring.try_log(LogLevel::kInfo, "p=%d i=%llu", p, static_cast<unsigned long long>(i))) {
          ++retries;
          std::this_thread::yield();
        }
      }
      full_retries.fetch_add(retries);
      producers_done.fetch_add(1);
    });
  }

  std::vector<std::uint64_t> next(kProducers, 0);
  std::uint64_t bad = 0;
  std::uint64_t received = 0;
  auto sink = [&](const LogRecord& r) {
    int p = -1;
    unsigned long long i = 0;
    char expect_name[16];
    if (std::sscanf(r.text, "p=%d i=%llu", &p, &i) != 2 || p < 0 || p >= kProducers) {
      ++bad;
      return;
    }
    std::snprintf(expect_name, sizeof(expect_name), "prod%d", p);
    bad +=
        (i != next[static_cast<std::size_t>(p)] || std::strcmp(r.thread, expect_name) != 0) ? 1 : 0;
    next[static_cast<std::size_t>(p)] = i + 1;
    ++received;
  };
  for (;;) {
    const bool all_done = producers_done.load() == kProducers;
    if (ring.drain(sink) == 0 && all_done) {
      break;
    }
  }
  for (auto& t : producers) {
    t.join();
  }
  EXPECT_EQ(bad, 0u);
  EXPECT_EQ(received, per_producer * kProducers);
  for (int p = 0; p < kProducers; ++p) {
    EXPECT_EQ(next[static_cast<std::size_t>(p)], per_producer) << p;
  }
  EXPECT_EQ(ring.dropped(), full_retries.load());  // each failed try_log counted once
}

}  // namespace
}  // namespace mer::platform
