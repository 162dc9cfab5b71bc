#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>
#include <string>
#include <string_view>
#include <vector>

namespace mer::platform {

/// One traced stage execution.
struct TraceSample {
  /// Frame / item sequence number the stage processed.
  std::uint64_t seq;
  /// monotonic_now_ns() when the stage started.
  std::int64_t start_ns;
  /// How long it took, ns.
  std::int64_t duration_ns;
};

/// Latency statistics of one pipeline stage, recorded on the stage's own thread without
/// allocating or locking.
///
/// - Histogram: log-linear (HdrHistogram-style) over [0, 2^37 ns ~ 137 s]: exact below
///   32 ns, then 32 linear sub-bins per power of two, i.e. every bin spans at most 1/32 of
///   its lower edge (3.1 %); with linear interpolation inside the bin a percentile is within
///   ~2 % of the true sample quantile. Durations above 137 s land in the last bin (max stays
///   exact). 1056 bins, 8.4 KB.
/// - count, sum, min, max: exact.
/// - Overruns: samples with duration > budget_ns (none counted when budget_ns <= 0).
/// - Trace: the last `trace_capacity` samples, a ring allocated in the constructor.
///
/// Threading: record() has a single writer (the stage thread). All statistics are relaxed
/// atomics written with plain load+store (no lock prefix), so a monitor thread may read
/// count(), overruns(), max_ms(), percentile_ms() live and get a recent, approximately
/// consistent view. copy_trace() must only be called when the writer has stopped.
class LatencyRecorder {
 public:
  /// `name`: stage name for reports; `budget_ns`: per-execution budget (<= 0: none);
  /// `trace_capacity`: samples kept for the trace (0 disables the trace). Allocates here only.
  LatencyRecorder(std::string_view name, std::int64_t budget_ns, std::size_t trace_capacity = 1024);
  /// Movable (the statistics live on the heap); a moved-from recorder may only be destroyed
  /// or assigned to.
  LatencyRecorder(LatencyRecorder&&) noexcept;
  /// Move assignment.
  LatencyRecorder& operator=(LatencyRecorder&&) noexcept;
  LatencyRecorder(const LatencyRecorder&) = delete;
  LatencyRecorder& operator=(const LatencyRecorder&) = delete;
  /// Frees the histogram and trace.
  ~LatencyRecorder();

  /// Records one execution. Negative durations are recorded as 0. No allocation, no lock;
  /// single writer thread only.
  void record(std::uint64_t seq, std::int64_t start_ns, std::int64_t duration_ns) noexcept;

  /// Latency at quantile `q` (clamped to [0, 1]) in milliseconds: the histogram bin holding
  /// rank q * count, linearly interpolated inside the bin, clamped to the exact [min, max].
  /// 0 when nothing was recorded.
  double percentile_ms(double q) const noexcept;
  /// Largest recorded duration, ms (exact). 0 when empty.
  double max_ms() const noexcept;
  /// Smallest recorded duration, ms (exact). 0 when empty.
  double min_ms() const noexcept;
  /// Mean duration, ms (exact sum / count). 0 when empty.
  double mean_ms() const noexcept;
  /// Number of recorded executions.
  std::uint64_t count() const noexcept;
  /// Executions with duration > budget_ns() (0 when budget_ns() <= 0).
  std::uint64_t overruns() const noexcept;
  /// The budget given at construction, ns.
  std::int64_t budget_ns() const noexcept { return budget_ns_; }
  /// The stage name given at construction.
  std::string_view name() const noexcept { return name_; }
  /// Capacity of the trace ring.
  std::size_t trace_capacity() const noexcept;

  /// Replaces `out` with the traced samples, oldest first (at most trace_capacity()).
  /// Not real-time (may allocate); call after the writer thread stopped.
  void copy_trace(std::vector<TraceSample>& out) const;

  /// Clears all statistics and the trace. Not concurrent with record().
  void reset() noexcept;

 private:
  struct State;
  std::string name_;
  std::int64_t budget_ns_;
  std::unique_ptr<State> state_;
};

}  // namespace mer::platform
