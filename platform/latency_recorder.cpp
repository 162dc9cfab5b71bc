#include "platform/latency_recorder.h"

#include <algorithm>
#include <array>
#include <atomic>
#include <bit>
#include <limits>

namespace mer::platform {

namespace {

constexpr int kSubBits = 5;                       // 32 sub-bins per octave
constexpr std::uint64_t kSub = 1ULL << kSubBits;  // values below this are exact
constexpr int kMaxExponent = 36;                  // top octave [2^36, 2^37) ns
constexpr std::size_t kBins = kSub + (kMaxExponent - kSubBits + 1) * kSub;  // 1056
constexpr double kNsPerMs = 1e6;

constexpr std::size_t bin_of(std::uint64_t v) noexcept {
  if (v < kSub) {
    return static_cast<std::size_t>(v);
  }
  const int e = std::bit_width(v) - 1;  // >= kSubBits
  if (e > kMaxExponent) {
    return kBins - 1;
  }
  const std::uint64_t sub = (v >> (e - kSubBits)) & (kSub - 1);
  return static_cast<std::size_t>(kSub + static_cast<std::uint64_t>(e - kSubBits) * kSub + sub);
}

struct BinRange {
  double lower;
  double width;
};

constexpr BinRange bin_range(std::size_t b) noexcept {
  if (b < kSub) {
    return {static_cast<double>(b), 1.0};
  }
  const std::size_t e = (b - kSub) / kSub + kSubBits;
  const std::uint64_t sub = (b - kSub) % kSub;
  const std::uint64_t shift = e - kSubBits;
  return {static_cast<double>((kSub + sub) << shift), static_cast<double>(1ULL << shift)};
}

static_assert(bin_of(31) == 31 && bin_of(32) == 32 && bin_of(63) == 63 && bin_of(64) == 64);
static_assert(bin_of(65) == 64 && bin_of(66) == 65);
static_assert(bin_of((1ULL << 37) - 1) == kBins - 1 && bin_of(1ULL << 40) == kBins - 1);
static_assert(bin_range(64).lower == 64.0 && bin_range(64).width == 2.0);

// Single-writer increment: a relaxed load + store, no lock-prefixed RMW.
template <typename A, typename V>
inline void add_relaxed(A& a, V v) noexcept {
  a.store(a.load(std::memory_order_relaxed) + v, std::memory_order_relaxed);
}

}  // namespace

struct LatencyRecorder::State {
  explicit State(std::size_t trace_cap)
      : trace(trace_cap > 0 ? std::make_unique<TraceSample[]>(trace_cap) : nullptr),
        trace_capacity(trace_cap) {}

