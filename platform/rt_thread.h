#pragma once

#include <functional>
#include <string>
#include <string_view>
#include <thread>

namespace mer::platform {

/// How one thread should run: its name, the CPU it is pinned to and its real-time priority.
/// A plain constexpr-constructible aggregate, so thread tables can be `constexpr` data.
struct ThreadSpec {
  /// Thread name (shown by top/ps/gdb; truncated to 15 characters by the kernel).
  std::string_view name;
  /// CPU core to pin to; -1 = any core (no affinity).
  int core = -1;
  /// 0 = normal scheduling (SCHED_OTHER); 1..99 = SCHED_FIFO with this priority.
  int priority = 0;
};

/// What RtThread::start() managed to apply. Settings that could not be applied fall back to
/// normal scheduling and are described in `warning` (also logged once to default_log()).
struct ThreadStartReport {
  /// The thread was created and is running its body.
  bool started = false;
  /// pthread_setname_np succeeded.
  bool name_applied = false;
  /// spec.core >= 0 was asked for.
  bool affinity_requested = false;
  /// The thread is pinned to spec.core.
  bool affinity_applied = false;
  /// spec.priority > 0 was asked for.
  bool priority_requested = false;
  /// The thread runs SCHED_FIFO at spec.priority.
  bool priority_applied = false;
  /// Empty when everything requested was applied; otherwise the reason(s), one line.
  std::string warning;

  /// True when every requested setting was applied.
  bool fully_applied() const noexcept {
    return started && (!affinity_requested || affinity_applied) &&
           (!priority_requested || priority_applied);
  }
};

/// Move-only owner of one std::thread that runs with a ThreadSpec applied.
///
/// The new thread first sets its name (also used as the log-ring thread name), its CPU
/// affinity (if spec.core >= 0) and SCHED_FIFO priority (if spec.priority > 0), then runs
/// the body. A setting that is not permitted (EPERM without CAP_SYS_NICE, a core outside
/// the process's CPU set, a priority outside 1..99) is skipped with ONE warning line naming
/// the thread and the reason: it never fails the program. start() returns after the
/// settings were applied, so report() is complete when start() returns.
///
/// The destructor joins (like std::jthread, minus the stop token): signal the body to stop
/// before destroying the owner.
class RtThread {
 public:
  /// No thread.
  RtThread() = default;
  /// Starts a thread at once; check joinable()/report() for the outcome.
  RtThread(const ThreadSpec& spec, std::function<void()> body) {
    static_cast<void>(start(spec, std::move(body)));
  }
  RtThread(const RtThread&) = delete;
  RtThread& operator=(const RtThread&) = delete;
  /// Takes over `other`'s thread.
  RtThread(RtThread&& other) noexcept = default;
  /// Joins the current thread (if any), then takes over `other`'s.
  RtThread& operator=(RtThread&& other) noexcept;
  /// Joins the thread if it is still joinable.
  ~RtThread();

  /// Starts the thread: applies `spec`, then runs `body`. Returns false only when the
  /// thread could not be created or this object already owns a running thread; fallbacks
  /// of affinity/priority still return true (see report()). Allocates: call at start-up.
  [[nodiscard]] bool start(const ThreadSpec& spec, std::function<void()> body);

  /// Waits for the body to return. No-op when not joinable.
  void join();

  /// True while a started thread has not been joined.
  bool joinable() const noexcept { return thread_.joinable(); }

  /// What start() applied (default-constructed before start()).
  const ThreadStartReport& report() const noexcept { return report_; }

  /// The name from the spec (untruncated).
  const std::string& name() const noexcept { return name_; }

 private:
  std::thread thread_;
  ThreadStartReport report_;
  std::string name_;
};

/// Applies `spec` to the *calling* thread (name, affinity, priority) with the same
/// fallback-and-warn rules as RtThread. Used by RtThread; useful for the main thread.
ThreadStartReport apply_thread_spec(const ThreadSpec& spec);

}  // namespace mer::platform
