#pragma once

#include <atomic>
#include <cstdarg>
#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <memory>
#include <string_view>

#include "platform/cache_line.h"
#include "platform/notifier.h"
#include "platform/rt_thread.h"

namespace mer::platform {

/// Severity of a log record.
enum class LogLevel : std::uint8_t { kDebug, kInfo, kWarn, kError };

/// One-letter tag of a level: 'D', 'I', 'W', 'E'.
char log_level_letter(LogLevel level) noexcept;

/// Bytes for the thread name in a record (15 characters + terminator, the kernel's limit).
inline constexpr std::size_t kLogThreadNameSize = 16;
/// Bytes for the formatted text in a record (longer messages are truncated).
inline constexpr std::size_t kLogTextSize = 200;

/// One fixed-size log record (no heap: the text is formatted in place).
struct LogRecord {
  /// monotonic_now_ns() when the record was logged.
  std::int64_t t_ns;
  /// Severity.
  LogLevel level;
  /// Name of the logging thread (set_thread_log_name()), NUL-terminated.
  char thread[kLogThreadNameSize];
  /// Formatted message, NUL-terminated, truncated to kLogTextSize - 1 characters.
  char text[kLogTextSize];
};

/// Sets the calling thread's name used in log records (truncated to 15 chars). RtThread
/// calls it with the ThreadSpec name; threads that never call it log as "main".
void set_thread_log_name(std::string_view name) noexcept;

/// The calling thread's log name (NUL-terminated, at most 15 chars).
const char* thread_log_name() noexcept;

/// Lock-free bounded log ring: any number of producer threads, one consumer (drain() also
/// tolerates several consumers). A Vyukov bounded MPMC queue of fixed-size records: a
/// producer claims a cell with one CAS, formats into it with vsnprintf (no heap for
/// ordinary formats) and publishes it with a release store of the cell's sequence number.
/// When the ring is full the record is dropped and counted; logging never blocks.
class LogRing {
 public:
  /// Allocates `capacity_pow2` records (the only allocation). Throws std::invalid_argument
  /// unless capacity_pow2 is a power of two >= 2.
  explicit LogRing(std::size_t capacity_pow2);
  LogRing(const LogRing&) = delete;
  LogRing& operator=(const LogRing&) = delete;

  /// Formats a record (printf syntax, truncated to kLogTextSize - 1 chars) and enqueues it.
  /// Returns false (and counts a drop) when the ring is full. Wait-free apart from the
  /// claim CAS; safe on real-time threads.
  bool try_log(LogLevel level, const char* fmt, ...) noexcept __attribute__((format(printf, 3, 4)));

  /// va_list variant of try_log().
  bool try_logv(LogLevel level, const char* fmt, std::va_list args) noexcept
      __attribute__((format(printf, 3, 0)));

  /// Consumer: pops the records present (at most capacity() per call, so a flood of
  /// producers can't keep it here forever) and calls `sink(const LogRecord&)` on each,
  /// oldest first. Returns the number of records popped.
  template <class F>
  std::size_t drain(F&& sink) {
    std::size_t n = 0;
    for (; n < capacity(); ++n) {
      std::size_t pos = dequeue_pos_.load(std::memory_order_relaxed);
      Cell* cell = nullptr;
      for (;;) {
        cell = &cells_[pos & mask_];
        const std::size_t seq = cell->seq.load(std::memory_order_acquire);
        const auto dif = static_cast<std::ptrdiff_t>(seq) - static_cast<std::ptrdiff_t>(pos + 1);
        if (dif == 0) {
          if (dequeue_pos_.compare_exchange_weak(pos, pos + 1, std::memory_order_relaxed)) {
            break;
          }
        } else if (dif < 0) {
          return n;  // empty (or the next record is still being written)
        } else {
          pos = dequeue_pos_.load(std::memory_order_relaxed);
        }
      }
      sink(static_cast<const LogRecord&>(cell->rec));
      cell->seq.store(pos + mask_ + 1, std::memory_order_release);
    }
    return n;
  }