  std::atomic<std::uint64_t> count{0};
  std::atomic<std::uint64_t> overruns{0};
  std::atomic<std::int64_t> sum_ns{0};
  std::atomic<std::int64_t> min_ns{std::numeric_limits<std::int64_t>::max()};
  std::atomic<std::int64_t> max_ns{0};
  std::array<std::atomic<std::uint64_t>, kBins> bins{};
  std::unique_ptr<TraceSample[]> trace;
  std::size_t trace_capacity;
};

LatencyRecorder::LatencyRecorder(std::string_view name, std::int64_t budget_ns,
                                 std::size_t trace_capacity)
    : name_(name), budget_ns_(budget_ns), state_(std::make_unique<State>(trace_capacity)) {}

LatencyRecorder::LatencyRecorder(LatencyRecorder&&) noexcept = default;
LatencyRecorder& LatencyRecorder::operator=(LatencyRecorder&&) noexcept = default;
LatencyRecorder::~LatencyRecorder() = default;

void LatencyRecorder::record(std::uint64_t seq, std::int64_t start_ns,
                             std::int64_t duration_ns) noexcept {
  State& s = *state_;
  const std::int64_t d = duration_ns > 0 ? duration_ns : 0;
  const std::uint64_t n = s.count.load(std::memory_order_relaxed);
  if (s.trace_capacity > 0) {
    s.trace[n % s.trace_capacity] = TraceSample{seq, start_ns, d};
  }
  add_relaxed(s.bins[bin_of(static_cast<std::uint64_t>(d))], std::uint64_t{1});
  add_relaxed(s.sum_ns, d);
  if (d < s.min_ns.load(std::memory_order_relaxed)) {
    s.min_ns.store(d, std::memory_order_relaxed);
  }
  if (d > s.max_ns.load(std::memory_order_relaxed)) {
    s.max_ns.store(d, std::memory_order_relaxed);
  }
  if (budget_ns_ > 0 && d > budget_ns_) {
    add_relaxed(s.overruns, std::uint64_t{1});
  }
  // Count last, release: a reader that sees count n sees the bins of those n samples.
  s.count.store(n + 1, std::memory_order_release);
}

double LatencyRecorder::percentile_ms(double q) const noexcept {
  const State& s = *state_;
  const std::uint64_t n = s.count.load(std::memory_order_acquire);
  if (n == 0) {
    return 0.0;
  }
  q = std::clamp(q, 0.0, 1.0);
  const double lo = static_cast<double>(s.min_ns.load(std::memory_order_relaxed));
  const double hi = static_cast<double>(s.max_ns.load(std::memory_order_relaxed));
  const double rank = q * static_cast<double>(n);
  double cum = 0.0;
  for (std::size_t b = 0; b < kBins; ++b) {
    const double c = static_cast<double>(s.bins[b].load(std::memory_order_relaxed));
    if (c == 0.0) {
      continue;
    }
    if (cum + c >= rank) {
      BinRange r = bin_range(b);
      if (b == kBins - 1 && hi > r.lower + r.width) {
        r.width = hi - r.lower;  // overflow bin: extends up to the exact max
      }
      const double v = r.lower + r.width * ((rank - cum) / c);
      return std::clamp(v, lo, hi) / kNsPerMs;
    }
    cum += c;
  }
  return hi / kNsPerMs;  // live reader saw count ahead of the bins
}

double LatencyRecorder::max_ms() const noexcept {
  return count() == 0
             ? 0.0
             : static_cast<double>(state_->max_ns.load(std::memory_order_relaxed)) / kNsPerMs;
}

double LatencyRecorder::min_ms() const noexcept {
  return count() == 0
             ? 0.0
             : static_cast<double>(state_->min_ns.load(std::memory_order_relaxed)) / kNsPerMs;
}

double LatencyRecorder::mean_ms() const noexcept {
  const std::uint64_t n = count();
  return n == 0 ? 0.0
                : static_cast<double>(state_->sum_ns.load(std::memory_order_relaxed)) /
                      static_cast<double>(n) / kNsPerMs;
}

std::uint64_t LatencyRecorder::count() const noexcept {
  return state_->count.load(std::memory_order_acquire);
}

std::uint64_t LatencyRecorder::overruns() const noexcept {
  return state_->overruns.load(std::memory_order_relaxed);
}

std::size_t LatencyRecorder::trace_capacity() const noexcept {
  return state_->trace_capacity;
}

void LatencyRecorder::copy_trace(std::vector<TraceSample>& out) const {
  const State& s = *state_;
  out.clear();
  const std::uint64_t n = s.count.load(std::memory_order_acquire);
  if (s.trace_capacity == 0 || n == 0) {
    return;
  }
  const std::uint64_t kept = std::min<std::uint64_t>(n, s.trace_capacity);
  out.reserve(kept);
  for (std::uint64_t i = n - kept; i < n; ++i) {
    out.push_back(s.trace[i % s.trace_capacity]);
  }
}

void LatencyRecorder::reset() noexcept {
  State& s = *state_;
  s.count.store(0, std::memory_order_relaxed);
  s.overruns.store(0, std::memory_order_relaxed);
  s.sum_ns.store(0, std::memory_order_relaxed);
  s.min_ns.store(std::numeric_limits<std::int64_t>::max(), std::memory_order_relaxed);
  s.max_ns.store(0, std::memory_order_relaxed);
  for (auto& b : s.bins) {
    b.store(0, std::memory_order_relaxed);
  }
}

}  // namespace mer::platform
