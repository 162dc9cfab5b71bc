#include "platform/log_ring.h"

#include <algorithm>
#include <cinttypes>
#include <cstring>
#include <stdexcept>

#include "platform/clock.h"

namespace mer::platform {

namespace {

// Constant-initialized POD: no TLS guard, no allocation on first use in a thread.
thread_local char t_log_name[kLogThreadNameSize] = "main";

constexpr std::size_t kDefaultLogCapacity = 1024;

}  // namespace

char log_level_letter(LogLevel level) noexcept {
  switch (level) {
    case LogLevel::kDebug:
      return 'D';
    case LogLevel::kInfo:
      return 'I';
    case LogLevel::kWarn:
      return 'W';
    case LogLevel::kError:
      return 'E';
  }
  return '?';
}

void set_thread_log_name(std::string_view name) noexcept {
  const std::size_t n = std::min(name.size(), kLogThreadNameSize - 1);
  std::memcpy(t_log_name, name.data(), n);
  t_log_name[n] = '\0';
}

const char* thread_log_name() noexcept {
  return t_log_name;
}

LogRing::LogRing(std::size_t capacity_pow2) : mask_(capacity_pow2 - 1) {
  if (capacity_pow2 < 2 || (capacity_pow2 & (capacity_pow2 - 1)) != 0) {
    throw std::invalid_argument("LogRing: capacity must be a power of two >= 2");
  }
  cells_ = std::make_unique<Cell[]>(capacity_pow2);
  for (std::size_t i = 0; i < capacity_pow2; ++i) {
    cells_[i].seq.store(i, std::memory_order_relaxed);
  }
}

bool LogRing::try_log(LogLevel level, const char* fmt, ...) noexcept {
  std::va_list args;
  va_start(args, fmt);
  const bool ok = try_logv(level, fmt, args);
  va_end(args);
  return ok;
}

bool LogRing::try_logv(LogLevel level, const char* fmt, std::va_list args) noexcept {
  std::size_t pos = enqueue_pos_.load(std::memory_order_relaxed);
  Cell* cell = nullptr;
  for (;;) {
    cell = &cells_[pos & mask_];
    const std::size_t seq = cell->seq.load(std::memory_order_acquire);
    const auto dif = static_cast<std::ptrdiff_t>(seq) - static_cast<std::ptrdiff_t>(pos);
    if (dif == 0) {
      if (enqueue_pos_.compare_exchange_weak(pos, pos + 1, std::memory_order_relaxed)) {
        break;
      }
    } else if (dif < 0) {
      dropped_.fetch_add(1, std::memory_order_relaxed);  // full: never block the caller
      return false;
    } else {
      pos = enqueue_pos_.load(std::memory_order_relaxed);
    }
  }
  // The cell is ours until the release store below publishes it to the consumer.
  LogRecord& rec = cell->rec;
  rec.t_ns = monotonic_now_ns();
  rec.level = level;
  std::memcpy(rec.thread, t_log_name, kLogThreadNameSize);
  if (std::vsnprintf(rec.text, kLogTextSize, fmt, args) < 0) {
    std::strncpy(rec.text, "<log format error>", kLogTextSize - 1);
    rec.text[kLogTextSize - 1] = '\0';
  }
  cell->seq.store(pos + 1, std::memory_order_release);
  return true;
}

std::size_t format_log_record(const LogRecord& rec, char* buf, std::size_t size) noexcept {
  if (size == 0) {
    return 0;
  }
  const std::int64_t sec = rec.t_ns / 1'000'000'000LL;
  const std::int64_t usec = (rec.t_ns % 1'000'000'000LL) / 1000;
  const int n = std::snprintf(buf, size, "%" PRId64 ".%06" PRId64 " %c [%s] %s\n", sec, usec,
                              log_level_letter(rec.level), rec.thread, rec.text);
  if (n < 0) {
    buf[0] = '\0';
    return 0;
  }
  if (static_cast<std::size_t>(n) >= size) {
    // Truncated: keep the line terminated.
    if (size >= 2) {
      buf[size - 2] = '\n';
    }
    return size - 1;
  }
  return static_cast<std::size_t>(n);
}

LogDrain::LogDrain(LogRing& ring, std::FILE* out, LogLevel min_level,
                   std::int64_t period_ms) noexcept
    : ring_(ring),
      out_(out != nullptr ? out : stderr),
      min_level_(min_level),
      period_ns_((period_ms > 0 ? period_ms : 1) * 1'000'000LL) {}

LogDrain::~LogDrain() {
  stop();
}

bool LogDrain::start(const ThreadSpec& spec) {
  if (thread_.joinable()) {
    return false;
  }
  stop_.store(false, std::memory_order_release);
  return thread_.start(spec, [this] { run(); });
}

void LogDrain::stop() {
  if (thread_.joinable()) {
    stop_.store(true, std::memory_order_release);
    wake_.notify_all();
    thread_.join();
  }
  // Records logged after the thread's last pass (or with no thread at all). Bounded: a
  // pass pops at most capacity() records, and only a full pass asks for another.
  std::size_t n = 0;
  do {
    n = drain_now();
  } while (n == ring_.capacity());
  std::fflush(out_);
}

void LogDrain::run() {
  while (!stop_.load(std::memory_order_acquire)) {
    const std::uint32_t seen = wake_.epoch();
    drain_now();
    std::fflush(out_);
    if (stop_.load(std::memory_order_acquire)) {
      break;
    }
    wake_.wait_for(seen, period_ns_);
  }
}

std::size_t LogDrain::drain_now() {
  char line[kLogTextSize + kLogThreadNameSize + 48];
  const std::size_t n = ring_.drain([&](const LogRecord& rec) {
    if (rec.level < min_level_) {
      return;
    }
    const std::size_t len = format_log_record(rec, line, sizeof(line));
    std::fwrite(line, 1, len, out_);
    written_.fetch_add(1, std::memory_order_relaxed);
  });
  const std::uint64_t drops = ring_.dropped();
  const std::uint64_t reported = reported_drops_.exchange(drops, std::memory_order_relaxed);
  if (drops > reported) {
    std::fprintf(out_, "log: %" PRIu64 " records dropped (ring full)\n", drops - reported);
  }
  return n;
}

LogRing& default_log() {
  static LogRing ring(kDefaultLogCapacity);
  return ring;
}

void flush_default_log_to_stderr(LogLevel min_level) {
  LogDrain drain(default_log(), stderr, min_level);
  drain.stop();  // no thread: just drains everything on this thread
}

}  // namespace mer::platform
