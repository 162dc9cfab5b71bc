#include "platform/pi_mutex.h"

#include <sched.h>

#include <atomic>
#include <cstdint>
#include <mutex>
#include <thread>
#include <vector>

#include <gtest/gtest.h>

#include "platform/clock.h"
#include "platform/rt_thread.h"

namespace mer::platform {
namespace {

TEST(PiMutex, UsesPriorityInheritanceOnLinux) {
  PiMutex m;
  EXPECT_TRUE(m.priority_inheritance());  // glibc supports PTHREAD_PRIO_INHERIT
}

TEST(PiMutex, TryLockFailsWhileAnotherThreadOwnsIt) {
  PiMutex m;
  m.lock();
  bool taken = true;
  std::thread([&] { taken = m.try_lock(); }).join();
  EXPECT_FALSE(taken);
  m.unlock();
  std::thread([&] {
    taken = m.try_lock();
    if (taken) m.unlock();
  }).join();
  EXPECT_TRUE(taken);
}

TEST(PiMutex, MutualExclusion) {
  PiMutex m;
  constexpr int kThreads = 4;
  constexpr int kIncrements = 50'000;
  std::int64_t counter = 0;  // plain: only the mutex orders the increments
  std::vector<std::thread> threads;
  for (int t = 0; t < kThreads; ++t) {
    threads.emplace_back([&] {
      for (int i = 0; i < kIncrements; ++i) {
        const std::lock_guard<PiMutex> lock(m);
        ++counter;
      }
    });
  }
  for (auto& t : threads) t.join();
  EXPECT_EQ(counter, std::int64_t{kThreads} * kIncrements);
}

/// Times of the classic inversion: low (FIFO 10) owns the mutex and needs kLowWorkNs of CPU,
/// high (FIFO 30) waits for it, mid (FIFO 20) spins kMidSpinNs; all on one CPU.
struct Inversion {
  bool applied = false;  ///< SCHED_FIFO and the pinning were permitted
  std::int64_t high_acquired_ns = 0;
  std::int64_t mid_done_ns = 0;
};

constexpr std::int64_t kLowWorkNs = 40'000'000;
constexpr std::int64_t kMidSpinNs = 150'000'000;
constexpr std::int64_t kSettleNs = 10'000'000;

void spin_until(std::int64_t t_ns) {
  while (monotonic_now_ns() < t_ns) {
  }
}

/// Runs the scenario on `core` from a controller thread pinned to `other_core`. Threads are
/// made SCHED_FIFO before they move to `core` (a SCHED_OTHER thread could not get onto a
/// CPU a FIFO thread is spinning on).
template <class Mutex>
Inversion run_inversion(int core, int other_core) {
  Inversion out;
  RtThread controller;
  const bool started = controller.start(ThreadSpec{"mer_pi_ctl", other_core, 0}, [&] {
    Mutex m;
    std::atomic<int> applied{0};
    std::atomic<bool> low_locked{false};
    std::atomic<bool> high_ready{false};
    std::atomic<std::int64_t> high_acquired{0};
    std::atomic<std::int64_t> mid_done{0};
    // Threads inherit the controller's affinity: move the calling (already FIFO) thread
    // to `core` directly.
    auto pin = [&] {
      cpu_set_t one;
      CPU_ZERO(&one);
      CPU_SET(core, &one);
      if (sched_setaffinity(0, sizeof(one), &one) == 0) applied.fetch_add(1);
    };
    RtThread low;
    RtThread high;
    RtThread mid;
    (void)low.start(ThreadSpec{"mer_pi_low", -1, 10}, [&] {
      pin();
      m.lock();
      const std::int64_t t0 = monotonic_now_ns();
      low_locked.store(true);
      spin_until(t0 + kLowWorkNs);  // wall time: stalls while preempted
      m.unlock();
    });
    while (!low_locked.load()) std::this_thread::yield();
    (void)high.start(ThreadSpec{"mer_pi_high", -1, 30}, [&] {
      pin();
      high_ready.store(true);
      m.lock();  // blocks: low owns it
      high_acquired.store(monotonic_now_ns());
      m.unlock();
    });
    while (!high_ready.load()) std::this_thread::yield();
    spin_until(monotonic_now_ns() + kSettleNs);  // high is asleep in lock()
    (void)mid.start(ThreadSpec{"mer_pi_mid", -1, 20}, [&] {
      pin();
      spin_until(monotonic_now_ns() + kMidSpinNs);
      mid_done.store(monotonic_now_ns());
    });
    low.join();
    high.join();
    mid.join();
    out.applied = applied.load() == 3 && low.report().priority_applied &&
                  high.report().priority_applied && mid.report().priority_applied;
    out.high_acquired_ns = high_acquired.load();
    out.mid_done_ns = mid_done.load();
  });
  if (!started) return out;
  controller.join();
  return out;
}

TEST(PiMutex, BoundsPriorityInversion) {
  cpu_set_t set;
  CPU_ZERO(&set);
  ASSERT_EQ(sched_getaffinity(0, sizeof(set), &set), 0);
  std::vector<int> cpus;
  for (int c = 0; c < CPU_SETSIZE; ++c) {
    if (CPU_ISSET(c, &set)) cpus.push_back(c);
  }
  if (cpus.size() < 2) GTEST_SKIP() << "needs two CPUs";
  const int core = cpus.back();
  const int other = cpus.front();

  const Inversion pi = run_inversion<PiMutex>(core, other);
  if (!pi.applied) GTEST_SKIP() << "SCHED_FIFO or CPU pinning not permitted here";
  // Inherited priority: low runs at high's priority while high waits, so mid cannot
  // preempt it; high gets the mutex after low's work, long before mid's spin ends.
  EXPECT_LT(pi.high_acquired_ns, pi.mid_done_ns);

  // The same scenario with a plain mutex shows the inversion the test detects: mid
  // preempts low, and high waits for all of mid's spin.
  const Inversion plain = run_inversion<std::mutex>(core, other);
  ASSERT_TRUE(plain.applied);
  EXPECT_GT(plain.high_acquired_ns, plain.mid_done_ns);
}

}  // namespace
}  // namespace mer::platform
