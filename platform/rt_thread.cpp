#include "platform/rt_thread.h"

#include <pthread.h>
#include <sched.h>
#include <system_error>

#include <algorithm>
#include <cerrno>
#include <cstring>
#include <future>
#include <utility>

#include "platform/log_ring.h"

namespace mer::platform {

namespace {

constexpr std::size_t kMaxThreadName = 15;  // kernel limit (16 with the terminator)

void append_reason(std::string& warning, const std::string& reason) {
  if (!warning.empty()) {
    warning += "; ";
  }
  warning += reason;
}

}  // namespace

ThreadStartReport apply_thread_spec(const ThreadSpec& spec) {
  ThreadStartReport report;
  report.started = true;

  // Name: the kernel truncates nothing itself, it rejects >15 chars with ERANGE.
  char name[kMaxThreadName + 1] = {};
  const std::size_t len = std::min(spec.name.size(), kMaxThreadName);
  std::memcpy(name, spec.name.data(), len);
  report.name_applied = len > 0 && ::pthread_setname_np(::pthread_self(), name) == 0;
  set_thread_log_name(std::string_view(name, len));

  if (spec.core >= 0) {
    report.affinity_requested = true;
    cpu_set_t allowed;
    CPU_ZERO(&allowed);
    const bool have_mask = ::sched_getaffinity(0, sizeof(allowed), &allowed) == 0;
    if (spec.core >= CPU_SETSIZE || (have_mask && !CPU_ISSET(spec.core, &allowed))) {
      const int n = have_mask ? CPU_COUNT(&allowed) : 0;
      append_reason(report.warning, "core " + std::to_string(spec.core) + " not available (" +
                                        std::to_string(n) +
                                        " CPUs in this process's set), not pinned");
    } else {
      cpu_set_t set;
      CPU_ZERO(&set);
      CPU_SET(spec.core, &set);
      const int err = ::pthread_setaffinity_np(::pthread_self(), sizeof(set), &set);
      if (err == 0) {
        report.affinity_applied = true;
      } else {
        append_reason(report.warning, "pinning to core " + std::to_string(spec.core) +
                                          " refused (" + std::strerror(err) + ")");
      }
    }
  }

  if (spec.priority > 0) {
    report.priority_requested = true;
    const int lo = ::sched_get_priority_min(SCHED_FIFO);
    const int hi = ::sched_get_priority_max(SCHED_FIFO);
    if (spec.priority < lo || spec.priority > hi) {
      append_reason(report.warning, "SCHED_FIFO priority " + std::to_string(spec.priority) +
                                        " outside " + std::to_string(lo) + ".." +
                                        std::to_string(hi));
    } else {
      sched_param param{};
      param.sched_priority = spec.priority;
      const int err = ::pthread_setschedparam(::pthread_self(), SCHED_FIFO, &param);
      if (err == 0) {
        report.priority_applied = true;
      } else {
        std::string reason =
            "SCHED_FIFO " + std::to_string(spec.priority) + " refused (" + std::strerror(err) + ")";
        if (err == EPERM) {
          reason += ": needs CAP_SYS_NICE or an rtprio limit";
        }
        append_reason(report.warning, reason);
      }
    }
  }

  if (!report.warning.empty()) {
    // One line per thread; the ring truncates at 200 chars, which this stays well under.
    MER_LOG_WARN("thread '%s': %s; running with normal scheduling", name, report.warning.c_str());
  }
  return report;
}

RtThread& RtThread::operator=(RtThread&& other) noexcept {
  if (this != &other) {
    join();
    thread_ = std::move(other.thread_);
    report_ = std::move(other.report_);
    name_ = std::move(other.name_);
  }
  return *this;
}

RtThread::~RtThread() {
  join();
}

bool RtThread::start(const ThreadSpec& spec, std::function<void()> body) {
  if (thread_.joinable()) {
    return false;
  }
  name_.assign(spec.name);
  report_ = ThreadStartReport{};
  std::promise<ThreadStartReport> applied;
  std::future<ThreadStartReport> applied_future = applied.get_future();
  // The spec's name view may dangle once start() returns: give the thread its own copy.
  try {
    thread_ = std::thread([spec_copy = spec, name_copy = name_, body = std::move(body),
                           applied = std::move(applied)]() mutable {
      ThreadSpec s = spec_copy;
      s.name = name_copy;
      applied.set_value(apply_thread_spec(s));
      body();
    });
  } catch (const std::system_error& e) {
    report_.warning = std::string("thread creation failed: ") + e.what();
    MER_LOG_ERROR("thread '%s': %s", name_.c_str(), report_.warning.c_str());
    return false;
  }
  report_ = applied_future.get();
  return true;
}

void RtThread::join() {
  if (thread_.joinable()) {
    thread_.join();
  }
}

}  // namespace mer::platform