  /// Number of records dropped because the ring was full.
  std::uint64_t dropped() const noexcept { return dropped_.load(std::memory_order_relaxed); }

  /// Number of records the ring holds.
  std::size_t capacity() const noexcept { return mask_ + 1; }

 private:
  struct Cell {
    std::atomic<std::size_t> seq{0};
    LogRecord rec{};
  };

  std::unique_ptr<Cell[]> cells_;
  std::size_t mask_;
  alignas(kCacheLine) std::atomic<std::size_t> enqueue_pos_{0};
  alignas(kCacheLine) std::atomic<std::size_t> dequeue_pos_{0};
  alignas(kCacheLine) std::atomic<std::uint64_t> dropped_{0};
};

/// Formats `rec` as one line "<seconds>.<micros> <L> [<thread>] <text>\n" into `buf`
/// (truncated to `size`). Returns the number of characters written (excluding the NUL).
std::size_t format_log_record(const LogRecord& rec, char* buf, std::size_t size) noexcept;

/// Background writer: a low-priority RtThread that drains a LogRing every `period_ms`
/// (and when stopped) into a FILE*, skipping records below `min_level`. When the ring has
/// dropped records since the last drain, it writes one line saying how many.
class LogDrain {
 public:
  /// Does not start anything; call start().
  explicit LogDrain(LogRing& ring, std::FILE* out = stderr, LogLevel min_level = LogLevel::kInfo,
                    std::int64_t period_ms = 20) noexcept;
  LogDrain(const LogDrain&) = delete;
  LogDrain& operator=(const LogDrain&) = delete;
  /// stop().
  ~LogDrain();

  /// Starts the drain thread with `spec` (normally the board table's `log` entry, priority 0).
  /// Returns false if already running or the thread could not be created.
  [[nodiscard]] bool start(const ThreadSpec& spec);

  /// Stops the thread and writes every record still in the ring before returning.
  /// Idempotent.
  void stop();

  /// Drains on the calling thread now (works whether or not the thread runs). Returns the
  /// number of records popped (including filtered-out ones).
  std::size_t drain_now();

  /// Number of records written to the FILE so far.
  std::uint64_t written() const noexcept { return written_.load(std::memory_order_relaxed); }

 private:
  void run();

  LogRing& ring_;
  std::FILE* out_;
  LogLevel min_level_;
  std::int64_t period_ns_;
  std::atomic<bool> stop_{false};
  std::atomic<std::uint64_t> written_{0};
  std::atomic<std::uint64_t> reported_drops_{0};
  Notifier wake_;
  RtThread thread_;
};

/// Process-wide default log ring (1024 records), a function-local static constructed on
/// first use: call it once at start-up before hot threads run so the construction (and
/// its allocation) is not on a real-time path.
LogRing& default_log();

/// Writes every record still in default_log() (at or above `min_level`) to stderr. For
/// programs and tests that run no LogDrain; call at exit.
void flush_default_log_to_stderr(LogLevel min_level = LogLevel::kDebug);

}  // namespace mer::platform

/// Logs a printf-formatted debug record to default_log() (dropped and counted if full).
#define MER_LOG_DEBUG(...) \
  static_cast<void>(       \
      ::mer::platform::default_log().try_log(::mer::platform::LogLevel::kDebug, __VA_ARGS__))
/// Logs a printf-formatted info record to default_log().
#define MER_LOG_INFO(...) \
  static_cast<void>(      \
      ::mer::platform::default_log().try_log(::mer::platform::LogLevel::kInfo, __VA_ARGS__))
/// Logs a printf-formatted warning record to default_log().
#define MER_LOG_WARN(...) \
  static_cast<void>(      \
      ::mer::platform::default_log().try_log(::mer::platform::LogLevel::kWarn, __VA_ARGS__))
/// Logs a printf-formatted error record to default_log().
#define MER_LOG_ERROR(...) \
  static_cast<void>(       \
      ::mer::platform::default_log().try_log(::mer::platform::LogLevel::kError, __VA_ARGS__))
