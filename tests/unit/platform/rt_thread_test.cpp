#include "platform/rt_thread.h"

#include <pthread.h>
#include <sched.h>

#include <atomic>
#include <cstring>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "platform/log_ring.h"

namespace mer::platform {
namespace {

std::vector<std::string> drain_default_log_texts() {
  std::vector<std::string> out;
  default_log().drain([&](const LogRecord& r) { out.emplace_back(r.text); });
  return out;
}

TEST(RtThread, RunsBodyWithNameAppliedFirst) {
  std::string seen_name;
  std::string seen_log_name;
  RtThread t;
  EXPECT_FALSE(t.joinable());
  ASSERT_TRUE(t.start(ThreadSpec{"mer_unit_worker_with_long_name", -1, 0}, [&] {
    char buf[32] = {};
    pthread_getname_np(pthread_self(), buf, sizeof(buf));
    seen_name = buf;
    seen_log_name = thread_log_name();
  }));
  EXPECT_TRUE(t.joinable());
  EXPECT_TRUE(t.report().started);
  EXPECT_TRUE(t.report().name_applied);
  EXPECT_TRUE(t.report().fully_applied());
  EXPECT_TRUE(t.report().warning.empty());
  EXPECT_EQ(t.name(), "mer_unit_worker_with_long_name");
  t.join();
  EXPECT_FALSE(t.joinable());
  EXPECT_EQ(seen_name, "mer_unit_worker");  // truncated to 15 chars
  EXPECT_EQ(seen_log_name, "mer_unit_worker");
}

TEST(RtThread, StartTwiceFailsWhileRunning) {
  std::atomic<bool> release{false};
  RtThread t;
  ASSERT_TRUE(t.start(ThreadSpec{"mer_twice", -1, 0}, [&] {
    while (!release.load()) {
      std::this_thread::yield();
    }
  }));
  EXPECT_FALSE(t.start(ThreadSpec{"mer_twice2", -1, 0}, [] {}));
  release.store(true);
  t.join();
  EXPECT_TRUE(t.start(ThreadSpec{"mer_again", -1, 0}, [] {}));  // reusable after join
}

TEST(RtThread, PinsToAllowedCore) {
  cpu_set_t allowed;
  CPU_ZERO(&allowed);
  ASSERT_EQ(sched_getaffinity(0, sizeof(allowed), &allowed), 0);
  int core = 0;
  while (!CPU_ISSET(core, &allowed)) {
    ++core;
  }
  int ran_on_mask_count = -1;
  bool in_mask = false;
  RtThread t(ThreadSpec{"mer_pinned", core, 0}, [&] {
    cpu_set_t mine;
    CPU_ZERO(&mine);
    pthread_getaffinity_np(pthread_self(), sizeof(mine), &mine);
    ran_on_mask_count = CPU_COUNT(&mine);
    in_mask = CPU_ISSET(core, &mine);
  });
  t.join();
  EXPECT_TRUE(t.report().affinity_requested);
  EXPECT_TRUE(t.report().affinity_applied);
  EXPECT_EQ(ran_on_mask_count, 1);
  EXPECT_TRUE(in_mask);
}

TEST(RtThread, OutOfRangeCoreFallsBackWithOneWarning) {
  static_cast<void>(drain_default_log_texts());
  bool ran = false;
  RtThread t;
  ASSERT_TRUE(t.start(ThreadSpec{"mer_badcore", 1000, 0}, [&] { ran = true; }));
  t.join();
  EXPECT_TRUE(ran);
  EXPECT_TRUE(t.report().affinity_requested);
  EXPECT_FALSE(t.report().affinity_applied);
  EXPECT_FALSE(t.report().fully_applied());
  EXPECT_NE(t.report().warning.find("core 1000"), std::string::npos) << t.report().warning;
  const auto logs = drain_default_log_texts();
  ASSERT_EQ(logs.size(), 1u);
  EXPECT_NE(logs[0].find("thread 'mer_badcore'"), std::string::npos) << logs[0];
  EXPECT_NE(logs[0].find("core 1000"), std::string::npos) << logs[0];
}

TEST(RtThread, InvalidPriorityFallsBackWithOneWarning) {
  static_cast<void>(drain_default_log_texts());
  int policy = -1;
  RtThread t(ThreadSpec{"mer_badprio", -1, 150}, [&] {
    sched_param p{};
    pthread_getschedparam(pthread_self(), &policy, &p);
  });
  t.join();
  EXPECT_EQ(policy, SCHED_OTHER);
  EXPECT_TRUE(t.report().priority_requested);
  EXPECT_FALSE(t.report().priority_applied);
  const auto logs = drain_default_log_texts();
  ASSERT_EQ(logs.size(), 1u);
  EXPECT_NE(logs[0].find("mer_badprio"), std::string::npos) << logs[0];
  EXPECT_NE(logs[0].find("150"), std::string::npos) << logs[0];
}

TEST(RtThread, FifoPriorityAppliedOrReportedRefused) {
  static_cast<void>(drain_default_log_texts());
  int policy = -1;
  int prio = -1;
  RtThread t(ThreadSpec{"mer_fifo", -1, 10}, [&] {
    sched_param p{};
    pthread_getschedparam(pthread_self(), &policy, &p);
    prio = p.sched_priority;
  });
  t.join();
  const auto logs = drain_default_log_texts();
  if (t.report().priority_applied) {  // CAP_SYS_NICE / rtprio limit present
    EXPECT_EQ(policy, SCHED_FIFO);
    EXPECT_EQ(prio, 10);
    EXPECT_TRUE(logs.empty());
  } else {  // EPERM: fell back, said so once
    EXPECT_EQ(policy, SCHED_OTHER);
    ASSERT_EQ(logs.size(), 1u);
    EXPECT_NE(logs[0].find("mer_fifo"), std::string::npos) << logs[0];
  }
}

TEST(RtThread, MoveTransfersOwnership) {
  std::atomic<int> runs{0};
  RtThread a(ThreadSpec{"mer_move", -1, 0}, [&] { runs.fetch_add(1); });
  RtThread b = std::move(a);
  EXPECT_FALSE(a.joinable());  // NOLINT(bugprone-use-after-move)
  b.join();
  EXPECT_EQ(runs.load(), 1);
}

}  // namespace
}  // namespace mer::platform
